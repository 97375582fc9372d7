"""End to end: calibrate from a GalSim sensor's own data, then correct its stars.

For each GalSim sensor model (default lsst_itl_50_8 and lsst_e2v_50_8):

1. **a-matrix route**: GalSim's noise-free a-matrix of the sensor
   (:func:`~lsst_bfdrift.simulation.galsim_twins.galsim_acoeffs`, every lag
   the template holds, <= 9 for the 21 x 21 template, a00 included) with 2 % errors (+1e-10 floor), calibrated with
   :func:`~lsst_bfdrift.calibration.tuning.calibrate` (parameters chosen by
   the data, template refined to the a_ij).
2. **flats route** (``--flats``): flat pairs made with GalSim's own
   pixel-area response and Poisson noise
   (:func:`~lsst_bfdrift.simulation.flats.simulate_flat_pairs`, engine
   'galsim', 9 levels of 1e4-9e4 e, ``--pairs-per-level`` pairs of
   ``--flat-size`` pixels, ``--flat-steps`` fill steps, default 40), their
   covariances to ``--flat-max-lag`` (default 5), the Astier et al. (2019)
   fit for a_ij with errors, divided by 1 - 1/steps for the discrete
   filling, and the same calibration.
3. **stars**: Moffat and Kolmogorov stars (FWHM 0.6-0.9", fluxes 1e4-1.5e6
   e, sky 1000 e through the sensor) drawn by galsim.SiliconSensor with a
   paired no-BF twin
   (:func:`~lsst_bfdrift.validation.stars.draw_star_pairs`; a seed of its
   own per sensor), corrected by drift and astier23 with each template: the
   calibrated ones, GalSim's true template (its file imported with
   ``match='transfers'``), the bundled default, and the template that the
   a-matrix alone gives (the minimum-norm, curl-free edge shifts with
   GalSim's a_ij: no model of how the area change is shared between edges).

Prints the size and e1 slopes left, as % of the uncorrected slopes, and
writes ``benchmarks/calibration/calibrate_sensor_results.txt`` / ``.json``::

    python benchmarks/calibration/calibrate_sensor.py [--sensors lsst_itl_50_8 lsst_e2v_50_8]
        [--n-stars 200] [--pairs /tmp/cs_pairs] [--flats]
"""

import argparse
import os
import sys
import time
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.ptc.acoeffs import AcoeffTable  # noqa: E402
from lsst_bfdrift.calibration.tuning import calibrate  # noqa: E402
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.templates.refine import curl_free_template  # noqa: E402
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402
from lsst_bfdrift.validation.stars import (draw_star_pairs, per_star_residuals,  # noqa: E402
                                           residual_slopes, slope_through_origin as _slope)

METHODS = ("astier23", "drift")


def star_pairs(sensor, psf, args):
    seed = zlib.crc32(f"{sensor}:{psf}".encode()) % 100000  # own stars per sensor and PSF
    path = f"{args.pairs}_{sensor}_{psf}_{args.n_stars}_{seed}.npz" if args.pairs else None
    if path and os.path.isfile(path):
        d = np.load(path)
        return [{"bf": b, "truth": t, "flux": float(f)}
                for b, t, f in zip(d["bf"], d["truth"], d["flux"])], seed, None
    t0 = time.time()
    pairs = draw_star_pairs(args.n_stars, sensor=sensor, psf=psf, seed=seed)
    cost = time.time() - t0
    if path:
        np.savez_compressed(path, bf=np.array([p["bf"] for p in pairs]),
                            truth=np.array([p["truth"] for p in pairs]),
                            flux=np.array([p["flux"] for p in pairs]))
    return pairs, seed, cost


#: Fill steps of each simulated flat. Discrete filling gives C_ij = a_ij mu^2
#: (1 - 1/n) to first order (the charge of a step sees only the earlier
#: steps' boundaries; ``benchmarks/simulation/flat_closure.py`` checks it), so the fitted
#: a_ij are divided by 1 - 1/steps to be those of a continuous exposure.
FLAT_STEPS = 40


def _progress(what, t0):
    def report(done, total):
        print(f"  {what}: {done}/{total} pairs, {time.time() - t0:.0f} s", flush=True)
    return report


def flats_table(sensor, args):
    """a_ij with errors from GalSim-made flat pairs (Astier et al. 2019 fit),
    corrected for the simulation's discrete filling (1 - 1/steps)."""
    from lsst_bfdrift.ptc.covariances import measure_ptc
    from lsst_bfdrift.ptc.full_model import fit_covariance_model
    from lsst_bfdrift.simulation.flats import simulate_flat_pairs

    steps = args.flat_steps
    tag = ("" if steps == FLAT_STEPS else f"_{steps}") + (
        "" if args.flat_max_lag == 5 else f"_lag{args.flat_max_lag}")
    path = (f"{args.pairs}_{sensor}_flats_{args.flat_size}_{args.pairs_per_level}{tag}.npz"
            if args.pairs else None)
    if path and os.path.isfile(path):
        tab = dict(np.load(path))
    else:
        levels = np.repeat(np.linspace(1e4, 9e4, 9), args.pairs_per_level)
        pairs = simulate_flat_pairs(sensor, levels, engine="galsim",
                                    shape=(args.flat_size,) * 2, n_steps=steps,
                                    seed=zlib.crc32(sensor.encode()) % 1000,
                                    progress=_progress(f"{sensor} flats", time.time()))
        # GalSim's kernels vanish beyond lag 4; the far lags measured as ~0
        # (with their errors) constrain the model's far field
        tab = measure_ptc(pairs, max_lag=args.flat_max_lag)
        tab = {k: np.asarray(tab[k]) for k in ("mu", "cov", "npix")}
        if path:
            np.savez(path, **tab)
    fit = fit_covariance_model(tab["mu"], tab["cov"], npix=tab["npix"])
    factor = 1.0 - 1.0 / steps
    return AcoeffTable(fit["a"] / factor, fit["a_err"] / factor,
                       source=f"GalSim {sensor} flats"), fit


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8"])
    ap.add_argument("--psf", nargs="+", default=["moffat", "kolmogorov"])
    ap.add_argument("--n-stars", type=int, default=200)
    ap.add_argument("--pairs", help="cache prefix for the drawn stars and flats' covariances")
    ap.add_argument("--amatrix-lags", type=int, default=9,
                    help="lags of GalSim's a-matrix given to calibrate (9: all the 21 x 21 "
                         "template holds)")
    ap.add_argument("--flats", action="store_true", help="also calibrate from GalSim flats")
    ap.add_argument("--skip-amatrix", action="store_true",
                    help="leave out the a-matrix route (with --flats: flats only)")
    ap.add_argument("--flat-size", type=int, default=400)
    ap.add_argument("--pairs-per-level", type=int, default=2)
    ap.add_argument("--flat-max-lag", type=int, default=5,
                    help="largest lag of the flats' covariances and of the a_ij fitted to them")
    ap.add_argument("--flat-steps", type=int, default=FLAT_STEPS,
                    help="fill steps of each simulated flat (a_ij are divided by 1 - 1/steps)")
    ap.add_argument("--out", default=os.path.join(HERE, "calibrate_sensor_results"))
    args = ap.parse_args(argv)
    lines, out = [], {"sensors": {}}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    default = load_default_template()
    for sensor in args.sensors:
        rec = out["sensors"][sensor] = {"calibrations": {}, "psfs": {}}
        a = galsim_acoeffs(sensor, args.amatrix_lags)
        table = AcoeffTable(a, 0.02 * np.abs(a) + 1e-10, source=f"GalSim {sensor} a-matrix")
        templates = {}
        routes = [] if args.skip_amatrix else [("a-matrix", lambda: (table, None))]
        if args.flats:
            routes.append(("flats", lambda: flats_table(sensor, args)))
        for route, get in routes:
            t0 = time.time()
            tab, extra = get()
            res = calibrate(tab, allow_poor_fit=True)
            templates[f"calibrated ({route})"] = res.template
            f = res.fit
            say(f"{sensor}, {route}: {', '.join(f'{n} = {f.values[n]:.4g}' for n in f.names)}; "
                f"chi2 {f.chi2:.1f} / {f.dof} dof; a00 data {tab.a[0, 0]:.3e} model "
                f"{f.model[0, 0]:.3e}; a00 error {tab.sigma[0, 0] / abs(tab.a[0, 0]):.1%}, "
                f"a01 {tab.sigma[0, 1] / abs(tab.a[0, 1]):.1%}, a10 "
                f"{tab.sigma[1, 0] / abs(tab.a[1, 0]):.1%}; {time.time() - t0:.0f} s")
            rec["calibrations"][route] = res.summary()
            if route == "a-matrix":
                templates["a-matrix alone, curl-free"] = curl_free_template(res.built_template, a)
        templates["true (GalSim file)"] = import_galsim_sensor(sensor, match="transfers")
        templates["bundled default"] = default
        for psf in args.psf:
            pairs, seed, cost = star_pairs(sensor, psf, args)
            say(f" {sensor} {psf}: {len(pairs)} stars (seed {seed})"
                + (f", drawn in {cost:.0f} s" if cost else ""))
            rec["psfs"][psf] = {}
            per_template = {}
            for name, tpl in templates.items():
                fl, rows = per_template[name] = per_star_residuals(pairs, tpl, methods=METHODS,
                                                                   sky=1000.0)
                res = residual_slopes(fl, rows)
                u, ue = res["uncorrected"]["size_slope"], res["uncorrected"]["e_slope"]
                rec["psfs"][psf][name] = res
                for m in METHODS:
                    r = res[m]
                    say(f"  {name:24s} {m:9s} size {100 * r['size_slope'] / u:+6.2f} +- "
                        f"{100 * r['size_slope_err'] / abs(u):.2f} %   e1 "
                        f"{100 * r['e_slope'] / ue:+6.1f} +- {100 * r['e_slope_err'] / abs(ue):.1f}"
                        " % of uncorrected")
            # paired on the same stars: calibrated minus true template (drift)
            fl, true_rows = per_template["true (GalSim file)"]
            u = rec["psfs"][psf]["true (GalSim file)"]["uncorrected"]
            for name in (k for k in templates if k.startswith(("calibrated", "a-matrix alone"))):
                rows = per_template[name][1]
                ok = np.isfinite(fl)
                d = {}
                for col, key, ref in ((0, "size", u["size_slope"]), (1, "e1", u["e_slope"])):
                    diff = rows["drift"][ok, col] - true_rows["drift"][ok, col]
                    sl, se = _slope(fl[ok], diff)
                    d[key] = (100 * sl / ref, 100 * se / abs(ref))
                rec["psfs"][psf][f"{name} minus true, drift"] = d
                say(f"  paired {name} minus true, drift: size {d['size'][0]:+.2f} +- "
                    f"{d['size'][1]:.2f} %, e1 {d['e1'][0]:+.1f} +- {d['e1'][1]:.1f} %")
    say("target: calibrated drift <= 3 % of the size slope and <= 5 % of e1")
    write_results(args.out, lines, out, script=__file__, json_default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
