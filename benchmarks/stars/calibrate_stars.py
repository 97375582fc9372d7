"""End to end: calibrate from GalSim flats, and from flats plus a GalSim star field.

For each GalSim sensor model (default lsst_itl_50_8 and lsst_e2v_50_8):

1. **flats**: flat pairs made with GalSim's own pixel-area response and
   Poisson noise (:func:`~lsst_bfdrift.simulation.flats.simulate_flat_pairs`,
   engine 'galsim'), the Astier et al. (2019) fit for a_ij with errors, and
   :func:`~lsst_bfdrift.calibration.tuning.calibrate` (flats-only template).
2. **flats + stars**: sky-like fields of the same sensor drawn by
   galsim.SiliconSensor (:func:`~lsst_bfdrift.simulation.skysim.simulate_star_field`:
   Moffat PSF varying smoothly over the field, fluxes 1e4-1.5e6 e, sky
   through the sensor, no truth; ``--fields`` of them, own seeds), and
   :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars` (all
   stars fitted; the held-out slopes by two-fold cross-validation).
3. **validation on other stars**: GalSim stars of the same sensor with a
   paired no-BF twin (:func:`~lsst_bfdrift.validation.stars.draw_star_pairs`,
   Moffat, their own seed), corrected by drift with the flats-only, the
   flats+stars (the stars move the flats template within the a-matrix's
   errors; ``--model-directions-only``: along the model's directions),
   GalSim's own sensor file (imported with transfer- and with area-matched
   edges) and the bundled default template.
4. **the fields' own bias**: every field's usable stars corrected with
   GalSim's own sensor file (transfer-matched edges), whose paired stars
   are corrected to within 1-2 %: the size slope the fields then show is
   what the star route would pull the template by if the template were
   right (their noise, or a bias of the field measurement).

Prints the held-out field's slopes and the size and e1 slopes left on the
paired stars, as % of the uncorrected slopes, and writes
``benchmarks/stars/calibrate_stars_results.txt`` / ``.json``::

    python benchmarks/stars/calibrate_stars.py [--sensors lsst_itl_50_8 lsst_e2v_50_8]
        [--fields 3 | --fields 4 2] [--field-stars 800] [--field-size 2048] [--n-stars 200]
        [--cache /tmp/cst] [--save-templates /tmp/cs_templates]

Fields are cached in ``--cache``; a field that ``benchmarks/stars/field_twins.py``
drew there with its twin (the same image) is used as is.
``--save-templates DIR`` writes the flats-only and flats+stars templates for
``field_twins.py --templates-from DIR``.
"""

import argparse
import importlib.util
import os
import sys
import time
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.ptc.acoeffs import AcoeffTable  # noqa: E402
from lsst_bfdrift.calibration.star_fit import StarField, calibrate_with_stars  # noqa: E402
from lsst_bfdrift.calibration.tuning import calibrate  # noqa: E402
from lsst_bfdrift.simulation.skysim import simulate_star_field  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402
from lsst_bfdrift.utils.errors import InputError  # noqa: E402
from lsst_bfdrift.validation.stars import per_star_residuals, residual_slopes  # noqa: E402


def _script(folder, name):
    """Another benchmark script, ``benchmarks/FOLDER/NAME.py``, imported by its path
    (the package itself comes from the installed lsst_bfdrift)."""
    spec = importlib.util.spec_from_file_location(name, os.path.join(HERE, "..", folder,
                                                                     name + ".py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# the flats and the paired stars of the sensor calibration (same caches, same seeds)
_calibrate_sensor = _script("calibration", "calibrate_sensor")
FLAT_STEPS = _calibrate_sensor.FLAT_STEPS
flats_table, star_pairs = _calibrate_sensor.flats_table, _calibrate_sensor.star_pairs


def cached_flats(sensor, args):
    path = os.path.join(args.cache, f"flats_{sensor}_{args.flat_size}_{args.pairs_per_level}"
                        f"_{args.flat_steps}_{args.flat_max_lag}.npz")
    if os.path.isfile(path):
        d = np.load(path)
        return AcoeffTable(d["a"], d["a_err"], source=f"GalSim {sensor} flats"), 0.0
    t0 = time.time()
    table, _ = flats_table(sensor, args)
    np.savez(path, a=table.a, a_err=table.sigma)
    return table, time.time() - t0


def field_seed(sensor, k=0):
    """Seed of star field k of a sensor (field 0 keeps the historical seed)."""
    return zlib.crc32((f"field:{sensor}" + (f":{k}" if k else "")).encode()) % 100000


def twin_cache_path(sensor, args, seed):
    """Where ``benchmarks/stars/field_twins.py`` caches a field drawn with its twin."""
    return os.path.join(args.cache, f"twin_{sensor}_{args.field_size}_{args.field_stars}_"
                                    f"{seed}.npz")


def cached_field(sensor, args, k=0):
    """Star field k of a sensor (its own seed, :func:`field_seed`)."""
    seed = field_seed(sensor, k)
    path = os.path.join(args.cache, f"field_{sensor}_{args.field_size}_{args.field_stars}_{seed}.npy")
    if os.path.isfile(path):
        return np.load(path), seed, 0.0
    # the same field drawn with its twin by benchmarks/stars/field_twins.py (identical image)
    twin = twin_cache_path(sensor, args, seed)
    if os.path.isfile(twin):
        return np.load(twin)["bf"], seed, 0.0
    t0 = time.time()
    f = simulate_star_field((args.field_size,) * 2, args.field_stars, sensor=sensor,
                            flux=(1e4, 1.5e6), sky=1000.0, seed=seed, progress=True)
    np.save(path, f["image"])
    return f["image"], seed, time.time() - t0


def ivw_mean(values, errors):
    """Inverse-variance mean, its error and the chi2 about it."""
    v, w = np.asarray(values, float), 1.0 / np.asarray(errors, float) ** 2
    m = float(np.sum(w * v) / np.sum(w))
    return m, float(np.sum(w) ** -0.5), float(np.sum(w * (v - m) ** 2))


def held_out_mean(held_out):
    """Inverse-variance mean over the fields of the held-out size residual, in %
    of each field's uncorrected slope, with the chi2 about it."""
    cells = []
    for what in ("flats_only", "joint"):
        r = np.array([100 * d[what]["size"][0] / d["before"]["size"][0]
                      for d in held_out.values()])
        e = np.array([100 * d[what]["size"][1] / abs(d["before"]["size"][0])
                      for d in held_out.values()])
        m, m_err, chi2 = ivw_mean(r, e)
        cells.append(f"{what} {m:+.1f} +- {m_err:.1f} % (chi2 {chi2:.1f} / {r.size - 1})")
    # what the correction removed (uncorrected minus corrected): the stars' own
    # measurement noise, common to both slopes, cancels in it
    before = np.array([d["before"]["size"][0] for d in held_out.values()])
    e_b = np.array([d["before"]["size"][1] for d in held_out.values()])
    chi2_b = ivw_mean(before, e_b)[2]
    removed = before - np.array([d["flats_only"]["size"][0] for d in held_out.values()])
    return (f"held-out size residual over the {len(held_out)} fields (inverse-variance "
            "mean): " + ", ".join(cells) + f"; uncorrected slope chi2 "
            f"{chi2_b:.1f} / {before.size - 1} about its mean; "
            f"slope removed by the flats-only correction {removed.mean():.3e} per 1e5 e, "
            f"field-to-field rms {removed.std(ddof=1) / abs(removed.mean()):.1%}")


def stated_precision_line(joint, validation):
    """The paired stars' flats+stars residuals against the precision the fit states
    (``uncertainty``'s size and e1 slope sigma, means over the fitted fields), and
    the flat data the e1 target would take at that precision ('' without them).

    The e1 residual is compared in units of each star set's uncorrected size
    slope (the fields' stars are broader than the paired ones, and the e1 slope
    the flats template removes can differ from the paired stars' e1 effect, even
    in sign, when the flats do not pin it)."""
    unc = joint.uncertainty
    if not unc or "drift" not in validation:
        return ""
    sz, e1 = unc["size_slope_sigma"].values(), unc["e1_slope_sigma"].values()
    ss = float(np.mean([v["joint_percent"] for v in sz]))
    field_size = float(np.mean([100 * v["flats"] / v["flats_percent"] for v in sz]))
    se_f, se_j = (float(np.nanmean([v[k] for v in e1])) for k in ("flats_percent",
                                                                  "joint_percent"))
    se_size = 100 * float(np.mean([v["joint"] for v in e1])) / field_size
    d, u = validation["drift"], validation["uncorrected"]
    us = abs(u["size_slope"])
    ps, ps_e = 100 * d["size_slope"] / u["size_slope"], 100 * d["size_slope_err"] / us
    pe, pe_s, pe_se = (100 * d["e_slope"] / u["e_slope"], 100 * d["e_slope"] / us,
                       100 * d["e_slope_err"] / us)
    return (f"paired flats+stars residuals against the fit's stated precision: size "
            f"{ps:+.1f} % (+- {ss:.1f} % stated, {ps / np.hypot(ss, ps_e):+.1f} sigma); e1 "
            f"{pe:+.1f} % of its uncorrected slope, {pe_s:+.2f} % of the uncorrected size slope "
            f"(stated: +- {se_size:.2f} % of the size slope, +- {se_j:.0f} % of the e1 slope the "
            f"flats template removes; {pe_s / np.hypot(se_size, pe_se):+.1f} sigma); e1 known to "
            f"5 % would take the flats' e1 error (+- {se_f:.0f} %) {se_f / 5:.0f} times smaller: "
            f"about {(se_f / 5) ** 2:.0f} times this flat data")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8"])
    ap.add_argument("--field-stars", type=int, default=800)
    ap.add_argument("--field-size", type=int, default=2048)
    ap.add_argument("--fields", type=int, nargs="+", default=[3],
                    help="star fields per sensor (own seeds, the same PSF family; one value, "
                         "or one per sensor)")
    ap.add_argument("--holdout", default="auto", help="held-out stars (calibrate_with_stars)")
    ap.add_argument("--model-directions-only", action="store_true",
                    help="the joint fit moves the template along the model's directions, not "
                         "within the a-matrix's errors (calibrate_with_stars(flats_uncertainty="
                         "False))")
    ap.add_argument("--fitted-slopes", nargs="+", default=["size"],
                    help="star slopes the joint fit nulls (calibrate_with_stars(fitted_slopes=...))")
    ap.add_argument("--n-stars", type=int, default=200)
    ap.add_argument("--flat-size", type=int, default=400)
    ap.add_argument("--pairs-per-level", type=int, default=2)
    ap.add_argument("--flat-max-lag", type=int, nargs="+", default=[5],
                    help="largest lag of the flats' covariances and of the a_ij fitted to them "
                         "(one value, or one per sensor)")
    ap.add_argument("--flat-steps", type=int, default=FLAT_STEPS,
                    help="fill steps of each simulated flat (a_ij are divided by 1 - 1/steps)")
    ap.add_argument("--cache", default="/tmp/cst")
    ap.add_argument("--pairs", default="/tmp/cs_pairs", help="cache prefix of the paired stars")
    ap.add_argument("--out", default=os.path.join(HERE, "calibrate_stars_results"))
    ap.add_argument("--save-templates", metavar="DIR",
                    help="write the flats-only and flats+stars templates to "
                         "DIR/SENSOR_flats.fits and DIR/SENSOR_joint.fits "
                         "(for benchmarks/stars/field_twins.py --templates-from)")
    args = ap.parse_args(argv)
    os.makedirs(args.cache, exist_ok=True)
    lines, out = [], {"sensors": {}, "machine": "2 cores"}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    default = load_default_template()
    lags = args.flat_max_lag
    n_fields = args.fields
    if len(lags) not in (1, len(args.sensors)):
        ap.error("--flat-max-lag: one value, or one per sensor")
    if len(n_fields) not in (1, len(args.sensors)):
        ap.error("--fields: one value, or one per sensor")
    for k_sensor, sensor in enumerate(args.sensors):
        rec = out["sensors"][sensor] = {}
        args.flat_max_lag = lags[k_sensor if len(lags) > 1 else 0]
        args.fields = n_fields[k_sensor if len(n_fields) > 1 else 0]
        table, cost = cached_flats(sensor, args)
        say(f"{sensor}: flats a-matrix (lags <= {table.max_lag})"
            + (f", flats drawn and fitted in {cost:.0f} s" if cost else " (cached)"))
        t0 = time.time()
        res = calibrate(table, allow_poor_fit=True)
        f = res.fit
        say(f"  flats-only: {', '.join(f'{n} = {f.values[n]:.4g}' for n in f.names)}; chi2 "
            f"{f.chi2:.1f} / {f.dof} dof; {time.time() - t0:.0f} s")
        rec["flats"] = res.summary()
        imgs, seeds = [], []
        for k in range(args.fields):
            img, fseed, fcost = cached_field(sensor, args, k)
            imgs.append(img)
            seeds.append(fseed)
            say(f"  star field {k}: {args.field_size}^2, {args.field_stars} stars (seed {fseed})"
                + (f", drawn in {fcost:.0f} s" if fcost else " (cached)"))
        t0 = time.time()
        fields = [StarField(img, name=f"field{k}") for k, img in enumerate(imgs)]
        # the first field's seed: every field's halves stay the same whatever --fields
        joint = calibrate_with_stars(res, fields, seed=seeds[0], holdout=args.holdout,
                                     flats_uncertainty=not args.model_directions_only,
                                     fitted_slopes=args.fitted_slopes,
                                     progress=True)
        say("  flats+stars: directions "
            + (", ".join(f"{n} {c['parameter_change']:+.3g} +- {c['parameter_change_err']:.2g}"
                         for n, c in joint.coefficients.items())
               or "none (none lowers the chi2 by ln N)")
            + f"; chi2 a-matrix {joint.chi2['flats_only']['amatrix']:.1f} -> "
            f"{joint.chi2['joint']['amatrix']:.1f} ({joint.chi2['n_amatrix']} lags), stars "
            f"{joint.chi2['flats_only']['stars']:.1f} -> {joint.chi2['joint']['stars']:.1f} "
            f"({joint.chi2['n_stars']} slopes); {joint.tension_line()}; "
            f"{time.time() - t0:.0f} s")
        if joint.uncertainty:
            say("  " + joint.uncertainty_line())
        if joint.star_information:
            say("  star share of the information: " + ", ".join(
                f"{n} {v:.2f}" for n, v in joint.star_information.items()))
        for w in joint.warnings:
            say(f"  warning: {w}")
        for ln in joint.held_out_table().splitlines():
            say("  " + ln)
        if len(joint.held_out) > 1:
            say("  " + held_out_mean(joint.held_out))
        # the summary less the directions' covariance (99 x 99 on e2v: the bulk of the file)
        rec["joint"] = {k: v for k, v in joint.summary().items() if k != "covariance"}
        if args.save_templates:
            os.makedirs(args.save_templates, exist_ok=True)
            for tag, tpl in (("flats", res.template), ("joint", joint.template)):
                tpl.save(os.path.join(args.save_templates, f"{sensor}_{tag}.fits"),
                         overwrite=True)
        templates = {"flats-only": res.template, "flats+stars": joint.template,
                     # GalSim's own sensor file, imported two ways: neither reproduces
                     # GalSim's e1 exactly (galsim_crosscheck.py: 0.88-1.13 of it)
                     "GalSim file, transfers": import_galsim_sensor(sensor, match="transfers"),
                     "GalSim file, areas": import_galsim_sensor(sensor, match="areas"),
                     "bundled default": default}
        # what the fields say of GalSim's own template (all their usable stars)
        true_tpl = templates["GalSim file, transfers"]
        vals, errs, cells = [], [], []
        try:
            for f in fields:
                b = f.slopes(None, f.usable, n_boot=200, seed=seeds[0])["size"]
                t = f.slopes(true_tpl, f.usable, n_boot=200, seed=seeds[0])["size"]
                vals.append(100 * t[0] / b[0])
                errs.append(100 * t[1] / abs(b[0]))
                cells.append(f"{vals[-1]:+.1f} +- {errs[-1]:.1f}")
        except InputError as exc:  # beyond the file's modelled range
            say(f"  fields corrected with GalSim's own template: refused ({exc})")
        else:
            m, m_err, chi2 = ivw_mean(vals, errs)
            rec["fields_with_galsim_template"] = {"size_pct": vals, "size_pct_err": errs,
                                                  "mean": m, "mean_err": m_err}
            say("  fields corrected with GalSim's own template (transfers), size slope left: "
                + ", ".join(cells) + f" %; mean {m:+.1f} +- {m_err:.1f} % "
                f"(chi2 {chi2:.1f} / {len(vals) - 1})")
        pairs, pseed, pcost = star_pairs(sensor, "moffat", args)
        say(f"  paired validation stars: {len(pairs)} Moffat (seed {pseed})"
            + (f", drawn in {pcost:.0f} s" if pcost else ""))
        rec["validation"] = {}
        for name, tpl in templates.items():
            try:
                fl, rows = per_star_residuals(pairs, tpl, methods=("drift",), sky=1000.0)
            except InputError as exc:  # a template too strong for the brightest stars
                rec["validation"][name] = {"refused": str(exc)}
                say(f"    {name:20s} drift  refused: {exc}")
                continue
            r = residual_slopes(fl, rows)
            u, ue = r["uncorrected"]["size_slope"], r["uncorrected"]["e_slope"]
            d = r["drift"]
            rec["validation"][name] = r
            say(f"    {name:20s} drift  size {100 * d['size_slope'] / u:+6.2f} +- "
                f"{100 * d['size_slope_err'] / abs(u):.2f} %   e1 {100 * d['e_slope'] / ue:+6.1f}"
                f" +- {100 * d['e_slope_err'] / abs(ue):.1f} % of uncorrected")
        line = stated_precision_line(joint, rec["validation"].get("flats+stars", {}))
        if line:
            say("  " + line)
    say("target: flats+stars drift <= 3 % of the size slope and <= 5 % of e1")
    write_results(args.out, lines, out, script=__file__, json_default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
