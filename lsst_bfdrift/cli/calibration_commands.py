"""``bfdrift calibrate``, ``bfdrift ptc`` and ``bfdrift diagnose``: the commands
on flats and a-matrices (options and commands).

The options' defaults are those of the functions they feed
(:func:`~lsst_bfdrift.ptc.inputs.read_calibration_input`,
:func:`~lsst_bfdrift.calibration.tuning.calibrate`,
:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`,
:func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`,
:func:`~lsst_bfdrift.diagnosis.effects_fit.load_input`), except where a
comment says why not.
"""

import argparse
import json
import os
import sys
import warnings

from astropy.io import fits

from lsst_bfdrift.calibration.acoeff_model import LinearBasis, load_default_basis
from lsst_bfdrift.calibration.band_transfer import band_a00_table, calibrated_band_templates
from lsst_bfdrift.calibration.lsst_products import write_bfk, write_distortion_matrix
from lsst_bfdrift.calibration.routes import MODELS, calibrate_route
from lsst_bfdrift.calibration.spot_fit import (SPOT_SPLITS, calibrate_with_spots,
                                               check_spot_fields, read_spot_fields)
from lsst_bfdrift.calibration.star_fit import calibrate_with_stars, check_size_goal
from lsst_bfdrift.calibration.fit_model import CANDIDATES, MODEL_NUMERICS
from lsst_bfdrift.calibration.tuning import CalibrationWarning, calibrate, measured_acoeffs
from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.cli._common import (add_common_options, check_output_dir, check_outputs, emit,
                                      library_default, print_json, save_plot)
from lsst_bfdrift.diagnosis import consequence
from lsst_bfdrift.diagnosis.effects_fit import diagnose, load_input
from lsst_bfdrift.diagnosis.report import (notable_not_excluded, template_change_lines,
                                           write_report)
from lsst_bfdrift.ptc import covariances as ptc
from lsst_bfdrift.ptc.full_model import fit_covariance_model
from lsst_bfdrift.ptc.data import describe_paths
from lsst_bfdrift.ptc.inputs import ExposureLevelWarning, read_calibration_input, read_ptc_file
from lsst_bfdrift.correction.task import BAND_KEYWORDS, exposure_band
from lsst_bfdrift.physics.absorption import check_temperature
from lsst_bfdrift.physics.depth import normalize_band
from lsst_bfdrift.utils.errors import InputError, InputFileError, InputNotFoundError
from lsst_bfdrift.utils.io import data_files, not_fits_reason
from lsst_bfdrift.utils.progress import Activity, ProgressBar

__all__ = ["add_calibrate_parser", "add_ptc_parser", "add_diagnose_parser", "cmd_calibrate",
           "cmd_ptc", "cmd_diagnose", "PTC_MAX_LAG", "read_with_progress", "fit_with_progress"]

#: Largest lag of ``bfdrift ptc`` on FITS flats unless ``--max-lag`` is given:
#: the command reports a00..a11 and the full model's fit to these lags, not the
#: lags to 8 that ``calibrate`` reads (read_calibration_input's default).
PTC_MAX_LAG = 3

#: Relative error of the near-field response S1 above which ``calibrate`` says
#: that its data leave S1 (and so the stars' size correction) to the model.
NEAR_FIELD_NOTE = 0.1


def read_with_progress(command, files, *, quiet=False, **kwargs):
    """:func:`~lsst_bfdrift.ptc.inputs.read_calibration_input` with the progress of
    reading flats (``COMMAND: reading N flats, covariances of their pairs``, from
    the first file on) and its warnings said at once on stderr (flat levels not
    proportional to EXPTIME), before any fit.

    Parameters
    ----------
    command : str
        The command's name, for the label and the warnings.
    files : list of str
        The inputs.
    quiet : bool, optional
        No progress bar (the warnings are still said).
    **kwargs
        Passed to ``read_calibration_input``.

    Returns
    -------
    CalibrationData
    """
    bar = ProgressBar(1, f"{command}: reading {len(files)} flats, covariances of their pairs",
                      enabled=not quiet)

    def progress(done, total):
        if bar.total != total:
            bar.total = max(int(total), 1)
        if done == 0 and bar.done == 0:
            bar.show()
        bar(done - bar.done)

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", ExposureLevelWarning)
        try:
            data = read_calibration_input(files, progress=progress, **kwargs)
        except BaseException:
            bar.fail()
            raise
        finally:
            if bar.done:
                bar.__exit__(None, None, None)
    for w in caught:
        if issubclass(w.category, ExposureLevelWarning):
            print(f"bfdrift {command}: warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    return data


def fit_with_progress(command, data, *, quiet=False):
    """:func:`~lsst_bfdrift.calibration.tuning.measured_acoeffs` saying what runs
    (``COMMAND: covariance model fit (b_ij free and fixed) ...``, then its time
    and model and Jacobian evaluations; silent for inputs that need no fit).

    Parameters
    ----------
    command : str
        The command's name, for the label.
    data : CalibrationData
    quiet : bool, optional
        Nothing on stderr.

    Returns
    -------
    AcoeffTable
    """
    with Activity(f"{command}: covariance model fit (Astier et al. 2019; b_ij fixed, then "
                  "free)", unit="model and Jacobian evaluations", enabled=not quiet) as act:
        return measured_acoeffs(data, progress=act)


def _dropped_text(dropped):
    """One entry per dropped pair or file (which and why); PTC points grouped by reason."""
    parts, points = [], {}
    for d in dropped:
        if d.get("files"):
            parts.append(f"{', '.join(os.path.basename(f) for f in d['files'])} "
                         f"({d['reason']})")
        elif "mu" in d:
            points.setdefault(d["reason"], []).append(d["mu"])
        else:
            parts.append(d["reason"])
    for reason, mu in points.items():
        at = f"mean {mu[0]:.6g}" if len(mu) == 1 else f"means {min(mu):.6g}..{max(mu):.6g}"
        parts.append(f"{len(mu)} point(s) at {at} ({reason})")
    return "; ".join(parts)


def _print_calibration(args, res, joint, data, table):
    """The text report of ``calibrate`` (without ``--json``)."""
    f = res.fit
    print(f"calibrated {table.source}: {len(f.names)} parameters chosen by the data")
    for n in f.names:
        print(f"  {n:>18s} = {f.values[n]:.6g} +- {f.errors[n]:.2g}"
              + ("  (at its bound)" if n in f.at_bound else ""))
    print(f"  chi2 = {f.chi2:.2f} for {f.dof} dof (p = {f.p_value:.3g}); worst lags: "
          + ", ".join(f"a{i}{j} {p:+.1f} sigma" for (i, j), p in f.worst(3)))
    sr = res.sum_rule
    print(f"  sum rule: sum a_ij = {sr['sum']:+.3e} +- {sr['error']:.1e} per e")
    nf = res.near_field
    if nf is not None:
        rel = "" if nf["relative_error"] is None else f" ({100 * nf['relative_error']:.0f} %)"
        print(f"  near field S1 = a00 + 2 (a01 + a10) + 4 a11 (sets the stars' size correction): "
              f"data {nf['data']:+.3e} +- {nf['error']:.1e}{rel}, model {nf['model']:+.3e}"
              + ("" if nf["template"] is None else f", template {nf['template']:+.3e}")
              + " per e")
        if nf["relative_error"] is not None and nf["relative_error"] > NEAR_FIELD_NOTE:
            print(f"  note: this a-matrix measures S1 to {100 * nf['relative_error']:.0f} %; the "
                  "template's comes mostly from the model, and the stars' size slope left "
                  "follows it (about 0.7-1 % per 1 % of S1): star fields (--stars) or spots "
                  "(--spots) measure it")
    if data.kind == "flats":
        print(f"  input: {len(data.pairs_used)} flat pair(s) used at {data.n_levels} level(s); "
              f"dropped: {_dropped_text(data.pairs_dropped) or 'none'}")
    if joint is None:
        print(f"  template: {args.out} ({'areas refined to the data' if res.refined else 'model'})"
              f" in {res.seconds['total']:.1f} s")
        unc = ((res.template.meta.get("calibration") or {}).get("uncertainty") or {}
               if res.template is not None else {})
        modes = (unc.get("parameter_modes") or {}).get("kept")
        if modes:
            print(f"  uncertainty stored: the a_ij errors and {len(modes)} parameter mode(s) "
                  "beyond the areas (how area changes divide between column and row edges, "
                  "which sets the e1 stars keep and no a-matrix measures; spots or star fields "
                  "measure it)")
        return
    c2 = joint.chi2
    what = " and ".join(w for w in (
        f"{len(args.stars)} star field(s)" if args.stars else "",
        f"{len(args.spots)} spot series" if args.spots else "") if w)
    print(f"  with {what}: directions {', '.join(joint.directions) or 'none'}; "
          f"chi2 a-matrix {c2['flats_only']['amatrix']:.1f} -> {c2['joint']['amatrix']:.1f}, "
          f"{'spot and star' if args.spots else 'star'} slopes "
          f"{c2['flats_only']['stars']:.1f} -> {c2['joint']['stars']:.1f}; "
          + joint.tension_line())
    for fld in joint.fields:
        b = fld.get("correction_bias")
        if b:
            print(f"  {fld['name']}: asked to keep the correction's own slopes on its design "
                  "(per 1e5 e): " + ", ".join(f"{q} {v[0]:+.2e} +- {v[1]:.1e}"
                                               for q, v in b.items()))
    for n, v in joint.star_information.items():
        cf = joint.coefficients[n]
        print(f"  {n:>18s} {cf['parameter_change']:+.3g} +- {cf['parameter_change_err']:.2g} "
              f"({'spots and stars' if args.spots else 'stars'} give {100 * v:.0f} % of its "
              "information)")
    if joint.uncertainty:
        print("  " + joint.uncertainty_line())
    for w in joint.warnings:
        print(f"  warning: {w}")
    print("  " + joint.held_out_table().replace("\n", "\n  "))
    print(f"  template: {args.out} (a-matrix and {what}) in "
          f"{res.seconds['total'] + joint.seconds['total']:.1f} s")


def cmd_calibrate(args):
    """``bfdrift calibrate``: the model tuned to a sensor's flats (and star fields).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    stars_plot = None
    spot_files = [x for group in args.spots or [] for x in group]
    kind = "spots" if spot_files else "stars"
    if args.plot and (args.stars or spot_files):
        root, ext = os.path.splitext(args.plot)
        stars_plot = root + f"_{kind}" + (ext or ".png")
    check_outputs(args, args.input + (args.stars or []) + spot_files,
                  {"--out": args.out, "--plot": args.plot, f"--plot ({kind})": stars_plot})
    check_size_goal(args.size_goal, "--size-goal")  # before any file is read
    _check_model_options(args)
    flats_band = _flats_band(args)  # before minutes of fitting
    if args.temperature is not None:
        if flats_band is None:
            raise InputError("--temperature sets the absorption lengths of the per-band "
                             "templates: give --band (the flats' band) as well")
        check_temperature(args.temperature)  # before minutes of fitting
    for opt, files in (("--stars", args.stars or []), ("--spots", spot_files)):
        for x in files:
            if not os.path.isfile(x):
                raise InputNotFoundError(f"{opt} {x}: no such file")
            reason = not_fits_reason(x)  # before minutes of fitting the flats
            if reason is not None:
                what = "a star field" if opt == "--stars" else "a spot image"
                raise InputFileError(f"{opt} {x}: {reason}; accepted: a FITS image of {what}", x)
    spot_fields = _spot_fields(args) if spot_files else None  # refused before the flats
    data = read_with_progress("calibrate", args.input, quiet=args.quiet, max_lag=args.max_lag)
    table = fit_with_progress("calibrate", data, quiet=args.quiet)
    if args.model != "electrostatic":
        return _lsst_route(args, data, table)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", CalibrationWarning)
        res = calibrate(table, free=args.free, refine=not args.no_refine,
                        allow_poor_fit=args.allow_poor_fit, max_chi2_dof=args.max_chi2_dof,
                        max_evaluations=args.max_evaluations, progress=not args.quiet,
                        model_settings=MODEL_NUMERICS[args.model_numerics],
                        # a joint (stars, spots) template does not carry the modes
                        modes=not (args.no_parameter_modes or args.stars or args.spots))
    for w in caught:  # a poor physics fit: written, with the misfit in its uncertainty
        if issubclass(w.category, CalibrationWarning):
            print(f"bfdrift calibrate: warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    res.template.meta["calibration"]["inputs"] = [os.path.abspath(x) for x in args.input]
    joint = None
    stars = [os.path.abspath(x) for x in args.stars or []]
    if spot_fields:
        joint = calibrate_with_spots(res, spot_fields, stars=stars, holdout=args.holdout,
                                     gain=args.gain,
                                     flats_uncertainty=not args.model_directions_only,
                                     fitted_slopes=args.fit_slopes, size_goal=args.size_goal,
                                     correction_bias=args.spot_correction_bias,
                                     progress=not args.quiet)
    elif stars:
        joint = calibrate_with_stars(res, stars, holdout=args.holdout, gain=args.gain,
                                     flats_uncertainty=not args.model_directions_only,
                                     fitted_slopes=args.fit_slopes,
                                     size_goal=args.size_goal,
                                     progress=not args.quiet)
    if joint is not None:
        joint.template.meta["calibration"]["inputs"] = \
            [os.path.abspath(x) for x in args.input + (args.stars or []) + spot_files]
    final = res.template if joint is None else joint.template
    bands = None
    if flats_band is None:
        final.save(args.out, overwrite=args.overwrite)
    else:
        bands = calibrated_band_templates(final, flats_band, fit=res.fit, nodes=args.band_nodes,
                                          temperature=args.temperature,
                                          progress=not args.quiet)
        bands.save(args.out, overwrite=args.overwrite)
    summary = res.summary()
    if bands is not None:
        summary["bands"] = {"flats": flats_band, "a00": band_a00_table(bands)}
    if joint is not None:
        summary[kind] = joint.summary()
    summary["input"] = data.summary()
    summary["out"] = os.path.abspath(args.out)
    if args.plot:
        # matplotlib: calibration.plots imports it; only when --plot is given
        from lsst_bfdrift.calibration.plots import plot_calibration, plot_star_calibration
        save_plot(plot_calibration(res), args.plot, summary)
        if joint is not None:  # a second figure next to the first: NAME_stars.png (_spots)
            save_plot(plot_star_calibration(joint), stars_plot)
            summary[f"plot_{kind}"] = os.path.abspath(stars_plot)
    if args.json:
        print_json(summary)
    else:
        _print_calibration(args, res, joint, data, table)
        if bands is not None:
            _print_bands(summary["bands"])
    return 0


def _print_bands(info):
    """The per-band a00 of ``calibrate --band`` (text output)."""
    print(f"  bands (flats in {info['flats']}): a00 per band, 1/e, with its error from the "
          "calibration (and from the parameter covariance)")
    for band, row in info["a00"].items():
        err = "" if row["a00_err"] is None else f" +- {row['a00_err']:.2g}"
        perr = "" if row["a00_err_params"] is None else \
            f" (parameters: +- {row['a00_err_params']:.2g})"
        print(f"  {band:>6s}: a00 {row['a00']:.4g}{err}{perr}, {row['ratio_a00']:.4f} x the "
              f"flats' band, mean conversion height {row['mean_height']:.1f} um")


def _flats_band(args):
    """The band of ``--band``: a band name, or 'header' (FILTER/BAND of the inputs); None."""
    if args.band is None:
        return None
    if args.band.strip().lower() != "header":
        return normalize_band(args.band)
    found = {}
    for path in args.input:
        reason = not_fits_reason(path) if os.path.isfile(path) else "no such file"
        if reason is not None:
            raise InputError(f"--band header reads the FILTER or BAND keyword of FITS flats; "
                             f"{path}: {reason}; give the band (--band r)")
        with fits.open(path) as hdul:
            headers = [h.header for h in hdul if h.is_image][:2]
        meta = {}
        for h in reversed(headers):  # the image HDU's value over the primary's
            meta.update({k: h[k] for k in BAND_KEYWORDS if k in h})
        band, _ = exposure_band(meta)
        if band is None:
            raise InputError(f"--band header: {path} has no {' or '.join(BAND_KEYWORDS)} "
                             "keyword; give the band (--band r)")
        found[path] = band
    if len(set(found.values())) > 1:
        raise InputError("--band header: the flats are of different bands ("
                         + ", ".join(f"{os.path.basename(p)}: {b}" for p, b in found.items())
                         + "); calibrate one band at a time")
    return next(iter(found.values()))


def _spot_fields(args):
    """The ``--spots`` series, read, measured and checked against ``--holdout`` (the
    refusals come before the flats are read)."""
    series = [SpotSeries(group, gain=args.gain, saturation=args.spot_saturation,
                         gain_name="--gain", saturation_name="--spot-saturation",
                         progress=not args.quiet) for group in args.spots]
    fields = read_spot_fields(series, fitted_slopes=args.spot_fit_slopes,
                              split_by=args.spot_split, min_spots=args.min_spots)
    check_spot_fields(fields, args.holdout, n_stars=len(args.stars or []))
    return fields


def _check_model_options(args):
    """Refuse options that ``--model`` astier23 or coulton18 would ignore (before any
    file is read), and ``--product`` with the package's own route."""
    if args.model == "electrostatic":
        if args.product:
            raise InputError("--product writes LSST's product of --model astier23 "
                             "(electroBfDistortionMatrix) or coulton18 (bfk); --model "
                             "electrostatic writes its template only (--out)")
        return
    given = [opt for opt, on in (("--stars", bool(args.stars)), ("--spots", bool(args.spots)),
                                 ("--free", bool(args.free)),
                                 ("--no-refine", args.no_refine),
                                 ("--no-parameter-modes", args.no_parameter_modes),
                                 ("--allow-poor-fit", args.allow_poor_fit),
                                 ("--band", args.band is not None)) if on]
    if given:
        raise InputError(f"{', '.join(given)}: options of --model electrostatic (this "
                         f"package's model); --model {args.model} is LSST's route and has none "
                         "of them")
    if args.product:
        check_outputs(args, args.input, {"--product": args.product})


def _lsst_route(args, data, table):
    """``calibrate --model astier23|coulton18``: LSST's route from the same a-matrix."""
    route = calibrate_route(table, args.model)
    tpl = route.template
    tpl.meta["calibration"] = {"source": table.source, "route": args.model,
                               "chi2": float(route.chi2), "dof": int(route.dof),
                               "inputs": [os.path.abspath(x) for x in args.input]}
    tpl.save(args.out, overwrite=args.overwrite)
    if args.product:
        if args.model == "astier23":
            write_distortion_matrix(args.product, route.product, overwrite=args.overwrite,
                                    inputs=args.input)
        else:
            write_bfk(args.product, route.product.kernel, overwrite=args.overwrite,
                      inputs=args.input)
    summary = {"model": args.model, **route.summary(), "input": data.summary(),
               "out": os.path.abspath(args.out),
               "product": None if not args.product else os.path.abspath(args.product)}
    if args.model == "astier23":
        m = route.product
        summary["parameters"] = {k: {"value": m.fit_params[k],
                                     "error": m.fit_errors.get(k, 0.0)} for k in m.free_params}
    if args.json:
        print_json(summary)
        return 0
    what = {"astier23": "the Astier & Regnault 2023 model (LSST's DP2 route)",
            "coulton18": "the kernel of the measured a-matrix (LSST's DP1 route)"}[args.model]
    print(f"calibrated {table.source} with {what}")
    if args.model == "astier23":
        for k, v in summary["parameters"].items():
            print(f"  {k:>8s} = {v['value']:.6g} +- {v['error']:.2g}")
        print(f"  chi2 = {route.chi2:.2f} for {route.dof} dof")
    print(f"  template: {args.out} (correct with --method {route.method})"
          + (f"; LSST product: {args.product}" if args.product else ""))
    return 0


def cmd_ptc(args):
    """``bfdrift ptc``: photon transfer fit of a PTC text file or of FITS flat pairs.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    files = list(args.files)
    if len(files) == 1 and os.path.isdir(files[0]):  # its FITS flats, never a .tmp-* leftover
        files = data_files(files[0], (".fits", ".fit", ".fits.gz"))
    if len(files) == 1 and not files[0].lower().endswith((".fits", ".fit", ".fits.gz")):
        # the reader of `bfdrift calibrate`: the turn-off cut, each dropped point's reason,
        # and as many points as the exponential fit needs
        data = read_ptc_file(files[0], min_levels=ptc.MIN_PTC_POINTS)
        fit = _named_fit(files[0], ptc.fit_ptc_exponential, data.mu, data.var, mu_max=None)
        out = {"input": files[0], "model": "exponential C00 (Astier et al. 2019 eq. 16)",
               "gain": fit["gain"], "gain_err": fit["gain_err"], "a00": fit["a00"],
               "a00_err": fit["a00_err"], "noise_e2": fit["noise"],
               "noise_e2_err": fit["noise_err"], "npoints": fit["npoints"],
               "mu_max": fit["mu_max"], "chi2": fit["chi2"], "dof": fit["dof"],
               "points_dropped": data.summary()["pairs_dropped"], "notes": data.notes}
        for k in ("a01", "a10", "a11"):
            out[k] = out[k + "_err"] = None  # a variance-only PTC does not constrain them
    else:
        if args.max_lag < 1:
            raise InputError(f"--max-lag must be >= 1 for FITS flats (the model's a01 and a10 "
                             f"need lag 1), got {args.max_lag}")
        # the reader of `bfdrift calibrate`: pairs by EXPTIME, masks, turn-off; as many
        # levels as the full covariance model needs, or a refusal naming the files and
        # why each dropped pair was dropped
        data = read_with_progress("ptc", files, quiet=args.quiet, max_lag=args.max_lag,
                                  min_levels=ptc.MIN_COVARIANCE_LEVELS)
        if data.kind != "flats":
            raise InputError(f"{files[0]}: a {data.kind} input; bfdrift ptc takes one PTC text "
                             "file or FITS flat pairs")
        table = {"mu": data.mu, "cov": data.cov, "npix": data.npix}
        with Activity("ptc: covariance model fit (Astier et al. 2019; b_ij fixed, then free)",
                      unit="model and Jacobian evaluations", enabled=not args.quiet) as act:
            fit = _named_fit(describe_paths(files), fit_covariance_model, table["mu"],
                             table["cov"], npix=table["npix"], progress=act)
        out = {"input": files, "model": "full covariance model (Astier et al. 2019 eq. 20)",
               "gain": fit["gain"], "gain_err": fit["gain_err"], "npairs": int(data.mu.size),
               "chi2": fit["chi2"], "dof": fit["dof"], "units": data.units,
               "pairs_used": data.summary()["pairs_used"],
               "pairs_dropped": data.summary()["pairs_dropped"], "notes": data.notes}
        for name, (i, j) in (("a00", (0, 0)), ("a01", (0, 1)), ("a10", (1, 0)),
                             ("a11", (1, 1))):
            out[name] = float(fit["a"][i, j])
            out[name + "_err"] = float(fit["a_err"][i, j])
        out["a"] = fit["a"].tolist()
        if not args.json:
            out = dict(out, pairs_used=f"{len(out['pairs_used'])} pair(s) at "
                       f"{data.n_levels} level(s)")
    if not args.json:
        key = "pairs_dropped" if "pairs_dropped" in out else "points_dropped"
        out = dict(out, **{key: _dropped_text(out[key]) or "none"},
                   notes="; ".join(out["notes"]) or "none")
    return emit(out, args.json, 14)


def _named_fit(where, fit, *args, **kwargs):
    """``fit(*args, **kwargs)``, its refusal naming the input ``where``."""
    try:
        return fit(*args, **kwargs)
    except InputError as err:
        msg = str(err)
        raise InputError(msg if msg.startswith(where) else f"{where}: {msg}") from None


def cmd_diagnose(args):
    """``bfdrift diagnose``: where the electrostatic model is wrong, and which effect
    explains it.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_output_dir(args, args.report, "--report", inputs=[args.input])
    obs = load_input(args.input, max_lag=args.max_lag)
    if args.basis:
        with open(args.basis) as fh:
            basis = LinearBasis.from_dict(json.load(fh))
    else:
        basis = load_default_basis()
    d = diagnose(obs, basis).as_dict()
    d["input"] = args.input
    if getattr(args, "template_change", True) and d["effects_added"]:
        d["template_change"] = consequence.template_change(
            d, None if obs.kind == "ptc" else basis, max_lag=min(args.max_lag, basis.max_lag))
    if args.report:
        d["report_files"] = write_report(d, args.report)
    if args.json:
        print_json(d)
        return 0
    for s in d["steps"]:
        print(f"{s['label']:>24s}: chi2/dof {s['chi2_dof']:.3f}, rms pull {s['rms_pull']:.3f}")
    print(f"{'effects added':>24s}: {', '.join(d['effects_added']) or 'none'}")
    for x in notable_not_excluded(d):
        print(f"{'not excluded':>24s}: {x['effect']} would move a00 by "
              f"{x['a00_shift_sd']:+.1f} sigma, a01 by {x['a01_shift_sd']:+.1f} sigma "
              f"(a00 {x['a00'][0]:.4g} +- {x['a00'][1]:.2g} with it free)")
    print(d["verdict"])
    tc = d.get("template_change")
    if tc:
        print("\n".join(template_change_lines(tc)))
    return 0


def add_calibrate_parser(subparsers):
    """Add ``calibrate`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    def stars_default(name):
        return library_default(calibrate_with_stars, name)

    def spots_default(name):
        return library_default(calibrate_with_spots, name)

    ca = subparsers.add_parser("calibrate", help="tune the model to a sensor's data: "
                               "template out")
    ca.add_argument("input", nargs="+", help="flat-pair FITS files (EXPTIME in the header), a "
                    "PTC text file, an a-matrix table (i j a sigma, or ECSV i, j, a, a_err) or "
                    "cp_pipe's PTC dataset FITS")
    ca.add_argument("--out", required=True, help="calibrated template FITS file")
    ca.add_argument("--band", help="band of the flats (u, g, r, i, z, y or a physical filter "
                    "such as r_57), or 'header' (their FILTER or BAND keyword): --out then "
                    "holds templates for all six bands, the calibrated one carried to each by "
                    "the model's conversion depths, with its uncertainty")
    ca.add_argument("--band-nodes", type=int,
                    default=library_default(calibrated_band_templates, "nodes"),
                    help="with --band: conversion heights of the model's band templates "
                    "(each a template build; default: %(default)s)")
    ca.add_argument("--temperature", type=float, metavar="K",
                    default=library_default(calibrated_band_templates, "temperature"),
                    help="with --band: temperature of the sensor (K) for the absorption "
                    "lengths of every band, the flats' included (default: 300 K, GalSim's "
                    "table; an LSST sensor runs at about 173 K)")
    ca.add_argument("--model", choices=MODELS, default=library_default(calibrate_route, "model"),
                    help="electrostatic: this package's model (corrected with --method "
                         "drift); astier23: the Astier & Regnault 2023 model, LSST's DP2 route "
                         "(--method astier23); coulton18: the kernel of the a-matrix, LSST's "
                         "DP1 route (--method coulton18) (default: %(default)s)")
    ca.add_argument("--product", metavar="FILE",
                    help="with --model astier23 or coulton18: also write LSST's product, an "
                         "electroBfDistortionMatrix or a bfk FITS file")
    ca.add_argument("--free", nargs="+", metavar="NAME",
                    default=library_default(calibrate, "free"),
                    help="free parameters (default: chosen by the data from "
                         f"{', '.join(CANDIDATES)})")
    ca.add_argument("--max-lag", type=int,
                    default=library_default(read_calibration_input, "max_lag"),
                    help="largest lag measured from flat pairs (default: %(default)s)")
    ca.add_argument("--no-refine", action="store_true",
                    help="keep the model's areas (default: match them to the measured a_ij)")
    ca.add_argument("--no-parameter-modes", action="store_true",
                    help="store the a_ij errors alone as the template's uncertainty (default: "
                         "also the fitted parameters' modes beyond the areas, two small template "
                         "builds per free parameter; without them templates drawn from the "
                         "uncertainty never vary how area changes divide between column and row "
                         "edges)")
    ca.add_argument("--max-chi2-dof", type=float,
                    default=library_default(calibrate, "max_chi2_dof"),
                    help="a fit above this chi2/dof (and p < 1e-3) is poor: a warning and "
                         "the Birge ratio in the uncertainty, an error with --no-refine "
                         "(default: %(default)s)")
    ca.add_argument("--max-evaluations", type=int,
                    default=library_default(calibrate, "max_evaluations"),
                    help="model evaluations of the physics fit's search, each about 0.6 s "
                         "(default: %(default)s)")
    ca.add_argument("--model-numerics", choices=sorted(MODEL_NUMERICS), default="fit",
                    help="the physics fit's model a_ij: 'fit' (16 uniform samples per edge: "
                         "a10 ~20 %% below its converged value, the default) or 'converged' "
                         "(Chebyshev samples, within ~2 %%, 1.2-1.6x the time; on GalSim's "
                         "sensors it halves the e1 left and leaves more of the size)")
    ca.add_argument("--allow-poor-fit", action="store_true",
                    help="with --no-refine: write the model's template even when it fits "
                         "poorly (refined templates are written with the misfit in their "
                         "uncertainty, and a warning)")
    ca.add_argument("--stars", nargs="+", metavar="EXPOSURE",
                    help="star fields (FITS, electrons or ADU with GAIN) fitted jointly with "
                         "the a-matrix: corrected star size and shape must not depend on flux")
    ca.add_argument("--spots", nargs="+", action="append", metavar="SPOT_IMAGE",
                    help="a spot-projector series (FITS images of one grid at several EXPTIME; "
                         "electrons, or ADU with --gain / GAIN) fitted jointly with the "
                         "a-matrix: corrected spot size and shape must not depend on flux; "
                         "pins the e1 slope (the serial/parallel split no a-matrix sees); "
                         "repeat for several series")
    ca.add_argument("--holdout", choices=("auto", "cross", "split", "last"),
                    default=stars_default("holdout"),
                    help="stars (spots) held out for validation: two-fold cross-validation "
                         "over seeded halves of every field (series), the template fitted to "
                         "all ('cross', and 'auto'); one half fitted, the other held out "
                         "('split'); the last field or series held out ('last') (default: "
                         "%(default)s)")
    ca.add_argument("--spot-split", choices=SPOT_SPLITS, default=spots_default("split_by"),
                    help="with --spots: the halves of a series, its spots (paired by flux) or "
                         "its images (paired by EXPTIME) (default: %(default)s)")
    ca.add_argument("--spot-fit-slopes", nargs="+", choices=("size", "e1", "e2"),
                    default=list(spots_default("spot_slopes")), metavar="SLOPE",
                    help="with --spots: the spot slopes the fit nulls (default: size e1 e2; "
                         "'curl' is always in the fit)")
    ca.add_argument("--no-spot-correction-bias", dest="spot_correction_bias",
                    action="store_false",
                    help="with --spots: ask the fit for zero slopes left on the spots, not for "
                         "what the drift correction leaves on their design with a right "
                         "template (by default simulated photon by photon, up to ~30 s per series: "
                         "about -2 %% of the size slope on spots of sigma 1 px)")
    ca.add_argument("--min-spots", type=int, default=spots_default("min_spots"),
                    help="with --spots: fewest usable spots a series fits (per half with "
                         "cross-validation) (default: %(default)s)")
    ca.add_argument("--spot-saturation", type=float, default=spots_default("saturation"),
                    help="with --spots: saturation level of the spot images (their unit; "
                         "default: SATURATE keyword)")
    ca.add_argument("--gain", type=float, default=stars_default("gain"),
                    help="e/ADU of star fields and spot images in ADU without GAIN")
    ca.add_argument("--model-directions-only", action="store_true",
                    help="with --stars or --spots: move the template along the model's "
                         "directions only, "
                         "not within the a-matrix's errors lag by lag")
    ca.add_argument("--fit-slopes", nargs="+", choices=("size", "e1", "e2"),
                    default=list(stars_default("fitted_slopes")), metavar="SLOPE",
                    help="with --stars: the star slopes the fit nulls (size, e1, e2; default "
                         "size: a field measures e1 to about its own size, so fitting it adds "
                         "noise; the others are reported)")
    ca.add_argument("--size-goal", type=float, default=stars_default("size_goal"),
                    metavar="PERCENT",
                    help="with --stars: the precision of the corrected size slope (%% of the "
                         "uncorrected) the report measures the fit against; short of it, a "
                         "warning says how many fields would reach it (default: %(default)s)")
    ca.add_argument("--plot", help="write a PNG: a_ij against lag, pulls, correlations")
    ca.add_argument("--overwrite", action="store_true",
                    help="replace an existing --out or --plot")
    add_common_options(ca, "json", "quiet")
    ca.set_defaults(func=cmd_calibrate)
    return ca


def add_ptc_parser(subparsers):
    """Add ``ptc`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    pt = subparsers.add_parser("ptc", help="photon transfer curve fit (gain, a_ij)")
    pt.add_argument("files", nargs="+", help="PTC text file, or FITS flats in pairs (files, or "
                    "one directory: its FITS files sorted by name)")
    # not read_calibration_input's 8 (calibrate's): see PTC_MAX_LAG
    pt.add_argument("--max-lag", type=int, default=PTC_MAX_LAG, help="largest covariance lag")
    add_common_options(pt, "json", "quiet")
    pt.set_defaults(func=cmd_ptc)
    return pt


def add_diagnose_parser(subparsers):
    """Add ``diagnose`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    dg = subparsers.add_parser("diagnose", help="residual of the model and the effects "
                               "explaining it")
    dg.add_argument("input", help="a_ij table, PTC text file or directory of flat pairs")
    dg.add_argument("--json", action="store_true")
    dg.add_argument("--report", help="write report.md, diagnosis.json and figures here")
    dg.add_argument("--overwrite", action="store_true")
    dg.add_argument("--basis", help="linearised electrostatic model (JSON; default: the "
                    "shipped fit to the ITL a_ij)")
    dg.add_argument("--max-lag", type=int, default=library_default(load_input, "max_lag"),
                    help="largest lag for flat pairs")
    dg.add_argument("--template-change", action=argparse.BooleanOptionalAction, default=True,
                    help="when an added effect moves the base a_ij by more than 1 sigma, "
                    "calibrate templates without and with it and give what the first would "
                    "leave of the star size and e1 slopes (about a minute; default on)")
    dg.set_defaults(func=cmd_diagnose)
    return dg
