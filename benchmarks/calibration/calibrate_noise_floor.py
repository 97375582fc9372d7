"""How well flats of a given size can calibrate the star correction: the noise floor.

The flats route of ``benchmarks/calibration/calibrate_sensor.py`` leaves 6-9 % of the
size slope on GalSim ITL stars (depending on the flat set), where the
a-matrix route leaves -2.5 %. This script separates the model from the
statistics. It builds the template that
the flats' calibration fits (no refinement), then refines it to a_ij that
are known exactly except for noise:

* GalSim's noise-free a-matrix of the sensor, lags <= 3 and <= 5;
* the same plus Gaussian noise with the flats' own errors per lag (the
  covariance fit's ``a_err``), ``--draws`` times;
* the same with the errors divided by sqrt(f) for each further factor f of
  ``--data-factors`` (f times the flats' pixel pairs; default 10 and 74, the
  data the joint fit's stated e1 precision asks for e1 to 5 % on ITL);
* each of those refined as ``calibrate`` refines
  (:func:`~lsst_bfdrift.calibration.tuning.refinement_target`: a lag within
  its error is left to the model), with the errors the flats' and with them
  divided by sqrt(f): the noise-free line is the refinement's own bias at
  those errors, the draws its bias plus noise;
* the calibrated (refined) template of the flats and the draws that
  :func:`~lsst_bfdrift.templates.refine.draw_templates` makes from the
  uncertainty it stores (what the Task's ``uncertainty_draws`` use): their
  spread is the package's own statement of this floor.

Each template corrects the same GalSim stars (drift), and the size and e1
slopes left are printed as % of the uncorrected ones, with the rms over the
draws (size and e1). If the noise-free a_ij meet the target and the noisy ones scatter
as far as the flats route misses, the miss is the flats' statistics; if the
noise-free a_ij refined as ``calibrate`` refines miss too, it is the model's
error that the refinement keeps at those errors::

    python benchmarks/calibration/calibrate_sensor.py --sensors lsst_itl_50_8 --flats \\
        --skip-amatrix --flat-size 800 --pairs-per-level 4 --flat-steps 20 \\
        --pairs /tmp/cs_pairs          # draws and caches the flats and stars
    python benchmarks/calibration/calibrate_noise_floor.py --pairs /tmp/cs_pairs

Writes ``benchmarks/calibration/calibrate_noise_floor_results.txt`` and ``.json``.
"""

import argparse
import os
import platform
import sys
import time
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.ptc.acoeffs import AcoeffTable  # noqa: E402
from lsst_bfdrift.ptc.full_model import fit_covariance_model  # noqa: E402
from lsst_bfdrift.calibration.tuning import calibrate, refine_template  # noqa: E402
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.templates.refine import draw_templates, match_area_coefficients  # noqa: E402
from lsst_bfdrift.utils.errors import InputError  # noqa: E402
from lsst_bfdrift.validation.stars import per_star_residuals, residual_slopes  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensor", default="lsst_itl_50_8")
    ap.add_argument("--pairs", required=True, help="cache prefix of calibrate_sensor.py")
    ap.add_argument("--flat-size", type=int, default=800)
    ap.add_argument("--pairs-per-level", type=int, default=4)
    ap.add_argument("--flat-steps", type=int, default=20)
    ap.add_argument("--psf", default="moffat")
    ap.add_argument("--n-stars", type=int, default=200)
    ap.add_argument("--draws", type=int, default=6)
    ap.add_argument("--seed", type=int, default=2026)
    ap.add_argument("--data-factors", type=float, nargs="+", default=[10.0, 74.0],
                    help="besides the flats' own errors, draws with the errors / sqrt(f): f "
                         "times the flat data")
    ap.add_argument("--out", default=os.path.join(HERE, "calibrate_noise_floor_results"))
    args = ap.parse_args(argv)
    t_start = time.time()
    sensor, steps = args.sensor, args.flat_steps
    tag = "" if steps == 40 else f"_{steps}"
    flats = f"{args.pairs}_{sensor}_flats_{args.flat_size}_{args.pairs_per_level}{tag}.npz"
    seed = zlib.crc32(f"{sensor}:{args.psf}".encode()) % 100000
    stars = f"{args.pairs}_{sensor}_{args.psf}_{args.n_stars}_{seed}.npz"
    for p in (flats, stars):
        if not os.path.isfile(p):
            sys.exit(f"{p} is missing: run benchmarks/calibration/calibrate_sensor.py first "
                     "(docstring)")
    tab = dict(np.load(flats))
    fit = fit_covariance_model(tab["mu"], tab["cov"], npix=tab["npix"])
    factor = 1.0 - 1.0 / steps
    table = AcoeffTable(fit["a"] / factor, fit["a_err"] / factor, source=f"{sensor} flats")
    res = calibrate(table, allow_poor_fit=True, refine=False)
    built = res.template
    L = min(table.max_lag, built.center - 1)
    truth = galsim_acoeffs(sensor, L)
    sigma = table.sigma[:L + 1, :L + 1]
    rng = np.random.default_rng(args.seed)
    templates = {"built (flats fit, no refinement)": built}
    for k in (3, L):
        templates[f"GalSim a_ij, lags <= {k}"] = match_area_coefficients(
            built, galsim_acoeffs(sensor, k), max_lag=k)
    draws = {}
    levels = [(1.0, "flats' errors")] + [(f ** -0.5, f"errors / sqrt({f:g})")
                                         for f in args.data_factors]
    for scale, label in levels:
        for k in range(args.draws):
            draws[label, k] = truth + rng.normal(0.0, sigma * scale)
            templates[f"GalSim a_ij + {label}, draw {k}"] = match_area_coefficients(
                built, draws[label, k], max_lag=L)

    def as_calibrate(a, scale):
        """Refined to a (lags <= L) as calibrate refines, with the flats' errors x scale."""
        full = table.a.copy()
        full[:L + 1, :L + 1] = a
        t = AcoeffTable(full, table.sigma * scale, source="draw")
        return refine_template(built, t)

    for scale, label in levels:
        templates[f"GalSim a_ij, kept to model within {label}"] = as_calibrate(truth, scale)
        for k in range(args.draws):
            templates[f"  same + {label}, draw {k}"] = as_calibrate(draws[label, k], scale)
    # the package's own uncertainty: the calibrated (refined) template and the
    # draws the Task's uncertainty_draws make from it
    refined = calibrate(table, allow_poor_fit=True).template
    templates["calibrated (flats, refined)"] = refined
    for k, tpl in enumerate(draw_templates(refined, args.draws, seed=args.seed)):
        templates[f"its uncertainty draw {k} (draw_templates)"] = tpl
    templates["true (GalSim file)"] = import_galsim_sensor(sensor, match="transfers")
    d = np.load(stars)
    pairs = [{"bf": b, "truth": t, "flux": float(f)}
             for b, t, f in zip(d["bf"], d["truth"], d["flux"])]
    lines, rec = [], {"sensor": sensor, "flats": os.path.basename(flats),
                      "fit": {"names": res.fit.names, "chi2": res.fit.chi2, "dof": res.fit.dof},
                      "templates": {}}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    say(f"Noise floor of the flats route: {sensor}, flats {args.flat_size} x {args.flat_size} px "
        f"x {len(tab['mu'])} pairs (lags <= {L}; a00 error "
        f"{table.sigma[0, 0] / abs(table.a[0, 0]):.1%}, a11 "
        f"{table.sigma[1, 1] / abs(table.a[1, 1]):.0%}, a02 "
        f"{table.sigma[0, 2] / abs(table.a[0, 2]):.0%}); {len(pairs)} {args.psf} stars; drift; "
        f"{platform.machine()}, {os.cpu_count()} cores")
    say(f"  flats fit: {', '.join(res.fit.names)}; chi2 {res.fit.chi2:.1f} / {res.fit.dof} dof")
    for name, tpl in templates.items():
        try:
            fl, rows = per_star_residuals(pairs, tpl, methods=("drift",), sky=1000.0)
        except InputError as exc:  # e.g. the stars' brightest pixels beyond the template's range
            rec["templates"][name] = {"refused": str(exc)}
            say(f"  {name:44s} refused: {exc}")
            continue
        r = residual_slopes(fl, rows)
        u, ue = r["uncorrected"]["size_slope"], r["uncorrected"]["e_slope"]
        size, e1 = 100 * r["drift"]["size_slope"] / u, 100 * r["drift"]["e_slope"] / ue
        err = 100 * r["drift"]["size_slope_err"] / abs(u)
        rec["templates"][name] = {"size": size, "size_err": err, "e1": e1}
        say(f"  {name:44s} size {size:+6.2f} +- {err:.2f} %   e1 {e1:+6.1f} %")
    done = {k: v for k, v in rec["templates"].items() if "size" in v}
    own = np.array([v["size"] for k, v in done.items() if "draw_templates" in k])
    centre = done.get("calibrated (flats, refined)", {}).get("size")
    if own.size and centre is not None:
        rec["rms size, draw_templates about the calibrated template"] = float(
            np.sqrt(np.mean((own - centre) ** 2)))
        say(f"  the calibrated template's own draws (draw_templates, the Task's "
            f"uncertainty_draws): size spread rms {np.sqrt(np.mean((own - centre) ** 2)):.1f} % "
            f"about its {centre:+.1f} %")
    for q in ("size", "e1"):
        for _, label in levels:
            for how, prefix in (("matched lag by lag", "GalSim a_ij + "),
                                ("refined as calibrate does", "  same + ")):
                s = np.array([v[q] for k, v in done.items()
                              if k.startswith(prefix + label + ",")])
                if not s.size:
                    continue
                rec[f"rms {q}, {label}, {how}"] = float(np.sqrt(np.mean(s**2)))
                rec[f"mean {q}, {label}, {how}"] = float(np.mean(s))
                say(f"  {label:18s} {how:26s}: {q:4s} left over {s.size} draws: rms "
                    f"{np.sqrt(np.mean(s**2)):5.1f} %, mean {s.mean():+6.1f} %, range "
                    f"{s.min():+6.1f} to {s.max():+6.1f} %")
    say(f"target: <= 3 % of the size slope, <= 5 % of e1. ({time.time() - t_start:.0f} s)")
    write_results(args.out, lines, rec, script=__file__, json_default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
