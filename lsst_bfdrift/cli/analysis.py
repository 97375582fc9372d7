"""The ``bfdrift`` commands that measure and tune: calibrate, ptc, diagnose,
validate-sky, validate-stars and reproduce (their options: :mod:`lsst_bfdrift.cli.main`)."""

import json
import os

from lsst_bfdrift.cli._common import (_check_output_dir, _check_outputs, _emit, _load_template,
                                      _print_json, _save_plot, _template_input)
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.utils.errors import InputError, InputNotFoundError
from lsst_bfdrift.utils.io import atomic_output, data_files

__all__ = []


def _cmd_calibrate(args):
    from lsst_bfdrift.ptc.inputs import read_calibration_input
    from lsst_bfdrift.calibration.tuning import calibrate, measured_acoeffs

    stars_plot = None
    if args.plot and args.stars:
        root, ext = os.path.splitext(args.plot)
        stars_plot = root + "_stars" + (ext or ".png")
    _check_outputs(args, args.input + (args.stars or []),
                   {"--out": args.out, "--plot": args.plot, "--plot (stars)": stars_plot})
    for x in args.stars or []:
        if not os.path.isfile(x):
            raise InputNotFoundError(f"--stars {x}: no such file")
    from lsst_bfdrift.calibration.star_fit import check_size_goal
    check_size_goal(args.size_goal, "--size-goal")  # before any file is read
    data = read_calibration_input(args.input, max_lag=args.max_lag)
    table = measured_acoeffs(data)
    res = calibrate(table, free=args.free, refine=not args.no_refine,
                    allow_poor_fit=args.allow_poor_fit, max_chi2_dof=args.max_chi2_dof,
                    progress=not args.quiet)
    res.template.meta["calibration"]["inputs"] = [os.path.abspath(x) for x in args.input]
    joint = None
    if args.stars:
        from lsst_bfdrift.calibration.star_fit import calibrate_with_stars
        joint = calibrate_with_stars(res, [os.path.abspath(x) for x in args.stars],
                                     holdout=args.holdout, gain=args.gain,
                                     flats_uncertainty=not args.model_directions_only,
                                     fitted_slopes=args.fit_slopes,
                                     size_goal=args.size_goal,
                                     progress=not args.quiet)
        joint.template.meta["calibration"]["inputs"] = \
            [os.path.abspath(x) for x in args.input + args.stars]
        joint.template.save(args.out, overwrite=args.overwrite)
    else:
        res.template.save(args.out, overwrite=args.overwrite)
    summary = res.summary()
    if joint is not None:
        summary["stars"] = joint.summary()
    summary["input"] = data.summary()
    summary["out"] = os.path.abspath(args.out)
    if args.plot:
        from lsst_bfdrift.calibration.plots import plot_calibration, plot_star_calibration
        _save_plot(plot_calibration(res), args.plot, summary)
        if joint is not None:  # a second figure next to the first: NAME_stars.png
            _save_plot(plot_star_calibration(joint), stars_plot)
            summary["plot_stars"] = os.path.abspath(stars_plot)
    if args.json:
        _print_json(summary)
        return 0
    f = res.fit
    print(f"calibrated {table.source}: {len(f.names)} parameters chosen by the data")
    for n in f.names:
        print(f"  {n:>18s} = {f.values[n]:.6g} +- {f.errors[n]:.2g}"
              + ("  (at its bound)" if n in f.at_bound else ""))
    print(f"  chi2 = {f.chi2:.2f} for {f.dof} dof (p = {f.p_value:.3g}); worst lags: "
          + ", ".join(f"a{i}{j} {p:+.1f} sigma" for (i, j), p in f.worst(3)))
    sr = res.sum_rule
    print(f"  sum rule: sum a_ij = {sr['sum']:+.3e} +- {sr['error']:.1e} per e")
    if data.kind == "flats":
        print(f"  input: {len(data.pairs_used)} flat pair(s) used at {data.n_levels} level(s); "
              f"dropped: {_dropped_text(data.pairs_dropped) or 'none'}")
    if joint is None:
        print(f"  template: {args.out} ({'areas refined to the data' if res.refined else 'model'})"
              f" in {res.seconds['total']:.1f} s")
        return 0
    c2 = joint.chi2
    print(f"  with {len(args.stars)} star field(s): directions {', '.join(joint.directions)}; "
          f"chi2 a-matrix {c2['flats_only']['amatrix']:.1f} -> {c2['joint']['amatrix']:.1f}, "
          f"star slopes {c2['flats_only']['stars']:.1f} -> {c2['joint']['stars']:.1f}; "
          + joint.tension_line())
    for n, v in joint.star_information.items():
        cf = joint.coefficients[n]
        print(f"  {n:>18s} {cf['parameter_change']:+.3g} +- {cf['parameter_change_err']:.2g} "
              f"(stars give {100 * v:.0f} % of its information)")
    if joint.uncertainty:
        print("  " + joint.uncertainty_line())
    for w in joint.warnings:
        print(f"  warning: {w}")
    print("  " + joint.held_out_table().replace("\n", "\n  "))
    print(f"  template: {args.out} (a-matrix and stars) in "
          f"{res.seconds['total'] + joint.seconds['total']:.1f} s")
    return 0


def _cmd_ptc(args):
    from lsst_bfdrift.ptc import covariances as ptc
    files = list(args.files)
    if len(files) == 1 and os.path.isdir(files[0]):  # its FITS flats, never a .tmp-* leftover
        files = data_files(files[0], (".fits", ".fit", ".fits.gz"))
    if len(files) == 1 and not files[0].lower().endswith((".fits", ".fit", ".fits.gz")):
        mu, var = ptc.read_ptc_text(files[0])
        fit = ptc.fit_ptc_exponential(mu, var)
        out = {"input": files[0], "model": "exponential C00 (Astier et al. 2019 eq. 16)",
               "gain": fit["gain"], "gain_err": fit["gain_err"], "a00": fit["a00"],
               "a00_err": fit["a00_err"], "noise_e2": fit["noise"],
               "noise_e2_err": fit["noise_err"], "npoints": fit["npoints"],
               "mu_max": fit["mu_max"], "chi2": fit["chi2"], "dof": fit["dof"]}
        for k in ("a01", "a10", "a11"):
            out[k] = out[k + "_err"] = None  # a variance-only PTC does not constrain them
    else:
        if args.max_lag < 1:
            raise InputError(f"--max-lag must be >= 1 for FITS flats (the model's a01 and a10 "
                             f"need lag 1), got {args.max_lag}")
        # the reader of `bfdrift calibrate`: pairs by EXPTIME, masks, turn-off
        from lsst_bfdrift.ptc.inputs import read_calibration_input
        data = read_calibration_input(files, max_lag=args.max_lag)
        if data.kind != "flats":
            raise InputError(f"{files[0]}: a {data.kind} input; bfdrift ptc takes one PTC text "
                             "file or FITS flat pairs")
        table = {"mu": data.mu, "cov": data.cov, "npix": data.npix}
        fit = ptc.fit_covariance_model(table["mu"], table["cov"], npix=table["npix"])
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
                       f"{data.n_levels} level(s)",
                       pairs_dropped=_dropped_text(out["pairs_dropped"]) or "none",
                       notes="; ".join(out["notes"]) or "none")
    return _emit(out, args.json, 14)


def _dropped_text(dropped):
    """One line per dropped pair or file: which and why."""
    return "; ".join(f"{', '.join(os.path.basename(f) for f in d.get('files', []))} "
                     f"({d['reason']})" if d.get("files") else d["reason"] for d in dropped)


def _cmd_validate_stars(args):
    from lsst_bfdrift.templates.template import DistortionTemplate
    from lsst_bfdrift.validation.stars import draw_star_pairs, validate_stars
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
        _print_json(out)
    else:
        for k, v in res.items():
            paired = ("" if "size_slope_minus_astier23" not in v else
                      f"  paired minus astier23 {v['size_slope_minus_astier23']:+.2e} +- "
                      f"{v['size_slope_minus_astier23_err']:.1e}")
            print(f"{k:12s} size slope {v['size_slope']:+.2e} +- {v['size_slope_err']:.1e}  "
                  f"e1 slope {v['e_slope']:+.2e} +- {v['e_slope_err']:.1e}{paired}")
    return 0


def _cmd_reproduce(args):
    from lsst_bfdrift.utils.progress import ProgressBar
    from lsst_bfdrift.validation.paper_figures import reproduce, write_figures
    _check_output_dir(args, args.out, "--out")
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
    return _emit(numbers, args.json, 20)


def _cmd_validate_sky(args):
    from lsst_bfdrift.validation.sky import validate_sky
    _check_outputs(args, [args.image, None if args.galsim_sensor else
                          _template_input(args.template)],
                   {"--catalog": args.catalog, "--plot": args.plot})
    if args.galsim_sensor:
        tpl = import_galsim_sensor(args.galsim_sensor)
    else:
        tpl = _load_template(args.template)
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
        from lsst_bfdrift.validation.plots import plot_sky_validation
        _save_plot(plot_sky_validation(res), args.plot, out)
    if args.json:
        _print_json(out)
    else:
        print(out["verdict"])
    return 0


def _cmd_diagnose(args):
    from lsst_bfdrift.calibration.acoeff_model import LinearBasis, load_default_basis
    from lsst_bfdrift.diagnosis.effects_fit import diagnose, load_input

    _check_output_dir(args, args.report, "--report", inputs=[args.input])
    obs = load_input(args.input, max_lag=args.max_lag)
    if args.basis:
        with open(args.basis) as fh:
            basis = LinearBasis.from_dict(json.load(fh))
    else:
        basis = load_default_basis()
    d = diagnose(obs, basis).as_dict()
    d["input"] = args.input
    if getattr(args, "template_change", True) and d["effects_added"]:
        from lsst_bfdrift.diagnosis.consequence import template_change
        d["template_change"] = template_change(d, None if obs.kind == "ptc" else basis,
                                               max_lag=min(args.max_lag, basis.max_lag))
    if args.report:
        from lsst_bfdrift.diagnosis.report import write_report
        d["report_files"] = write_report(d, args.report)
    if args.json:
        _print_json(d)
    else:
        for s in d["steps"]:
            print(f"{s['label']:>24s}: chi2/dof {s['chi2_dof']:.3f}, rms pull {s['rms_pull']:.3f}")
        print(f"{'effects added':>24s}: {', '.join(d['effects_added']) or 'none'}")
        from lsst_bfdrift.diagnosis.report import notable_not_excluded
        for x in notable_not_excluded(d):
            print(f"{'not excluded':>24s}: {x['effect']} would move a00 by "
                  f"{x['a00_shift_sd']:+.1f} sigma, a01 by {x['a01_shift_sd']:+.1f} sigma "
                  f"(a00 {x['a00'][0]:.4g} +- {x['a00'][1]:.2g} with it free)")
        print(d["verdict"])
        tc = d.get("template_change")
        if tc:
            from lsst_bfdrift.diagnosis.report import template_change_lines
            print("\n".join(template_change_lines(tc)))
    return 0
