"""Command line interface ``bfdrift``.

Subcommands
-----------
``bfdrift template build --out FILE [--config FILE]``
    Compute a template from the electrostatic model (progress bar on stderr).
``bfdrift template summary [FILE] [--json]``
    Key numbers: A00, A01, A10, A11 (px^2, pixel at (di, dj) = (serial,
    parallel) offset), ratio_01_10 = dlnA01/dlnA10, area_sum_error (sum of
    all areas minus N^2), aggressor charge.
``bfdrift template plot [FILE] --out PNG``
    Distorted boundaries (exaggerated) and the area map.
``bfdrift template import-galsim NAME --out FILE``
    Convert a GalSim sensor file (e.g. lsst_itl_50_8) to a template file.
``bfdrift ptc FILES...|DIR [--max-lag L] [--json]``
    Photon transfer analysis (Astier et al. 2019): either one two-column text
    file (mean ADU, variance ADU^2; exponential C00 fit: gain, a00) or FITS
    flats paired by EXPTIME as ``calibrate`` reads them (covariances by FFT,
    full model: gain and a_ij; the pairs used and dropped are listed).
``bfdrift flat-sim [--template FILE] [--n-images N] [--steps K] ... [--json]``
    Flat-field simulation with moving boundaries: per-step covariances by the
    paper's all-pairs estimator and LSST's per-pair estimator.
``bfdrift star-sim [--psf gaussian|moffat|kolmogorov] [--fwhm F] [--flux N] ... [--json]``
    Star simulation with GalSim photons and moving boundaries: per-step
    central counts, size, ellipticity and orientation with and without BF.
``bfdrift correct IN.fits OUT.fits [--config FILE] [--method M] [--json]``
    BrighterFatterDriftTask on a FITS image; several inputs with
    ``--out-dir`` (in turn, or on a dask cluster with ``--scheduler local`` or
    ``--scheduler ADDRESS``; progress bar; a failed file is reported and the
    others go on).
``bfdrift validate-stars [--n-stars N] [--psf moffat|kolmogorov] [--json]``
    Sky-like stars drawn by galsim.SiliconSensor (paired BF-free twins):
    size and ellipticity slopes against flux for uncorrected, coulton18,
    astier23 and drift, with errors. Defaults: the sensor's template imported
    with ``--match transfers``, about 1000 GalSim boundary updates per
    exposure (``--updates 1000 --min-nrecalc 100``; converged, see
    ``benchmarks/correction/probe_validation_cadence_results.txt``).
``bfdrift reproduce [--json] [--out DIR] [--quick]``
    The paper's numbers next to the calibrated model's (A00..A11, ratio,
    radial slopes, neighbour recovery, fall-off), the V_BSS ratio scan, and
    figures in DIR.
``bfdrift validate-sky IMAGE.fits [--json] [--plot PNG] [--gain G] [--route R]``
    Star catalogue of a sky image (photutils, adaptive moments) and robust
    size- and ellipticity-flux slopes at fixed position, before and after
    the catalogue-level and/or pixel-level BF correction, with a verdict
    (``residual_bf_detected``) and optional figures.
``bfdrift diagnose INPUT [--json] [--report DIR] [--basis FILE] [--no-template-change]``
    Where the electrostatic model is wrong and which effect explains it:
    INPUT is an a_ij table, a PTC text file or a directory of flat pairs;
    chi2/dof, rms and largest residual lags before and after each added
    effect, and what an added effect changes in the calibrated template and
    in star corrections (see ``docs/calibration.rst``).
``bfdrift maps [IMAGE] [--template FILE] [--out FILE] [--plot PNG] [--json]``
    Final pixel geometry (area, centroid shift, ellipticity maps) of an image
    in electrons; with no IMAGE, the bundled sample star. This is the quick
    start's main job.

Build config files are pex_config override files of
:class:`~lsst_bfdrift.templates.build_config.TemplateBuildConfig`, or JSON/TOML
with up to two tables: ``sensor`` (keys of
:class:`~lsst_bfdrift.physics.sensor.SensorParameters`) and ``template`` (keys of
:class:`~lsst_bfdrift.templates.template.TemplateSettings`). Unknown keys are errors.
"""

import argparse
import os
import sys

import numpy as np

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.images.exposure import read_image
from lsst_bfdrift.utils.io import atomic_output, check_output, data_path
from lsst_bfdrift.simulation.stars import make_psf
from lsst_bfdrift.cli._common import (_check_outputs, _emit, _load_template, _print_json,
                                      _remove_stale_outputs, _save_and_report, _save_plot,
                                      _sigterm_raises, _template_input)
from lsst_bfdrift.cli.analysis import (_cmd_calibrate, _cmd_diagnose, _cmd_ptc,
                                       _cmd_reproduce, _cmd_validate_sky, _cmd_validate_stars)
from lsst_bfdrift.utils.errors import (BfdriftError, ComputationError, FieldValidationError,
                                       FitError, InputError, OutputExistsError)

__all__ = ["main", "exit_code", "EXIT_OK", "EXIT_OTHER", "EXIT_INPUT", "EXIT_EXISTS",
           "EXIT_FIT", "read_config", "sample_image_path", "make_psf", "read_image"]


def read_config(path):
    """Read a build configuration (:func:`~lsst_bfdrift.templates.build_config.read_build_config`).

    Returns
    -------
    params : SensorParameters
    settings : TemplateSettings
    """
    from lsst_bfdrift.templates.build_config import read_build_config
    return read_build_config(path)


def sample_image_path():
    """Path of the bundled sample image (a bright star on sky, electrons)."""
    return data_path("sample_star.fits")


def _cmd_template_build(args):
    from lsst_bfdrift.templates.template import build_template
    params, settings = read_config(args.config)
    overrides = {k: v for k, v in (("size", args.size), ("aggressor_charge", args.charge),
                                   ("edge_samples", args.samples), ("tol", args.tol),
                                   ("workers", args.workers)) if v is not None}
    if overrides:
        settings = type(settings).from_dict({**settings.to_dict(), **overrides})
    _check_outputs(args, [args.config], {"--out": args.out})
    return _save_and_report(build_template(params, settings, progress=not args.quiet), args)


def _cmd_template_summary(args):
    tpl = _load_template(args.file)
    return _emit(tpl.summary(), args.json)


def _cmd_template_plot(args):
    from lsst_bfdrift.templates.plots import plot_template
    _check_outputs(args, [_template_input(args.file)], {"--out": args.out})
    tpl = _load_template(args.file)
    _save_plot(plot_template(tpl, exaggerate=args.exaggerate, half_width=args.half_width),
               args.out)
    print(f"wrote {args.out}")
    return 0


def _cmd_template_export(args):
    from lsst_bfdrift.templates.galsim_export import export_galsim_sensor
    tpl = _load_template(args.file)
    cfg, dat = export_galsim_sensor(tpl, args.prefix, num_vertices=args.vertices,
                                    overwrite=args.overwrite)
    return _emit({"cfg": os.path.abspath(cfg), "dat": os.path.abspath(dat),
                  "pixels": f"{tpl.size} x {tpl.size}",
                  "num_vertices": tpl.edge_samples if args.vertices is None else args.vertices,
                  "charge": tpl.charge}, args.json)


def _cmd_template_import(args):
    _check_outputs(args, [], {"--out": args.out})
    return _save_and_report(import_galsim_sensor(args.name), args)


def _write_maps(path, maps, header):
    from astropy.io import fits
    hdus = [fits.PrimaryHDU(header=header)]
    for name, arr in maps.as_dict().items():
        hdus.append(fits.ImageHDU(arr.astype(np.float64), name=name.upper()))
    with atomic_output(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True, checksum=True)


def _cmd_maps(args):
    from lsst_bfdrift.utils.progress import ProgressBar
    from lsst_bfdrift.geometry.superpose import moment_maps
    path = args.image or sample_image_path()
    _check_outputs(args, [path, _template_input(args.template)],
                   {"--out": args.out, "--plot": args.plot})
    # the package's one unit, gain and saturation rule (as bfdrift correct): --gain means ADU
    electrons = to_electrons(path, gain=args.gain, gain_name="--gain")
    image, bad, header, gain = electrons.data, electrons.bad, electrons.meta, electrons.gain
    tpl = _load_template(args.template)
    with ProgressBar(image.shape[0], "maps", enabled=not args.quiet) as bar:
        samples = None if args.samples is None else min(args.samples, tpl.edge_samples)
        maps = moment_maps(tpl, image, mask=bad, workers=2, progress=bar, samples=samples)
    summary = {
        "image": os.path.abspath(path), "shape": list(image.shape),
        "template": args.template or "default",
        "template_charge": tpl.charge,
        "edge_samples": tpl.edge_samples if samples is None else samples,
        "masked_pixels": int(bad.sum()), "gain": gain,
        "max_charge": float(np.nanmax(np.where(bad, np.nan, image))),
        "area_min": float(maps.area.min()), "area_max": float(maps.area.max()),
        "area_sum_minus_npix": float(maps.area.sum() - maps.area.size),
        "max_abs_shift": float(max(np.abs(maps.dx).max(), np.abs(maps.dy).max())),
        "max_abs_e": float(np.hypot(maps.e1, maps.e2).max()),
    }
    if args.out:
        header["BFTEMPL"] = (str(args.template or "default")[-60:], "lsst_bfdrift template")
        header["BFGSAMP"] = (summary["edge_samples"], "edge samples of the geometry")
        _write_maps(args.out, maps, header)
        summary["out"] = os.path.abspath(args.out)
    if args.plot:
        from lsst_bfdrift.geometry.plots import plot_moment_maps
        _save_plot(plot_moment_maps(maps, image=np.where(bad, np.nan, image),
                                    title=os.path.basename(path)), args.plot, summary)
    return _emit(summary, args.json, 20)


def _cmd_flat_sim(args):
    from lsst_bfdrift.simulation.flats import simulate_flats
    _check_outputs(args, [_template_input(args.template)],
                   {"--out": args.out, "--plot": args.plot})
    tpl = _load_template(args.template)
    if args.responsivity is not None:
        # same displacements, attributed to the charge giving dlnA00/Q = responsivity
        from lsst_bfdrift.simulation.flats import with_responsivity
        tpl = with_responsivity(tpl, args.responsivity)
    tab = simulate_flats(tpl, n_images=args.n_images, shape=(args.size, args.size),
                         step=args.step, n_steps=args.steps, max_lag=args.max_lag,
                         seed=args.seed, progress=not args.quiet)
    if args.out:
        with atomic_output(args.out) as tmp:
            tab.write(tmp, format="ascii.ecsv", overwrite=True)
    if args.plot:
        from lsst_bfdrift.simulation.plots import plot_flat_simulation
        _save_plot(plot_flat_simulation(tab, tpl), args.plot)
    steps = [{"mu": float(r["mu"]),
              **{f"C{i}{j}_paper": float(r["paper"][i, j] * r["mu"]) for i in range(2)
                 for j in range(2)},
              **{f"C{i}{j}_pairs": float(r["pairs"][i, j]) for i in range(2) for j in range(2)},
              **{f"C{i}{j}_pairs_err": float(r["pairs_err"][i, j]) for i in range(2)
                 for j in range(2)}} for r in tab]
    out = {"template_charge": tpl.charge, "n_images": args.n_images,
           "shape": [args.size, args.size], "step": args.step, "steps": steps,
           "units": "covariances in e^2, mean in e"}
    if args.json:
        _print_json(out)
    else:
        last = steps[-1]
        print(f"final mean {last['mu']:.1f} e: C00 {last['C00_paper']:.1f}, C01 "
              f"{last['C01_paper']:.2f}, C10 {last['C10_paper']:.2f} e^2 (all pairs)")
    return 0


def _cmd_star_sim(args):
    from lsst_bfdrift.simulation.stars import simulate_star
    _check_outputs(args, [_template_input(args.template)],
                   {"--out": args.out, "--plot": args.plot})
    tpl = _load_template(args.template)
    psf = make_psf(args.psf, args.fwhm, e=args.e, beta=args.beta)
    hist, final = simulate_star(tpl, psf, args.flux, stamp_size=args.stamp,
                                update_every=args.update_every, pixel_scale=args.pixel_scale,
                                center=(args.dx, args.dy), seed=args.seed,
                                progress=not args.quiet)
    if args.out:
        with atomic_output(args.out) as tmp:
            hist.write(tmp, format="ascii.ecsv", overwrite=True)
    if args.plot:
        from lsst_bfdrift.simulation.plots import plot_star_history
        _save_plot(plot_star_history(hist), args.plot)
    last = hist[-1]
    out = {"psf": args.psf, "fwhm_arcsec": args.fwhm, "flux": args.flux,
           "template_charge": tpl.charge, "lost": final["lost"],
           "T_growth": float(last["T"] / last["T_nominal"] - 1),
           "central_counts": float(last["central"]),
           "central_counts_square_pixels": float(final["nominal_image"][args.stamp // 2,
                                                                         args.stamp // 2]),
           "min_area": float(final["maps"].area.min()),
           "steps": [{k: float(r[k]) for k in hist.colnames} for r in hist]}
    if args.json:
        _print_json(out)
    else:
        print(f"T grew by {100 * out['T_growth']:.3f} % relative to square pixels; "
              f"central pixel {out['central_counts']:.0f} e "
              f"({out['central_counts_square_pixels']:.0f} with square pixels)")
    return 0


def _cmd_correct(args):
    from lsst_bfdrift.correction.batch import correct_files, output_pairs
    from lsst_bfdrift.correction.task import BrighterFatterDriftConfig
    from lsst_bfdrift.utils.config import load_config
    cfg = BrighterFatterDriftConfig() if args.config is None else \
        load_config(BrighterFatterDriftConfig, args.config)
    if args.method:
        cfg.method = args.method
    if args.gain is not None:
        cfg.gain = args.gain
    if args.geometry is not None:
        cfg.compute_geometry = bool(args.geometry)
    if args.template is not None:
        cfg.template = os.path.abspath(args.template)
    if args.saturation is not None:
        cfg.saturation = args.saturation
    if args.blocking_planes is not None:
        cfg.blocking_mask_planes = [p.strip() for p in args.blocking_planes.split(",")
                                    if p.strip()]
    if args.strict:
        cfg.on_input_warning = "raise"
    cfg.validate()  # a bad --gain or --method is a usage error, not one failure per file
    files = list(args.inputs)
    if args.out_dir:
        os.makedirs(args.out_dir, exist_ok=True)
        pairs = output_pairs(files, args.out_dir)
    else:
        if len(files) != 2:
            raise InputError(f"{len(files)} paths without --out-dir: give IN.fits OUT.fits, or "
                             "several inputs with --out-dir DIR")
        pairs = [(files[0], files[1])]
    for src, dst in pairs:  # an existing output is one file's failure; an input, a usage error
        check_output(dst, [s for s, _ in pairs], overwrite=True, what="output")
    if not args.out_dir and args.overwrite and os.path.exists(files[1]) and \
            not _written_by_bfdrift(files[1]):
        # `correct a.fits b.fits --overwrite` meant as two inputs would replace b.fits
        raise OutputExistsError(
            f"refusing to overwrite {files[1]}: it exists and was not written by bfdrift "
            "correct (no BFDRIFT card); was it meant as a second input? Use --out-dir DIR "
            "for several inputs, or remove the file")
    if args.skip_existing and args.overwrite:
        raise InputError("--skip-existing and --overwrite contradict each other; give one")
    skipped = [(s_, d) for s_, d in pairs if args.skip_existing and os.path.exists(d)]
    todo = [p_ for p_ in pairs if p_ not in skipped]
    done = correct_files(todo, cfg, scheduler=args.scheduler, overwrite=args.overwrite,
                         n_workers=args.n_workers, processes=args.processes,
                         progress=not args.quiet) if todo else []
    by_pair = dict(zip(todo, done))
    results = [by_pair.get(p_) or {"input": p_[0], "output": p_[1], "error": None,
                                   "skipped": True, "iterations": None, "converged": None}
               for p_ in pairs]
    failed = [r for r in results if r["error"]]
    if args.json:
        _print_json({"method": cfg.method, "files": results, "failed": len(failed)})
    else:
        for r in results:
            if r["error"]:
                print(f"{r['input']}: FAILED: {r['error']}")
            elif r.get("skipped"):
                print(f"{r['input']} -> {r['output']}: skipped (the output exists)")
            else:
                # say what happened: the flux moved, and how the solver got there
                how = ("the series solution was within tolerance (no iteration needed)"
                       if r["iterations"] == 0 else f"{r['iterations']} iteration(s)")
                nw = len(r.get("warnings") or [])
                print(f"{r['input']} -> {r['output']}: moved {r['flux_moved_abs_sum'] / 2:.4g} e "
                      f"between pixels; {how}; "
                      + ("converged" if r["converged"] else "NOT converged (see the log)")
                      + (f"; {nw} input warning(s) (BFWARN; printed below, --strict refuses "
                         "such inputs)" if nw else ""))
    for r in results:
        for w in r.get("warnings") or []:
            print(f"bfdrift correct: {r['input']}: warning: {w}", file=sys.stderr)
    for r in failed:
        print(f"bfdrift correct: {r['input']}: {r['error']}", file=sys.stderr)
    return 1 if failed else 0


def _written_by_bfdrift(path):
    """Whether a FITS file carries the BFDRIFT card that ``bfdrift correct`` writes."""
    from astropy.io import fits

    try:
        with fits.open(path) as hdul:
            return any(h.header.get("BFDRIFT") is True for h in hdul)
    except (OSError, ValueError, TypeError):
        return False


def build_parser():
    """The argparse parser of ``bfdrift``."""
    from lsst_bfdrift.utils.version import __version__
    p = argparse.ArgumentParser(prog="bfdrift", description="Electrostatic brighter-fatter "
                                "model (Rasmussen 2015): templates and pixel-geometry maps.")
    p.add_argument("--version", action="version", version=f"bfdrift {__version__}",
                   help="print the package version and exit")
    sub = p.add_subparsers(dest="command", required=True)

    tp = sub.add_parser("template", help="build, inspect and convert templates")
    tsub = tp.add_subparsers(dest="action", required=True)
    b = tsub.add_parser("build", help="compute a template from the model")
    b.add_argument("--out", required=True, help="output FITS file")
    b.add_argument("--config", help="TemplateBuildConfig: a pex_config override file "
                   "(config.sensor.v_bss = -60.0), or JSON/TOML with 'sensor' and 'template' "
                   "tables")
    b.add_argument("--size", type=int, help="neighbourhood side N (odd)")
    b.add_argument("--charge", type=float, help="aggressor charge (e)")
    b.add_argument("--samples", type=int, help="samples per edge")
    b.add_argument("--tol", type=float, help="bisection tolerance (px)")
    b.add_argument("--workers", type=int, help="threads")
    b.add_argument("--overwrite", action="store_true")
    b.add_argument("--quiet", action="store_true", help="no progress bar")
    b.add_argument("--json", action="store_true", help="print the summary as JSON")
    b.set_defaults(func=_cmd_template_build)
    s = tsub.add_parser("summary", help="key numbers of a template")
    s.add_argument("file", nargs="?", help="template FITS file (default: bundled)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=_cmd_template_summary)
    pl = tsub.add_parser("plot", help="draw boundaries and area map")
    pl.add_argument("file", nargs="?", help="template FITS file (default: bundled)")
    pl.add_argument("--out", required=True, help="output PNG")
    pl.add_argument("--exaggerate", type=float, help="displacement factor")
    pl.add_argument("--half-width", type=int, help="pixels shown each side")
    pl.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    pl.set_defaults(func=_cmd_template_plot)
    ex = tsub.add_parser("export-galsim", help="write GalSim sensor files (.cfg, .dat) that "
                         "galsim.SiliconSensor(name=PREFIX) reads")
    ex.add_argument("file", nargs="?", help="template FITS file (default: bundled)")
    ex.add_argument("prefix", help="output path without extension")
    ex.add_argument("--vertices", type=int, help="vertices per edge (default: the template's "
                    "edge samples)")
    ex.add_argument("--overwrite", action="store_true", help="replace existing files")
    ex.add_argument("--json", action="store_true")
    ex.set_defaults(func=_cmd_template_export)
    g = tsub.add_parser("import-galsim", help="convert a GalSim sensor file")
    g.add_argument("name", help="sensor name (e.g. lsst_itl_50_8) or path prefix")
    g.add_argument("--out", required=True, help="output template FITS file")
    g.add_argument("--overwrite", action="store_true")
    g.add_argument("--json", action="store_true")
    g.set_defaults(func=_cmd_template_import)

    ca = sub.add_parser("calibrate", help="tune the model to a sensor's data: template out")
    ca.add_argument("input", nargs="+", help="flat-pair FITS files (EXPTIME in the header), a "
                    "PTC text file, an a-matrix table (i j a sigma, or ECSV i, j, a, a_err) or "
                    "cp_pipe's PTC dataset FITS")
    ca.add_argument("--out", required=True, help="calibrated template FITS file")
    ca.add_argument("--free", nargs="+", metavar="NAME",
                    help="free parameters (default: chosen by the data from channel_depth, "
                         "xi0, collection_height, clock_separation, v_bss, acceptor_density, "
                         "xi_ck, xi_cs)")
    ca.add_argument("--max-lag", type=int, default=8,
                    help="largest lag measured from flat pairs (default: %(default)s)")
    ca.add_argument("--no-refine", action="store_true",
                    help="keep the model's areas (default: match them to the measured a_ij)")
    ca.add_argument("--max-chi2-dof", type=float, default=3.0,
                    help="a fit above this chi2/dof (and p < 1e-3) is an error "
                         "(default: %(default)s)")
    ca.add_argument("--allow-poor-fit", action="store_true",
                    help="write the template even when the fit is poor")
    ca.add_argument("--stars", nargs="+", metavar="EXPOSURE",
                    help="star fields (FITS, electrons or ADU with GAIN) fitted jointly with "
                         "the a-matrix: corrected star size and shape must not depend on flux")
    ca.add_argument("--holdout", choices=("auto", "cross", "split", "last"), default="auto",
                    help="stars held out for validation: two-fold cross-validation over "
                         "seeded halves of every field, the template fitted to all stars "
                         "('cross', and 'auto'); one half fitted, the other held out "
                         "('split'); the last field held out ('last') (default: %(default)s)")
    ca.add_argument("--gain", type=float, help="e/ADU of star fields in ADU without GAIN")
    ca.add_argument("--model-directions-only", action="store_true",
                    help="with --stars: move the template along the model's directions only, "
                         "not within the a-matrix's errors lag by lag")
    ca.add_argument("--fit-slopes", nargs="+", choices=("size", "e1", "e2"), default=["size"],
                    metavar="SLOPE",
                    help="with --stars: the star slopes the fit nulls (size, e1, e2; default "
                         "size: a field measures e1 to about its own size, so fitting it adds "
                         "noise; the others are reported)")
    ca.add_argument("--size-goal", type=float, default=3.0, metavar="PERCENT",
                    help="with --stars: the precision of the corrected size slope (%% of the "
                         "uncorrected) the report measures the fit against; short of it, a "
                         "warning says how many fields would reach it (default: %(default)s)")
    ca.add_argument("--plot", help="write a PNG: a_ij against lag, pulls, correlations")
    ca.add_argument("--overwrite", action="store_true",
                    help="replace an existing --out or --plot")
    ca.add_argument("--json", action="store_true")
    ca.add_argument("--quiet", action="store_true", help="no progress bar")
    ca.set_defaults(func=_cmd_calibrate)
    pt = sub.add_parser("ptc", help="photon transfer curve fit (gain, a_ij)")
    pt.add_argument("files", nargs="+", help="PTC text file, or FITS flats in pairs (files, or "
                    "one directory: its FITS files sorted by name)")
    pt.add_argument("--max-lag", type=int, default=3, help="largest covariance lag")
    pt.add_argument("--json", action="store_true")
    pt.set_defaults(func=_cmd_ptc)

    fs = sub.add_parser("flat-sim", help="flat-field simulation with moving boundaries")
    fs.add_argument("--template", help="template FITS file (default: bundled)")
    fs.add_argument("--responsivity", type=float,
                    help="rescale the template to this dlnA00 per electron; write it "
                    "as --responsivity=-1e-5 (a leading minus needs the = form)")
    fs.add_argument("--n-images", type=int, default=1024, help="periodic images simulated")
    fs.add_argument("--size", type=int, default=16, help="side of each periodic image")
    fs.add_argument("--step", type=float, default=1000.0, help="electrons per pixel per step")
    fs.add_argument("--steps", type=int, default=250, help="exposure steps per image")
    fs.add_argument("--max-lag", type=int, default=3, help="largest covariance lag (px)")
    fs.add_argument("--seed", type=int, default=20151, help="random seed")
    fs.add_argument("--out", help="write the per-step table (ECSV)")
    fs.add_argument("--plot", help="write a PNG of covariances against mean")
    fs.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    fs.add_argument("--json", action="store_true")
    fs.add_argument("--quiet", action="store_true")
    fs.set_defaults(func=_cmd_flat_sim)

    ss = sub.add_parser("star-sim", help="star simulation with moving boundaries")
    ss.add_argument("--template", help="template FITS file (default: bundled)")
    ss.add_argument("--psf", default="gaussian", choices=("gaussian", "moffat", "kolmogorov"),
                    help="PSF profile")
    ss.add_argument("--fwhm", type=float, default=0.6, help="arcsec")
    ss.add_argument("--e", type=float, default=0.05, help="PSF ellipticity")
    ss.add_argument("--beta", type=float, default=30.0, help="PSF position angle (deg)")
    ss.add_argument("--flux", type=float, default=2e6, help="conversions (e)")
    ss.add_argument("--stamp", type=int, default=31, help="stamp side (px)")
    ss.add_argument("--update-every", type=int, default=1000,
                    help="electrons between boundary updates")
    ss.add_argument("--pixel-scale", type=float, default=0.2, help="arcsec per px")
    ss.add_argument("--dx", type=float, default=0.25, help="centre offset (px)")
    ss.add_argument("--dy", type=float, default=0.25, help="centre offset (px)")
    ss.add_argument("--seed", type=int, default=20151, help="random seed")
    ss.add_argument("--out", help="write the per-step table (ECSV)")
    ss.add_argument("--plot", help="write a PNG like the paper's Fig. 7")
    ss.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    ss.add_argument("--json", action="store_true")
    ss.add_argument("--quiet", action="store_true")
    ss.set_defaults(func=_cmd_star_sim)

    co = sub.add_parser("correct", help="brighter-fatter correction of FITS images")
    co.add_argument("inputs", nargs="+", help="IN.fits OUT.fits, or inputs with --out-dir")
    co.add_argument("--out-dir", help="directory for the corrected files (same names)")
    co.add_argument("--config", help="BrighterFatterDriftConfig: a pex_config override file "
                    "(config.method = 'astier23'), or a JSON/TOML table of field values")
    co.add_argument("--method", choices=("drift", "astier23", "coulton18"),
                    help="correction method (default: the config's, drift)")
    co.add_argument("--gain", type=float, help="e/ADU: the images are in ADU (one rule "
                    "everywhere; an image stating electrons is refused)")
    co.add_argument("--template", help="template FITS file (default: the config's, else the "
                    "bundled default)")
    co.add_argument("--saturation", type=float, help="level at and above which pixels are "
                    "blocked, in the image's units (default: the config's, else the SATURATE "
                    "keyword)")
    co.add_argument("--geometry", action=argparse.BooleanOptionalAction, default=None,
                    help="write the geometry maps (default: the config's compute_geometry, "
                    "True, as in the API)")
    co.add_argument("--overwrite", action="store_true",
                    help="replace existing outputs (with IN OUT, only a file bfdrift wrote)")
    co.add_argument("--strict", action="store_true",
                    help="refuse inputs that look wrong (bias pedestal, mask over the sources, "
                    "undeclared mask bits) instead of warning (config on_input_warning)")
    co.add_argument("--blocking-planes", help="comma-separated mask planes that block the "
                    "flux exchange (default: the config's, SAT,BAD,NO_DATA,SUSPECT,"
                    "UNMASKEDNAN); DETECTED and other planes never block unless named")
    co.add_argument("--skip-existing", action="store_true",
                    help="leave inputs whose output exists (resume an interrupted run)")
    co.add_argument("--scheduler", help="dask: 'local' (LocalCluster) or a scheduler address "
                    "(tcp://host:8786); default: serial")
    co.add_argument("--n-workers", type=int, default=2, help="LocalCluster workers")
    co.add_argument("--processes", action="store_true",
                    help="LocalCluster workers as processes (default: threads)")
    co.add_argument("--json", action="store_true")
    co.add_argument("--quiet", action="store_true")
    co.set_defaults(func=_cmd_correct)

    vs = sub.add_parser("validate-stars", help="corrections on galsim.SiliconSensor stars")
    vs.add_argument("--n-stars", type=int, default=200, help="stars per flux level")
    vs.add_argument("--psf", default="moffat", choices=("moffat", "kolmogorov", "gaussian"),
                    help="PSF profile")
    vs.add_argument("--sensor", default="lsst_itl_50_8", help="GalSim sensor name")
    vs.add_argument("--template", help="template for the corrections (default: the sensor's)")
    vs.add_argument("--match", default="transfers", choices=("transfers", "areas", "none"),
                    help="import of the sensor's file when no --template (import_galsim_sensor)")
    vs.add_argument("--updates", type=float, default=1000.0,
                    help="GalSim boundary updates per exposure (1000: converged)")
    vs.add_argument("--min-nrecalc", type=float, default=100.0,
                    help="smallest GalSim nrecalc (photons)")
    vs.add_argument("--sky", type=float, default=1000.0, help="sky level (e per pixel)")
    vs.add_argument("--seed", type=int, default=20151)
    vs.add_argument("--json", action="store_true")
    vs.add_argument("--quiet", action="store_true")
    vs.set_defaults(func=_cmd_validate_stars)

    rp = sub.add_parser("reproduce", help="the paper's numbers with the calibrated model")
    rp.add_argument("--out", help="directory for figures, template and JSON")
    rp.add_argument("--quick", action="store_true", help="small template and scan (tests)")
    rp.add_argument("--overwrite", action="store_true")
    rp.add_argument("--json", action="store_true")
    rp.add_argument("--quiet", action="store_true")
    rp.set_defaults(func=_cmd_reproduce)

    vk = sub.add_parser("validate-sky", help="BF size/shape-flux slopes of the stars of an "
                        "image, before and after correction (no truth needed)")
    vk.add_argument("image", help="FITS image (electrons, or ADU with --gain / GAIN keyword)")
    vk.add_argument("--gain", type=float, help="e/ADU if the image is in ADU")
    vk.add_argument("--saturation", type=float, help="saturation level (image unit)")
    vk.add_argument("--template", help="template FITS file (default: bundled)")
    vk.add_argument("--galsim-sensor", help="use the import of this GalSim sensor as template")
    vk.add_argument("--route", default="catalog", choices=["catalog", "pixel", "both", "none"],
                    help="correction route(s) to validate")
    vk.add_argument("--method", default="drift", help="Task method for the pixel route")
    vk.add_argument("--z-crit", type=float, default=3.0, help="detection significance (sigma)")
    vk.add_argument("--min-snr", type=float, default=30.0, help="faintest stars used (SNR)")
    vk.add_argument("--poly-order", type=int, default=2, help="PSF position polynomial order")
    vk.add_argument("--n-boot", type=int, default=200, help="bootstrap resamples")
    vk.add_argument("--catalog", help="write the (corrected) star catalogue (ECSV)")
    vk.add_argument("--plot", help="write a PNG: size/ellipticity vs flux and whiskers")
    vk.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    vk.add_argument("--json", action="store_true")
    vk.add_argument("--quiet", action="store_true")
    vk.set_defaults(func=_cmd_validate_sky)
    dg = sub.add_parser("diagnose", help="residual of the model and the effects explaining it")
    dg.add_argument("input", help="a_ij table, PTC text file or directory of flat pairs")
    dg.add_argument("--json", action="store_true")
    dg.add_argument("--report", help="write report.md, diagnosis.json and figures here")
    dg.add_argument("--overwrite", action="store_true")
    dg.add_argument("--basis", help="linearised electrostatic model (JSON; default: the "
                    "shipped fit to the ITL a_ij)")
    dg.add_argument("--max-lag", type=int, default=3, help="largest lag for flat pairs")
    dg.add_argument("--template-change", action=argparse.BooleanOptionalAction, default=True,
                    help="when an added effect moves the base a_ij by more than 1 sigma, "
                    "calibrate templates without and with it and give what the first would "
                    "leave of the star size and e1 slopes (about a minute; default on)")
    dg.set_defaults(func=_cmd_diagnose)

    m = sub.add_parser("maps", help="pixel geometry maps of an image (main job)")
    m.add_argument("image", nargs="?", help="FITS image in electrons (default: bundled sample)")
    m.add_argument("--template", help="template FITS file (default: bundled)")
    m.add_argument("--gain", type=float, help="e/ADU if the image is in ADU")
    m.add_argument("--out", help="write the maps to this FITS file")
    m.add_argument("--plot", help="write a PNG of the maps")
    m.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    m.add_argument("--samples", type=int, default=None,
                   help="resample the template's edges to this many samples (faster; 8 "
                        "keeps the maps within ~1e-5 of the full ones); default: all")
    m.add_argument("--json", action="store_true")
    m.add_argument("--quiet", action="store_true")
    m.set_defaults(func=_cmd_maps)
    _show_defaults(p)
    return p


_COMMON_HELP = {"--json": "print the result as JSON on stdout", "--seed": "random seed",
                "--quiet": "no progress bar",
                "--overwrite": "replace existing output files (never an input)"}


def _show_defaults(parser):
    """Every (sub)command's --help shows each option's default and a line for
    each option (the flags common to many commands get their line here)."""
    parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
    for action in parser._actions:
        if not action.help and action.option_strings:
            action.help = _COMMON_HELP.get(action.option_strings[-1])
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                _show_defaults(child)


#: Exit status of ``bfdrift`` for each kind of error (documented in ``docs/cli.rst``):
#: 0 success; 1 a file-system error (permission, disk full, ...) or files that
#: failed in ``correct``; 2 usage, a bad argument or a bad input; 3 an output
#: that exists (without ``--overwrite``) or is one of the inputs; 4 a fit or
#: computation that failed.
EXIT_OK, EXIT_OTHER, EXIT_INPUT, EXIT_EXISTS, EXIT_FIT = 0, 1, 2, 3, 4


def exit_code(exc):
    """Exit status of ``bfdrift`` for the exception ``exc`` (see :data:`EXIT_OK`).

    Parameters
    ----------
    exc : BfdriftError or OSError
        The error that ended the command.

    Returns
    -------
    code : int
        2 for :class:`~lsst_bfdrift.utils.errors.InputError` (and an input
        path that does not exist or is of the wrong kind), 3 for
        :class:`~lsst_bfdrift.utils.errors.OutputExistsError`, 4 for
        :class:`~lsst_bfdrift.utils.errors.FitError` and
        :class:`~lsst_bfdrift.utils.errors.ComputationError`, 1 otherwise.
    """
    if isinstance(exc, FileExistsError):
        return EXIT_EXISTS
    if isinstance(exc, (FitError, ComputationError)):
        return EXIT_FIT
    if isinstance(exc, (InputError, FieldValidationError, FileNotFoundError, IsADirectoryError,
                        NotADirectoryError)):
        return EXIT_INPUT
    return EXIT_OTHER


def main(argv=None):
    """Entry point; returns the exit status (errors: one message on stderr).

    Only the package's errors (:class:`~lsst_bfdrift.utils.errors.BfdriftError`)
    and ``OSError`` are caught, each mapped to one status by :func:`exit_code`;
    anything else is a bug and keeps its traceback.

    Before the command runs, partial files left by killed runs (``.tmp-*``
    files whose process is gone) are removed from the directories it writes
    into, and listed on stderr. SIGTERM ends the command through an exception
    (exit status 143), so that its partial output is removed like on
    Ctrl-C.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    with _sigterm_raises():
        try:
            _remove_stale_outputs(args)
            return args.func(args)
        except (BfdriftError, FieldValidationError, OSError) as exc:
            print(f"bfdrift: error: {exc}", file=sys.stderr)
            return exit_code(exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
