"""``bfdrift validate-stars``, ``bfdrift validate-sky`` and ``bfdrift reproduce``:
the commands that check the corrections and the model (options and commands).

The options' defaults are those of the functions they feed
(:func:`~lsst_bfdrift.validation.stars.draw_star_pairs`,
:func:`~lsst_bfdrift.validation.sky.validate_sky`), except where a comment
says why not.
"""

import json
import os

from lsst_bfdrift.cli._common import (add_common_options, check_output_dir, check_outputs, emit,
                                      library_default, load_template, print_json, save_plot,
                                      template_input)
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.templates.template import DistortionTemplate
from lsst_bfdrift.utils.io import atomic_output
from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.validation.paper_figures import reproduce, write_figures
from lsst_bfdrift.validation.sky import validate_sky
from lsst_bfdrift.validation.stars import draw_star_pairs, validate_stars

__all__ = ["add_validate_stars_parser", "add_validate_sky_parser", "add_reproduce_parser",
           "cmd_validate_stars", "cmd_validate_sky", "cmd_reproduce", "VALIDATE_STARS_MATCH"]

#: How ``validate-stars`` imports the sensor's file when no ``--template`` is
#: given: matched to GalSim's transfers, not import_galsim_sensor's default
#: ``'areas'`` (benchmarks/correction/probe_validation_cadence_results.txt,
#: docs/benchmarks.rst).
VALIDATE_STARS_MATCH = "transfers"


def cmd_validate_stars(args):
    """``bfdrift validate-stars``: the corrections on galsim.SiliconSensor stars.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    tpl = import_galsim_sensor(args.sensor, match=args.match) \
        if args.template is None else DistortionTemplate.load(args.template)
    pairs = draw_star_pairs(args.n_stars, sensor=args.sensor, psf=args.psf, sky=args.sky,
                            seed=args.seed, updates=args.updates,
                            min_nrecalc=args.min_nrecalc, progress=not args.quiet)
    res = validate_stars(pairs, tpl, sky=args.sky, progress=not args.quiet)
    unc = res["uncorrected"]["size_slope"]
    for k, v in res.items():
        v["size_slope_fraction_of_uncorrected"] = v["size_slope"] / unc if unc else None
    out = {"sensor": args.sensor, "psf": args.psf, "n_stars": args.n_stars,
           "units": "slopes per 1e5 e: fractional change of T = Ixx + Iyy, change of e1/e2",
           "template": args.template or f"galsim:{args.sensor} (match={args.match!r})",
           "updates": args.updates, "min_nrecalc": args.min_nrecalc, **res}
    if args.json:
        print_json(out)
    else:
        for k, v in res.items():
            paired = ("" if "size_slope_minus_astier23" not in v else
                      f"  paired minus astier23 {v['size_slope_minus_astier23']:+.2e} +- "
                      f"{v['size_slope_minus_astier23_err']:.1e}")
            print(f"{k:12s} size slope {v['size_slope']:+.2e} +- {v['size_slope_err']:.1e}  "
                  f"e1 slope {v['e_slope']:+.2e} +- {v['e_slope_err']:.1e}{paired}")
    return 0


def cmd_reproduce(args):
    """``bfdrift reproduce``: the paper's numbers next to the calibrated model's.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_output_dir(args, args.out, "--out")
    kw = dict(size=11, edge_samples=16, v_bss=(-65.0, -50.0), xi_ck=(4.0, 5.0),
              quick_features=True) if args.quick else {}
    n_scan = len(kw.get("v_bss", (0,) * 5)) * len(kw.get("xi_ck", (0,) * 5)) + 5
    tables = {}
    with ProgressBar(n_scan, "reproduce", enabled=not args.quiet) as bar:
        numbers, tpl, (v_bss, xi_ck, ratio) = reproduce(progress=bar, tables=tables, **kw)
    numbers["ratio_scan"] = {"v_bss": v_bss.tolist(), "xi_ck": xi_ck.tolist(),
                             "ratio_01_10": ratio.tolist()}
    if args.out:
        write_figures(numbers, tpl, (v_bss, xi_ck, ratio), tables, args.out)
        tpl.save(os.path.join(args.out, "paper_template.fits"), overwrite=True)
        with atomic_output(os.path.join(args.out, "reproduce.json")) as tmp, \
                open(tmp, "w") as fh:
            json.dump(numbers, fh, indent=2, default=float)
    return emit(numbers, args.json, 20)


def cmd_validate_sky(args):
    """``bfdrift validate-sky``: size- and shape-flux slopes of a sky image's stars,
    before and after correction.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_outputs(args, [args.image, None if args.galsim_sensor else
                         template_input(args.template)],
                  {"--catalog": args.catalog, "--plot": args.plot})
    if args.galsim_sensor:
        tpl = import_galsim_sensor(args.galsim_sensor)
    else:
        tpl = load_template(args.template)
    res = validate_sky(args.image, gain=args.gain, saturation=args.saturation, template=tpl,
                       route=args.route, method=args.method, z_crit=args.z_crit,
                       min_snr=args.min_snr, poly_order=args.poly_order, n_boot=args.n_boot,
                       progress=not args.quiet)
    out = dict(res.summary)
    out["image"] = os.path.abspath(args.image)
    out["template"] = (f"galsim:{args.galsim_sensor}" if args.galsim_sensor
                       else args.template or "default")
    if args.catalog:
        cat = res.corrected.get("catalog", res.catalog)
        with atomic_output(args.catalog) as tmp:
            cat.write(tmp, format="ascii.ecsv", overwrite=True)
        out["catalog"] = os.path.abspath(args.catalog)
    if args.plot:
        # matplotlib: validation.plots imports it; only when --plot is given
        from lsst_bfdrift.validation.plots import plot_sky_validation
        save_plot(plot_sky_validation(res), args.plot, out)
    if args.json:
        print_json(out)
    else:
        print(out["verdict"])
    return 0


def add_validate_stars_parser(subparsers):
    """Add ``validate-stars`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    def default(name):
        return library_default(draw_star_pairs, name)

    vs = subparsers.add_parser("validate-stars", help="corrections on galsim.SiliconSensor "
                               "stars")
    # the number of stars has no library default: the command's own
    vs.add_argument("--n-stars", type=int, default=200, help="stars per flux level")
    vs.add_argument("--psf", default=default("psf"),
                    choices=("moffat", "kolmogorov", "gaussian"), help="PSF profile")
    vs.add_argument("--sensor", default=default("sensor"), help="GalSim sensor name")
    vs.add_argument("--template", help="template for the corrections (default: the sensor's)")
    # not import_galsim_sensor's 'areas': see VALIDATE_STARS_MATCH
    vs.add_argument("--match", default=VALIDATE_STARS_MATCH,
                    choices=("transfers", "areas", "none"),
                    help="import of the sensor's file when no --template (import_galsim_sensor)")
    vs.add_argument("--updates", type=float, default=float(default("updates")),
                    help="GalSim boundary updates per exposure (1000: converged)")
    vs.add_argument("--min-nrecalc", type=float, default=float(default("min_nrecalc")),
                    help="smallest GalSim nrecalc (photons)")
    vs.add_argument("--sky", type=float, default=default("sky"), help="sky level (e per pixel)")
    vs.add_argument("--seed", type=int, default=default("seed"))
    add_common_options(vs, "json", "quiet")
    vs.set_defaults(func=cmd_validate_stars)
    return vs


def add_reproduce_parser(subparsers):
    """Add ``reproduce`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    rp = subparsers.add_parser("reproduce", help="the paper's numbers with the calibrated "
                               "model")
    rp.add_argument("--out", help="directory for figures, template and JSON")
    rp.add_argument("--quick", action="store_true", help="small template and scan (tests)")
    add_common_options(rp, "overwrite", "json", "quiet")
    rp.set_defaults(func=cmd_reproduce)
    return rp


def add_validate_sky_parser(subparsers):
    """Add ``validate-sky`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser.

    ``validate_sky``'s ``seed`` and ``history`` are not options: the command
    uses the function's defaults.

    """
    def default(name):
        return library_default(validate_sky, name)

    vk = subparsers.add_parser("validate-sky", help="BF size/shape-flux slopes of the stars of "
                               "an image, before and after correction (no truth needed)")
    vk.add_argument("image", help="FITS image (electrons, or ADU with --gain / GAIN keyword)")
    vk.add_argument("--gain", type=float, default=default("gain"),
                    help="e/ADU if the image is in ADU")
    vk.add_argument("--saturation", type=float, default=default("saturation"),
                    help="saturation level (image unit)")
    vk.add_argument("--template", help="template FITS file (default: bundled)")
    vk.add_argument("--galsim-sensor", help="use the import of this GalSim sensor as template")
    vk.add_argument("--route", default=default("route"),
                    choices=["catalog", "pixel", "both", "none"],
                    help="correction route(s) to validate")
    vk.add_argument("--method", default=default("method"), help="Task method for the pixel route")
    vk.add_argument("--z-crit", type=float, default=default("z_crit"),
                    help="detection significance (sigma)")
    vk.add_argument("--min-snr", type=float, default=default("min_snr"),
                    help="faintest stars used (SNR)")
    vk.add_argument("--poly-order", type=int, default=default("poly_order"),
                    help="PSF position polynomial order")
    vk.add_argument("--n-boot", type=int, default=default("n_boot"), help="bootstrap resamples")
    vk.add_argument("--catalog", help="write the (corrected) star catalog (ECSV)")
    vk.add_argument("--plot", help="write a PNG: size/ellipticity vs flux and whiskers")
    add_common_options(vk, "overwrite", "json", "quiet")
    vk.set_defaults(func=cmd_validate_sky)
    return vk
