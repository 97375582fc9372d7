"""``bfdrift spots``: the brighter-fatter slopes of a spot-projector series; ``bfdrift
spot-plan``: the spots a lab needs for a goal precision (options and commands).

The options' defaults are those of the functions they feed
(:class:`~lsst_bfdrift.catalogs.spot_series.SpotSeries`,
:func:`~lsst_bfdrift.catalogs.spot_slopes.predict_spot_slopes`), except where a
comment says why not.
"""

import json
import os

import numpy as np

from lsst_bfdrift.calibration.spot_plan import (PLAN_GOALS, PLAN_QUANTITIES, SpotDesign,
                                                plan_spot_acquisition, series_design)
from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.catalogs.spot_slopes import SPOT_MODELS, compare_slopes, predict_spot_slopes
from lsst_bfdrift.catalogs.spots import SPOT_QUANTITIES
from lsst_bfdrift.cli._common import (add_common_options, check_outputs, library_default,
                                      load_template, print_json, save_plot)
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.utils.errors import InputError, InputNotFoundError
from lsst_bfdrift.utils.io import atomic_output

__all__ = ["add_spots_parser", "cmd_spots", "spots_summary", "SPOTS_MATCH",
           "add_spot_plan_parser", "cmd_spot_plan"]

#: How ``spots --galsim-sensor`` imports the sensor's file: matched to GalSim's
#: transfers, as ``validate-stars`` does (its prediction of GalSim's own spots
#: is within about 1 % in size, ``benchmarks/calibration/spots_measure.py``).
SPOTS_MATCH = "transfers"

#: Units of the slopes, per quantity.
_UNITS = {"sigma_x": "px per 1e5 e", "sigma_y": "px per 1e5 e",
          "size": "fractional change of T = Ixx + Iyy per 1e5 e", "e1": "per 1e5 e",
          "e2": "per 1e5 e"}


def _fit_summary(fit):
    """The JSON of one quantity's fit (no per-row arrays)."""
    out = {k: fit[k] for k in ("slope", "slope_err", "err_formal", "err_image", "err_spot", "z",
                               "tau", "chi2_dof", "spread_chi2_dof", "n_points", "n_spots",
                               "n_images")}
    return out


def spots_summary(series, result, *, predicted=None, template=None):
    """The result of ``bfdrift spots`` as a JSON-ready dict.

    Parameters
    ----------
    series : SpotSeries
    result : dict
        :func:`~lsst_bfdrift.catalogs.spot_slopes.spot_slopes` of its rows.
    predicted : dict, optional
        :func:`~lsst_bfdrift.catalogs.spot_slopes.predict_spot_slopes`.
    template : str, optional
        How the template was given (a path or ``galsim:NAME``).

    Returns
    -------
    dict
        ``images`` (name, EXPTIME, rows used), ``grid`` (spots, weight sigma,
        radius), ``excluded`` (rows per flag, in total and per image),
        ``slopes`` (per quantity: slope and its three errors, tau, chi2),
        ``units``, ``per_spot`` (position and slopes of every spot) and, with
        a template, ``predicted`` (per quantity: measured, predicted, ratio, z).
    """
    cat, grid = series.catalog, series.grid
    excl = result["excluded"]
    images = [{"name": ex.name, "exptime": ex.exptime, "used": excl["images"][i]["used"],
               "median_flux": float(np.nanmedian(cat["flux"].value[np.asarray(cat["image"])
                                                                    == i]))}
              for i, ex in enumerate(series.exposures)]
    names = [k for k in SPOT_QUANTITIES if k in result]
    per_spot = []
    for k in range(len(grid)):
        row = {"spot": k, "x": float(grid.x[k]), "y": float(grid.y[k])}
        for q in names:
            ps = result[q]["per_spot"]
            hit = np.flatnonzero(ps["spot"] == k)
            row[q] = float(ps["slope"][hit[0]]) if hit.size else None
            row[f"{q}_err"] = float(ps["slope_err"][hit[0]]) if hit.size else None
        per_spot.append(row)
    out = {"images": images,
           "grid": {"n_spots": len(grid), "weight_sigma": grid.weight_sigma,
                    "adaptive_sigma": grid.adaptive_sigma, "radius": grid.radius,
                    "annulus": list(grid.annulus), "shape": list(grid.shape)},
           "moments": cat.meta["moments"],
           "excluded": {k: v for k, v in excl.items() if k != "images"},
           "excluded_per_image": excl["images"],
           "n_points": result["n_points"], "flux_range": result["flux_range"],
           "slopes": {q: _fit_summary(result[q]) for q in names},
           "units": {q: _UNITS[q] for q in names}, "per_spot": per_spot,
           "errors": "slope_err is the largest of err_formal (weighted least squares with the "
                     "extra scatter tau), err_image (clustered by image) and err_spot "
                     "(clustered by spot)"}
    if predicted is not None:
        cmp = compare_slopes(result, predicted, quantities=names)
        out["predicted"] = {"template": template, "model": predicted["model"],
                            "spots_skipped": predicted["spots_skipped"], **cmp}
    return out


def _print_text(out):
    """The text report of ``spots`` (without ``--json``)."""
    g, ex = out["grid"], out["excluded"]
    times = [im["exptime"] for im in out["images"]]
    left = ", ".join(f"{v} {k}" for k, v in ex.items() if k not in ("used", "rows") and v)
    print(f"{g['n_spots']} spots, {len(out['images'])} images (EXPTIME {min(times):.3g}-"
          f"{max(times):.3g} s), fixed Gaussian weight sigma {g['weight_sigma']:g} px; "
          f"{ex['used']} of {ex['rows']} rows used (left out: {left or 'none'})")
    print("slopes per 1e5 e (sigma_x, sigma_y in px; size: fractional change of T)")
    pred = out.get("predicted")
    for q, s in out["slopes"].items():
        line = (f"  {q:8s} {s['slope']:+.3e} +- {s['slope_err']:.1e}"
                f"  (formal {s['err_formal']:.1e}, image {s['err_image']:.1e}, spot "
                f"{s['err_spot']:.1e}; z {s['z']:+.1f})")
        if pred is not None:
            p = pred[q]
            line += f"  predicted {p['predicted']:+.3e}, measured/predicted {p['ratio']:.3f}" \
                    f" +- {p['ratio_err']:.3f}"
        print(line)
    if pred is not None:
        print(f"  prediction: template {pred['template']}, {pred['model']} spot model")


def cmd_spots(args):
    """``bfdrift spots``: find, measure and fit the spots of a series.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    if args.template and args.galsim_sensor:
        raise InputError("give --template or --galsim-sensor, not both")
    for path in args.images:
        if not os.path.exists(path):
            raise InputNotFoundError(f"{path}: no such file", path)
    check_outputs(args, list(args.images) + [args.template],
                  {"--catalog": args.catalog, "--plot": args.plot})
    series = SpotSeries(args.images, gain=args.gain, saturation=args.saturation,
                        weight_sigma=args.weight_sigma, min_snr=args.min_snr,
                        min_spots=args.min_spots, gain_name="--gain",
                        saturation_name="--saturation", progress=not args.quiet)
    result = series.fit()
    predicted, label = None, None
    if args.template or args.galsim_sensor:
        if args.galsim_sensor:
            tpl = import_galsim_sensor(args.galsim_sensor, match=args.match)
            label = f"galsim:{args.galsim_sensor} (match={args.match!r})"
        else:
            tpl, label = load_template(args.template), args.template
        predicted = predict_spot_slopes(series.catalog, tpl, exposures=series.exposures,
                                        model=args.model, measured=result,
                                        progress=not args.quiet)
    out = spots_summary(series, result, predicted=predicted, template=label)
    out["inputs"] = [os.path.abspath(p) for p in args.images]
    if args.catalog:
        with atomic_output(args.catalog) as tmp:
            series.catalog.write(tmp, format="ascii.ecsv", overwrite=True)
        out["catalog"] = os.path.abspath(args.catalog)
    if args.plot:
        # matplotlib: catalogs.plots imports it; only when --plot is given
        from lsst_bfdrift.catalogs.plots import plot_spot_slopes
        title = f"{len(series.grid)} spots x {len(series.exposures)} images" + \
            (f"; dashed: predicted by {label}" if label else "")
        save_plot(plot_spot_slopes(result, predicted=predicted, title=title), args.plot, out)
    if args.json:
        print_json(out)
    else:
        _print_text(out)
    return 0


def add_spots_parser(subparsers):
    """Add ``spots`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    def default(name):
        return library_default(SpotSeries, name)

    sp = subparsers.add_parser("spots", help="BF slopes of a spot-projector series (spot sizes "
                               "and shapes against flux), optionally predicted by a template")
    sp.add_argument("images", nargs="+", metavar="SPOT_IMAGE",
                    help="FITS spot images of one grid at several exposure times (EXPTIME; "
                         "electrons, or ADU with --gain / GAIN keyword)")
    sp.add_argument("--gain", type=float, default=default("gain"),
                    help="e/ADU of images in ADU without a GAIN keyword")
    sp.add_argument("--saturation", type=float, default=default("saturation"),
                    help="saturation level (image unit; default: SATURATE keyword)")
    sp.add_argument("--weight-sigma", type=float, default=default("weight_sigma"),
                    help="sigma of the fixed Gaussian weight (px; default: 1.5 times the "
                         "spots' median adaptive sigma)")
    sp.add_argument("--min-snr", type=float, default=default("min_snr"),
                    help="rows below this signal-to-noise ratio are left out")
    sp.add_argument("--min-spots", type=int, default=default("min_spots"),
                    help="fewest spots in the grid and detected in every image")
    sp.add_argument("--template", help="predict the slopes with this template FITS file")
    sp.add_argument("--galsim-sensor",
                    help="predict the slopes with the import of this GalSim sensor")
    # not import_galsim_sensor's 'areas': see SPOTS_MATCH
    sp.add_argument("--match", default=SPOTS_MATCH, choices=("transfers", "areas", "none"),
                    help="import of --galsim-sensor (import_galsim_sensor)")
    sp.add_argument("--model", default=library_default(predict_spot_slopes, "model"),
                    choices=SPOT_MODELS, help="BF-free spot profile of the prediction")
    sp.add_argument("--catalog", help="write the per-spot, per-image rows (ECSV)")
    sp.add_argument("--plot", help="write a PNG: moments against flux with the slopes")
    add_common_options(sp, "overwrite", "json", "quiet")
    sp.set_defaults(func=cmd_spots)
    return sp


def _calibration_spots(path, series_name):
    """The ``spots`` of a ``calibrate --json`` file, the series planned from, its entry
    in ``fields`` and the template written (``out``)."""
    try:
        with open(path) as fh:
            doc = json.load(fh)
    except FileNotFoundError:
        raise InputNotFoundError(f"{path}: no such file", path) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not the JSON of bfdrift calibrate --spots --json ({exc})") \
            from None
    spots = doc.get("spots") if isinstance(doc, dict) else None
    unc = (spots or {}).get("uncertainty") or {}
    stated = unc.get(PLAN_QUANTITIES["e1"]) or {}
    if not stated:
        raise InputError(f"{path}: no stated spot precision (the JSON of bfdrift calibrate "
                         "--spots ... --json, without --model-directions-only, has it)")
    names = sorted(stated)
    if series_name is None:
        if len(names) > 1:
            raise InputError(f"{path} fitted {len(names)} spot series; name one with --series "
                             f"({', '.join(names)})")
        series_name = names[0]
    elif series_name not in stated:
        raise InputError(f"--series {series_name!r} is not a fitted spot series of {path} "
                         f"({', '.join(names)})")
    field = next((f for f in spots.get("fields", []) if f.get("name") == series_name), {})
    return spots, series_name, field, doc.get("out")


def cmd_spot_plan(args):
    """``bfdrift spot-plan``: spots and exposures that reach goal precisions.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    for path in list(args.images) + [args.calibration]:
        if not os.path.exists(path):
            raise InputNotFoundError(f"{path}: no such file", path)
    goals = {"e1": tuple(args.goal_e1), "size": tuple(args.goal_size)}
    for q, gs in goals.items():
        if not all(np.isfinite(g) and g > 0 for g in gs):
            raise InputError(f"--goal-{q} must be positive percentages, got {list(gs)}")
    spots, name, field, out_path = _calibration_spots(args.calibration, args.series)
    series = SpotSeries(args.images, gain=args.gain, saturation=args.saturation,
                        gain_name="--gain", saturation_name="--saturation",
                        progress=not args.quiet)
    fitted, n_spots = series_design(series, read_noise=args.read_noise,
                                    background=args.background)
    if field.get("n_usable") and field.get("n_fit") is not None:
        # holdout 'split' fits half the spots: the fitted share of the usable rows
        n_spots = max(1, int(round(n_spots * field["n_fit"] / field["n_usable"])))
    designs = {"as fitted": fitted}
    template, template_label = None, None
    if args.sigma:
        template_label = args.template or out_path
        if not template_label or not os.path.isfile(template_label):
            raise InputError("--sigma plans other spot sizes, whose information is scaled by "
                             "a template's slopes: give --template (the calibrate --out file "
                             f"{out_path!r} is not there)")
        template = load_template(template_label)
        for sig in args.sigma:
            designs[f"sigma {sig:g}"] = SpotDesign.saturating(
                sig, len(fitted.levels), flux_min=fitted.levels[0], peak_max=args.peak_max,
                read_noise=args.read_noise, background=args.background)
    plan = plan_spot_acquisition(spots, name, fitted_design=fitted, n_spots=n_spots,
                                 designs=designs, goals=goals, template=template)
    plan.update(series=name, calibration=os.path.abspath(args.calibration),
                inputs=[os.path.abspath(p) for p in args.images], template=template_label,
                fitted_design={"sigma": fitted.sigma, "levels": list(fitted.levels),
                               "read_noise": fitted.read_noise,
                               "background": fitted.background,
                               "weight_sigma": fitted.weight})
    if args.json:
        print_json(plan)
        return 0
    st = plan["stated"]
    print(f"spot series {name}: {n_spots} spots x {len(fitted.levels)} levels "
          f"({fitted.levels[0]:.3g}-{fitted.levels[-1]:.3g} e), spot sigma "
          f"{fitted.sigma:.2f} px; stated precision of the corrected e1 slope +- "
          f"{st['e1']['flats_percent']:.1f} % (flats alone) -> +- "
          f"{st['e1']['joint_percent']:.1f} % (with the spots), size +- "
          f"{st['size']['flats_percent']:.1f} % -> +- {st['size']['joint_percent']:.1f} %")
    for row in plan["rows"]:
        print(f"  {row['text']}")
    return 0


def add_spot_plan_parser(subparsers):
    """Add ``spot-plan`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    def default(name):
        return library_default(SpotDesign, name)

    sp = subparsers.add_parser(
        "spot-plan", help="spots and exposures a lab needs to state the corrected e1 and size "
                          "slopes to a goal, from a calibrate --spots fit's stated precision")
    sp.add_argument("calibration", metavar="CALIBRATION_JSON",
                    help="the output of bfdrift calibrate ... --spots ... --json")
    sp.add_argument("images", nargs="+", metavar="SPOT_IMAGE",
                    help="the fitted spot series' images (its levels, spot size and spots)")
    sp.add_argument("--series", help="the fitted series planned from (its name in the JSON; "
                                     "needed when several were fitted)")
    sp.add_argument("--goal-e1", type=float, nargs="+", default=list(PLAN_GOALS["e1"]),
                    metavar="PERCENT", help="goal standard deviations of the corrected e1 "
                    "slope (%% of the e1 slope the flats template removes)")
    sp.add_argument("--goal-size", type=float, nargs="+", default=list(PLAN_GOALS["size"]),
                    metavar="PERCENT", help="goal standard deviations of the corrected size "
                    "slope (%% of the uncorrected size slope)")
    sp.add_argument("--read-noise", type=float, default=default("read_noise"),
                    help="read noise of the spot images (e rms)")
    sp.add_argument("--background", type=float, default=default("background"),
                    help="background of the spot images (e per pixel)")
    sp.add_argument("--sigma", type=float, nargs="+", metavar="PX",
                    help="also plan for these spot sigmas (px), levels from the series' "
                         "faintest to a peak pixel of --peak-max")
    sp.add_argument("--peak-max", type=float,
                    default=library_default(SpotDesign.saturating, "peak_max"),
                    help="with --sigma: peak pixel of the brightest level (e)")
    sp.add_argument("--template", help="with --sigma: the template whose slopes scale the "
                                       "information of other spot sizes (default: the "
                                       "calibration's --out)")
    sp.add_argument("--gain", type=float, default=library_default(SpotSeries, "gain"),
                    help="e/ADU of images in ADU without a GAIN keyword")
    sp.add_argument("--saturation", type=float,
                    default=library_default(SpotSeries, "saturation"),
                    help="saturation level (image unit; default: SATURATE keyword)")
    add_common_options(sp, "json", "quiet")
    sp.set_defaults(func=cmd_spot_plan)
    return sp
