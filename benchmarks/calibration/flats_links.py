"""Which link of the electrostatic route loses on GalSim flats (issue 41).

``peers.py --flats`` finds that the template ``calibrate`` makes from an
a-matrix fitted to GalSim flat pairs over-corrects GalSim's stars' size
slope by 12-17 % where the noise-free a-matrix leaves about 6 %. This script
follows the route link by link on the same calibrations and the same
paired stars, for each input (GalSim's noise-free a-matrix with errors of
3 % + 1e-9/e, its ``--draws`` noisy draws, and the flats' fit; ``peers.py``'s
inputs and caches):

* ``model``: the template built at ``calibrate``'s best fit (before refinement);
* ``refined``: the template ``calibrate`` writes (each lag's residual kept
  with the weight max(0, 1 - 1/pull^2));
* ``model full``: the built template matched to every measured lag 0..3
  (:func:`~lsst_bfdrift.templates.refine.match_area_coefficients`);
* ``galsim full``: GalSim's file (``match='transfers'``) matched to every
  measured lag: ``model full`` minus this is what the model's far field and
  its serial/parallel split do, the a_ij at lags 0..3 being the same;
* ``model, truth <= 1``: the built template with GalSim's noise-free a_ij at
  lags <= 1 only (the rest the model's);
* ``galsim``: GalSim's file as it is.

Printed per input: the fitted parameters (bounds hit), per template a00, a01,
a10, a11 and S1 = a00 + 2 (a01 + a10) + 4 a11 (the net area response of the
3 x 3 block around a charge), the net response of the lags 2-3 ring and
minus that of lags 0-3 (what area conservation leaves beyond lag 3), each
as a ratio to GalSim's noise-free a-matrix's, the chi2
of its a_ij at lags 0..3 against the input and the pulls of the worst three;
the input's S1 with its error (the a_ij errors taken as independent) and
the % of the uncorrected size and e1 slopes each template leaves (drift,
errors from the stars)::

    python benchmarks/calibration/flats_links.py [--sensors ...] [--draws 0]
        [--pairs /work/cache/spots_val/pairs] [--cache PREFIX]

Writes ``benchmarks/calibration/flats_links_results.txt`` and ``.json``.
"""

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common

from _common import Lines, settings_record, write_results  # noqa: E402
from calibrate_sensor import flats_table  # noqa: E402
from peers import amatrix_inputs  # noqa: E402
from refinement_policy import cached_pairs, calibration, left  # noqa: E402

from lsst_bfdrift.ptc.acoeffs import near_field_response  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.templates.refine import (lag_multiplicity, match_area_coefficients,  # noqa: E402
                                           template_alpha)

def lag_a(template, lags):
    """The template's linear area response at lags 0..lags, [i serial, j parallel] (1/e)."""
    c = template.center
    return template_alpha(template)[c:c + lags + 1, c:c + lags + 1].T


def s1(a):
    """a00 + 2 (a01 + a10) + 4 a11 of a quadrant a-matrix (the package's near-field response)."""
    return near_field_response(a)[0]


def rings(a):
    """(S1, net area response of the lags 2-3 ring, -(sum over lags 0-3)): the last is
    what area conservation leaves to the lags beyond 3, the far field."""
    a = np.asarray(a)[:4, :4]
    s3 = float(np.sum(lag_multiplicity(3) * a))
    return s1(a), s3 - s1(a), -s3


def templates_of(res, table, truth, true_tpl, lags):
    """The route's links as templates (module docstring)."""
    built = res.built_template
    near = lag_a(built, lags)
    near[:2, :2] = truth[:2, :2]
    return {"model": built, "refined": res.template,
            "model full": match_area_coefficients(built, table.a, max_lag=lags),
            "galsim full": match_area_coefficients(true_tpl, table.a, max_lag=lags),
            "model, truth <= 1": match_area_coefficients(built, near, max_lag=lags),
            "galsim": true_tpl}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8"])
    ap.add_argument("--psf", nargs="+", default=["moffat", "kolmogorov"])
    ap.add_argument("--draws", type=int, default=0, help="noisy draws of the noise-free a-matrix")
    ap.add_argument("--pairs", default="/work/cache/spots_val/pairs",
                    help="cache prefix of peers.py's stars and flats' covariances")
    ap.add_argument("--flat-size", type=int, default=400)
    ap.add_argument("--pairs-per-level", type=int, default=2)
    ap.add_argument("--flat-max-lag", type=int, default=3)
    ap.add_argument("--flat-steps", type=int, default=40)
    ap.add_argument("--cache", default="/work/cache/refpol/cal",
                    help="cache prefix of the calibrations (refinement_policy.py's)")
    ap.add_argument("--out", default=os.path.join(HERE, "flats_links_results"))
    args = ap.parse_args(argv)
    lags = 3
    say = Lines(note="% of the uncorrected slope left on paired GalSim stars (drift), errors "
                     "from the stars; S1 = a00 + 2 (a01 + a10) + 4 a11 (1/e)")
    rec = {"settings": settings_record(args), "sensors": {}}
    for sensor in args.sensors:
        truth, inputs = amatrix_inputs(sensor, lags, args.draws)
        inputs.append(("flats", flats_table(sensor, args)[0]))
        true_tpl = import_galsim_sensor(sensor, match="transfers")
        pairs = {psf: cached_pairs(sensor, psf, [args.pairs]) for psf in args.psf}
        s1_true = s1(truth)
        ring_true = rings(truth)
        rs = rec["sensors"][sensor] = {"s1_truth": s1_true}
        for name, table in inputs:
            res, cost = calibration(sensor, name, table, args.cache)
            f = res.fit
            a, sig = table.a[:lags + 1, :lags + 1], table.sigma[:lags + 1, :lags + 1]
            s1_err = near_field_response(a, sig)[1]
            ri = rs[name] = {"chi2": f.chi2, "dof": f.dof, "values": f.values,
                             "at_bound": f.at_bound, "s1": s1(a), "s1_err": s1_err,
                             "templates": {}}
            say(f"{sensor} {name}: fit chi2 {f.chi2:.1f} / {f.dof}; " + ", ".join(
                f"{n} {f.values[n]:.4g} +- {f.errors[n]:.2g}" for n in f.names)
                + (f"; at a bound: {', '.join(f.at_bound)}" if f.at_bound else "")
                + ("" if cost is None else f"; calibrated in {cost:.0f} s"))
            say(f"  GalSim's S1 / ring 2-3 / beyond 3 {ring_true[0]:+.3e} / {ring_true[1]:+.3e}"
                f" / {ring_true[2]:+.3e}; input's " + " / ".join(
                    f"{v / t:.2f}" for v, t in zip(rings(a), ring_true)) + " x")
            say(f"  input        a00 {a[0, 0]:+.3e} a01 {a[0, 1]:.3e} a10 {a[1, 0]:.3e} a11 "
                f"{a[1, 1]:.3e}  S1 {s1(a):+.3e} +- {s1_err:.1e} ({s1(a) / s1_true:.2f} x "
                f"GalSim's {s1_true:+.3e}); errors a00 {sig[0, 0] / abs(a[0, 0]):.0%} a01 "
                f"{sig[0, 1] / abs(a[0, 1]):.0%} a10 {sig[1, 0] / abs(a[1, 0]):.0%} a11 "
                f"{sig[1, 1] / abs(a[1, 1]):.0%}")
            tpls = templates_of(res, table, truth, true_tpl, lags)
            stars = {psf: left(pp, tpls)[0] for psf, pp in pairs.items()}
            for k, t in tpls.items():
                ta = lag_a(t, lags)
                pull = (ta - a) / sig
                worst = np.argsort(-np.abs(pull), axis=None)[:3]
                ring = [v / t for v, t in zip(rings(ta), ring_true)]
                rt = ri["templates"][k] = {"a": ta.tolist(), "s1": s1(ta), "rings": ring,
                                          "chi2": float(np.sum(pull ** 2)), "stars": {}}
                line = (f"  {k:17s} a00 {ta[0, 0]:+.3e} a01 {ta[0, 1]:.3e} a10 {ta[1, 0]:.3e} "
                        f"a11 {ta[1, 1]:.3e}  S1 / ring 2-3 / beyond 3 {ring[0]:.2f} / "
                        f"{ring[1]:.2f} / {ring[2]:.2f} x; chi2 "
                        f"{rt['chi2']:6.1f} (worst " + ", ".join(
                            "a{}{} {:+.1f}".format(*np.unravel_index(w, pull.shape),
                                                   pull.flat[w]) for w in worst) + ")")
                for psf, out in stars.items():
                    rt["stars"][psf] = out[k]
                    line += (f"; {psf[:3]} size {out[k]['size'][0]:+5.1f} +- "
                             f"{out[k]['size'][1]:.1f} e1 {out[k]['e1'][0]:+6.1f}")
                say(line)
            write_results(args.out, say, rec, script=__file__)
    say("size left against S1 / GalSim's S1 - 1 over every template and input (a line "
        "fitted per sensor and PSF; rms of the points about it):")
    rec["s1_line"] = {}
    for sensor, rs in rec["sensors"].items():
        for psf in args.psf:
            x = np.array([t["s1"] / rs["s1_truth"] - 1 for n, r in rs.items() if n != "s1_truth"
                          for t in r["templates"].values()])
            y = np.array([t["stars"][psf]["size"][0] for n, r in rs.items() if n != "s1_truth"
                          for t in r["templates"].values()])
            c1, c0 = np.polyfit(x, y, 1)
            rms = float(np.sqrt(np.mean((y - c0 - c1 * x) ** 2)))
            rec["s1_line"][f"{sensor} {psf}"] = {"offset": c0, "slope": c1, "rms": rms,
                                                 "points": int(x.size)}
            say(f"  {sensor} {psf:10s} size {c0:+5.1f} {c1:+6.1f} x (S1 ratio - 1), rms "
                f"{rms:.1f} over {x.size} templates")
    write_results(args.out, say, rec, script=__file__)


if __name__ == "__main__":
    main()
