"""``bfdrift correct`` and ``bfdrift maps``: the commands on images (options and
commands).

``correct`` takes its defaults from
:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftConfig` (an option
not given leaves the config's field) and from
:func:`~lsst_bfdrift.correction.batch.correct_files`; ``maps`` from
:func:`~lsst_bfdrift.geometry.superpose.moment_maps`.
"""

import argparse
import math
import os
import sys
import warnings

import numpy as np
from astropy.io import fits

from lsst_bfdrift.cli._common import (add_common_options, check_outputs, emit, library_default,
                                      load_template, print_json, save_plot, template_input)
from lsst_bfdrift.correction.batch import correct_files, output_pairs
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig
from lsst_bfdrift.geometry.superpose import moment_maps
from lsst_bfdrift.images.electrons import gain_value, to_electrons
from lsst_bfdrift.utils.config import load_config
from lsst_bfdrift.utils.errors import FieldValidationError, InputError, OutputExistsError
from lsst_bfdrift.utils.io import atomic_output, check_output, data_path
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["sample_image_path", "add_correct_parser", "add_maps_parser", "cmd_correct",
           "cmd_maps"]


def sample_image_path():
    """Path of the bundled sample image (a bright star on sky, electrons).

    Returns
    -------
    path : str
    """
    return data_path("sample_star.fits")


#: Unit and description of each geometry map ``maps --out`` writes.
MAP_UNITS = {"area": ("pix2", "final pixel area"),
             "dx": ("pix", "centroid shift along x (serial) from the pixel centre"),
             "dy": ("pix", "centroid shift along y (parallel) from the pixel centre"),
             "e1": ("", "e1 = (Ixx - Iyy) / (Ixx + Iyy) of the final pixel"),
             "e2": ("", "e2 = 2 Ixy / (Ixx + Iyy) of the final pixel")}


def _write_maps(path, maps, header):
    """The maps file: the input's header in the primary HDU (its BUNIT kept as
    BFIUNIT: the file holds no image in that unit), one HDU per map with its
    BUNIT and description."""
    header = fits.Header(header)
    if "BUNIT" in header:
        header["BFIUNIT"] = (header.pop("BUNIT"), "unit of the input image")
    hdus = [fits.PrimaryHDU(header=header)]
    for name, arr in maps.as_dict().items():
        hdu = fits.ImageHDU(arr.astype(np.float64), name=name.upper())
        unit, doc = MAP_UNITS.get(name, ("", name))
        hdu.header["BUNIT"] = (unit, "dimensionless" if not unit else "")
        hdu.header["BFDESC"] = doc
        hdus.append(hdu)
    with atomic_output(path) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True, checksum=True)


def cmd_maps(args):
    """``bfdrift maps``: the final pixel geometry of an image in electrons.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    path = args.image or sample_image_path()
    check_outputs(args, [path, template_input(args.template)],
                  {"--out": args.out, "--plot": args.plot})
    # the package's one unit, gain and saturation rule (as bfdrift correct): --gain means ADU
    electrons = to_electrons(path, gain=args.gain, gain_name="--gain")
    image, bad, header, gain = electrons.data, electrons.bad, electrons.meta, electrons.gain
    if bad.all():
        raise InputError(f"{path}: every one of the {bad.size} pixels is masked or non-finite: "
                         "there is no charge to map")
    tpl = load_template(args.template)
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
        # matplotlib: geometry.plots imports it; only when --plot is given
        from lsst_bfdrift.geometry.plots import plot_moment_maps
        save_plot(plot_moment_maps(maps, image=np.where(bad, np.nan, image),
                                   title=os.path.basename(path)), args.plot, summary)
    return emit(summary, args.json, 20)


def _correct_config(args):
    """The Task config of ``correct``: ``--config``, then the options given."""
    cfg = BrighterFatterDriftConfig() if args.config is None else \
        load_config(BrighterFatterDriftConfig, args.config)
    if args.method:
        cfg.method = args.method
    if args.gain is not None:  # named by its option, not by the config field's source line
        cfg.gain = gain_value(args.gain, what="--gain")
    if args.geometry is not None:
        cfg.compute_geometry = bool(args.geometry)
    if args.template is not None:
        cfg.template = os.path.abspath(args.template)
    if args.band is not None:
        cfg.band = args.band
    if args.saturation is not None:
        if not (math.isfinite(args.saturation) and args.saturation > 0):
            raise InputError(f"--saturation {args.saturation:g} is not a positive level; "
                             "accepted: a positive finite level in the images' unit (e or ADU)")
        cfg.saturation = args.saturation
    if args.blocking_planes is not None:
        cfg.blocking_mask_planes = [p.strip() for p in args.blocking_planes.split(",")
                                    if p.strip()]
    if args.strict:
        cfg.on_input_warning = "raise"
    try:  # a bad value is a usage error, not one failure per file
        cfg.validate()
    except FieldValidationError as exc:
        # pex_config's message ends with the source lines of the field: not the user's
        text = str(exc).split("\nFor more information")[0].strip()
        raise InputError(f"--config {args.config}: {text}" if args.config else text) from None
    return cfg


def _correct_pairs(args):
    """The (input, output) pairs of ``correct``, checked against the overwrite rule."""
    files = list(args.inputs)
    if args.out_dir:
        if os.path.exists(args.out_dir) and not os.path.isdir(args.out_dir):
            raise InputError(f"--out-dir {args.out_dir}: exists and is not a directory; "
                             "accepted: a directory (created if missing)")
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
    return pairs


def _print_correct_results(results, failed, method, as_json):
    """The report of ``correct``: one line per file done or skipped (or JSON) on
    stdout, the warnings and failures on stderr (a failure once, there)."""
    if as_json:
        print_json({"method": method, "files": results, "failed": len(failed)})
    else:
        for r in results:
            if r["error"]:
                continue  # said once, on stderr, below
            if r.get("skipped"):
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
        # the package's messages start with the file already
        text = r["error"] if r["error"].startswith(f"{r['input']}:") else \
            f"{r['input']}: {r['error']}"
        print(f"bfdrift correct: error: {text}", file=sys.stderr)
    if failed and len(results) > 1:
        rest = "" if len(failed) == len(results) else "; the others are done"
        print(f"bfdrift correct: {len(failed)} of {len(results)} files failed (listed "
              f"above){rest}", file=sys.stderr)


def cmd_correct(args):
    """``bfdrift correct``: BrighterFatterDriftTask on FITS images.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status: 1 when a file failed (the others are done).
    """
    cfg = _correct_config(args)
    pairs = _correct_pairs(args)
    # --skip-existing skips only an output bfdrift correct wrote completely; another file
    # there is that input's failure, saying what was found
    found = {p_: _output_state(p_[1]) for p_ in pairs
             if args.skip_existing and os.path.exists(p_[1])}
    todo = [p_ for p_ in pairs if p_ not in found]
    done = correct_files(todo, cfg, scheduler=args.scheduler, overwrite=args.overwrite,
                         n_workers=args.n_workers, processes=args.processes,
                         progress=not args.quiet) if todo else []
    by_pair = dict(zip(todo, done))
    for p_, state in found.items():
        by_pair[p_] = {"input": p_[0], "output": p_[1], "iterations": None,
                       "converged": None, "skipped": state is None,
                       "error": None if state is None else
                       f"--skip-existing: {p_[1]} exists but {state}; remove it, or give "
                       "--overwrite to replace it"}
    results = [by_pair[p_] for p_ in pairs]
    failed = [r for r in results if r["error"]]
    _print_correct_results(results, failed, cfg.method, args.json)
    return 1 if failed else 0


def _output_state(path):
    """None for a complete output of ``bfdrift correct`` (every HDU readable, the
    BFDRIFT card set), else what is wrong with the file at ``path``."""
    try:
        with warnings.catch_warnings():  # what is wrong is said in the returned text
            warnings.simplefilter("ignore")
            with fits.open(path) as hdul:
                for h in hdul:
                    _ = h.data  # a file cut short fails here
                if not any(h.header.get("BFDRIFT") is True for h in hdul):
                    return "was not written by bfdrift correct (no BFDRIFT card)"
    except (OSError, ValueError, TypeError, IndexError) as exc:
        return f"is not a readable FITS file, perhaps an output cut short ({exc})"
    return None


def _written_by_bfdrift(path):
    """Whether a FITS file carries the BFDRIFT card that ``bfdrift correct`` writes."""
    try:
        with fits.open(path) as hdul:
            return any(h.header.get("BFDRIFT") is True for h in hdul)
    except (OSError, ValueError, TypeError):
        return False


def add_correct_parser(subparsers):
    """Add ``correct`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser.

    The Task's options are None by default: the config's field stays (its
    value, from :class:`~lsst_bfdrift.correction.task.BrighterFatterDriftConfig`,
    is quoted in the help); the dask options default to
    :func:`~lsst_bfdrift.correction.batch.correct_files`'s.

    """
    cfg = BrighterFatterDriftConfig()
    co = subparsers.add_parser("correct", help="brighter-fatter correction of FITS images")
    co.add_argument("inputs", nargs="+", help="IN.fits OUT.fits, or inputs with --out-dir")
    co.add_argument("--out-dir", help="directory for the corrected files (same names)")
    co.add_argument("--config", help="BrighterFatterDriftConfig: a pex_config override file "
                    "(config.method = 'astier23'), or a JSON/TOML table of field values")
    co.add_argument("--method", choices=tuple(BrighterFatterDriftConfig.method.allowed),
                    help=f"correction method (default: the config's, {cfg.method})")
    co.add_argument("--gain", type=float, help="e/ADU: the images are in ADU (one rule "
                    "everywhere; an image stating electrons is refused)")
    co.add_argument("--template", help="template FITS file (default: the config's, else the "
                    "bundled default)")
    co.add_argument("--band", help="band of the images for a multi-band template (u .. y or "
                    "a physical filter such as r_57; default: the config's, else each image's "
                    "BAND or FILTER keyword)")
    co.add_argument("--saturation", type=float, help="level at and above which pixels are "
                    "blocked, in the image's units (default: the config's, else the SATURATE "
                    "keyword)")
    co.add_argument("--geometry", action=argparse.BooleanOptionalAction, default=None,
                    help="write the geometry maps (default: the config's compute_geometry, "
                    f"{cfg.compute_geometry}, as in the API)")
    co.add_argument("--overwrite", action="store_true",
                    help="replace existing outputs (with IN OUT, only a file bfdrift wrote)")
    co.add_argument("--strict", action="store_true",
                    help="refuse inputs that look wrong (bias pedestal, mask over the sources, "
                    "undeclared mask bits) instead of warning (config on_input_warning)")
    co.add_argument("--blocking-planes", help="comma-separated mask planes that block the "
                    "flux exchange (default: the config's, "
                    f"{','.join(cfg.blocking_mask_planes)}); DETECTED and other planes never "
                    "block unless named")
    co.add_argument("--skip-existing", action="store_true",
                    help="leave inputs whose output exists (resume an interrupted run)")
    co.add_argument("--scheduler", default=library_default(correct_files, "scheduler"),
                    help="dask: 'local' (LocalCluster) or a scheduler address "
                    "(tcp://host:8786); default: serial")
    co.add_argument("--n-workers", type=int, default=library_default(correct_files, "n_workers"),
                    help="LocalCluster workers")
    co.add_argument("--processes", action="store_true",
                    help="LocalCluster workers as processes (default: threads)")
    add_common_options(co, "json", "quiet")
    co.set_defaults(func=cmd_correct)
    return co


def add_maps_parser(subparsers):
    """Add ``maps`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    m = subparsers.add_parser("maps", help="pixel geometry maps of an image (main job)")
    m.add_argument("image", nargs="?", help="FITS image in electrons (default: bundled sample)")
    m.add_argument("--template", help="template FITS file (default: bundled)")
    m.add_argument("--gain", type=float, help="e/ADU if the image is in ADU")
    m.add_argument("--out", help="write the maps to this FITS file")
    m.add_argument("--plot", help="write a PNG of the maps")
    m.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    m.add_argument("--samples", type=int, default=library_default(moment_maps, "samples"),
                   help="resample the template's edges to this many samples (faster; 8 "
                        "keeps the maps within ~1e-5 of the full ones); default: all")
    add_common_options(m, "json", "quiet")
    m.set_defaults(func=cmd_maps)
    return m
