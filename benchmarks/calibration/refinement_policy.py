# command: python benchmarks/calibration/refinement_policy.py
"""How far to refine the template to the a-matrix: judged on GalSim's stars (issues 41, 42).

``calibrate`` fits the electrostatic model to the a-matrix and then
refines the template's pixel areas toward the measured a_ij lag by lag,
each residual kept with the weight max(0, 1 - 1/pull^2)
(:func:`~lsst_bfdrift.calibration.tuning.refinement_target`): a lag within
its error is left to the model. On GalSim's sensors the model's residuals
are within their errors lag by lag but of one sign at the lags that set a
star's size, and the template over-corrects the stars' size slope by
several % (``peers.py``, ``spots_stars.py``). This script compares, on the
same calibrations and the same paired GalSim stars, three policies:

* ``model``: the template built at the best fit, not refined;
* ``shrink``: ``calibrate``'s refinement (what it writes);
* ``full``: the template's linear area response matched to every measured
  lag 0..``--lags`` (:func:`~lsst_bfdrift.templates.refine.match_area_coefficients`),
  noise and all;
* ``prior T``: each lag's residual r = measured - model kept with the weight
  tau^2 / (tau^2 + sigma^2), tau = T x |model a_ij| (``--tau``): the
  posterior mean of the a_ij when the model is taken to be good to a
  fraction T at every lag and the data to their errors.

Inputs per GalSim sensor file (default the four of ``peers.py``): its
noise-free a-matrix with cp_pipe-scale errors (3 % + 1e-9/e) and
``--draws`` draws of it with noise at that scale (``peers.py``'s
``amatrix_inputs``, the same seeds). Stars: the paired GalSim stars cached
by ``peers.py`` / ``spots_stars.py`` (Moffat and Kolmogorov; the largest
cached set under ``--pairs``), corrected by drift with each template. Printed
per sensor, input and PSF: % of the uncorrected size and e1 slopes left,
errors from the stars; then per policy the root mean square over inputs
and PSFs (what a user can expect from one calibration). Writes
``benchmarks/calibration/refinement_policy_results.txt`` / ``.json``::

    python benchmarks/calibration/refinement_policy.py [--sensors ...] [--draws 3]
"""

import argparse
import glob
import os
import sys
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common

from _common import Lines, settings_record, write_results  # noqa: E402
from calibrate_sensor import star_pairs  # noqa: E402
from peers import amatrix_inputs  # noqa: E402
from spots_stars import cached_calibration  # noqa: E402

from lsst_bfdrift.templates.refine import match_area_coefficients, template_alpha  # noqa: E402
from lsst_bfdrift.validation.stars import per_star_residuals, slope_through_origin  # noqa: E402

POLICIES = ("model", "shrink", "full")  # and one "prior T" per --tau
QUANTITIES = ((0, "size"), (1, "e1"))



def calibration(sensor, name, table, cache):
    """calibrate() of one input (spots_stars.py's cached_calibration), keyed by its a_ij."""
    key = zlib.crc32(np.asarray(table.a).tobytes()) % 100000
    return cached_calibration(
        table, f"{cache}_{sensor}_{name.replace(' ', '')}_{key}.pkl" if cache else None)


def prior_target(template, table, lags, tau):
    """Model a_ij plus the residual weighted by tau^2 / (tau^2 + sigma^2), tau = T |model|."""
    c = template.center
    model = template_alpha(template)[c:c + lags + 1, c:c + lags + 1].T
    a, sig = table.a[:lags + 1, :lags + 1], table.sigma[:lags + 1, :lags + 1]
    t2 = (tau * np.abs(model)) ** 2
    return np.where(table.mask()[:lags + 1, :lags + 1], model + t2 / (t2 + sig ** 2) * (a - model),
                    np.nan)


def policy_templates(res, table, lags, taus):
    built = res.built_template
    out = {"model": built, "shrink": res.template,
           "full": match_area_coefficients(built, table.a, max_lag=lags)}
    for t in taus:
        out[f"prior {t:g}"] = match_area_coefficients(built, prior_target(built, table, lags, t),
                                                      max_lag=lags)
    return out


def cached_pairs(sensor, psf, prefixes):
    """The largest cached set of the sensor's paired stars under any of ``prefixes``."""
    seed = zlib.crc32(f"{sensor}:{psf}".encode()) % 100000
    found = []
    for p in prefixes:
        found += glob.glob(f"{p}_{sensor}_{psf}_*_{seed}.npz")
    if not found:
        raise SystemExit(f"no cached stars for {sensor} {psf} under {prefixes}: run peers.py")
    best = max(found, key=lambda p: int(p.rsplit("_", 2)[-2]))
    ns = argparse.Namespace(pairs=best.rsplit(f"_{sensor}_", 1)[0],
                            n_stars=int(best.rsplit("_", 2)[-2]))
    return star_pairs(sensor, psf, ns)[0]


def left(pairs, templates):
    """% of the uncorrected size and e1 slopes each template leaves (errors from the stars)."""
    res = {n: per_star_residuals(pairs, t, methods={n: {"method": "drift"}}, sky=1000.0)
           for n, t in templates.items()}
    fl, first = next(iter(res.values()))
    ok = np.isfinite(fl)
    u = {q: slope_through_origin(fl[ok], first["uncorrected"][ok, c]) for c, q in QUANTITIES}
    out = {}
    for n, (f, rows) in res.items():
        g = np.isfinite(f)
        out[n] = {}
        for c, q in QUANTITIES:
            s, e = slope_through_origin(f[g], rows[n][g, c])
            out[n][q] = (100 * s / u[q][0], 100 * e / abs(u[q][0]))
    return out, int(ok.sum())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8",
                                                     "lsst_itl_50_32", "lsst_e2v_50_32"])
    ap.add_argument("--psf", nargs="+", default=["moffat", "kolmogorov"])
    ap.add_argument("--lags", type=int, default=3)
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--tau", type=float, nargs="*", default=[0.05, 0.1, 0.2],
                    help="model precisions of the 'prior' policies (fraction of each a_ij)")
    ap.add_argument("--pairs", nargs="+", default=["/work/cache/spots_val/pairs",
                                                    "/work/cache/pairs"],
                    help="cache prefixes of the paired stars (peers.py's, spots_stars.py's)")
    ap.add_argument("--cache", default="/work/cache/refpol/cal")
    ap.add_argument("--out", default=os.path.join(HERE, "refinement_policy_results"))
    args = ap.parse_args(argv)
    if args.cache:
        os.makedirs(os.path.dirname(args.cache), exist_ok=True)
    rec = {"settings": settings_record(args), "sensors": {}}
    say = Lines(note="% of the uncorrected slope left on paired GalSim stars, errors from "
                     "the stars")
    policies = list(POLICIES) + [f"prior {t:g}" for t in args.tau]
    rms = {p: {q: [] for _, q in QUANTITIES} for p in policies}
    for sensor in args.sensors:
        _, inputs = amatrix_inputs(sensor, args.lags, args.draws)
        pairs = {psf: cached_pairs(sensor, psf, args.pairs) for psf in args.psf}
        rs = rec["sensors"][sensor] = {}
        for name, table in inputs:
            res, cost = calibration(sensor, name, table, args.cache)
            tpl = policy_templates(res, table, args.lags, args.tau)
            say(f"{sensor} {name}: chi2 {res.fit.chi2:.1f} / {res.fit.dof}"
                + (f", calibrated in {cost:.0f} s" if cost else " (cached)"))
            ri = rs[name] = {"chi2": res.fit.chi2, "dof": res.fit.dof}
            for psf, pp in pairs.items():
                out, n = left(pp, tpl)
                ri[psf] = out
                say(f"  {psf:10s} ({n} stars) " + "  ".join(
                    f"{p} size {out[p]['size'][0]:+5.1f} +- {out[p]['size'][1]:3.1f} e1 "
                    f"{out[p]['e1'][0]:+5.1f}" for p in policies))
                for p in policies:
                    for _, q in QUANTITIES:
                        rms[p][q].append(out[p][q][0])
        write_results(args.out, say, script=__file__)
    say(f"root mean square over {len(rms['model']['size'])} sensor-input-PSF rows "
        "(what one calibration leaves):")
    rec["rms"] = {}
    for p in policies:
        r = {q: float(np.sqrt(np.mean(np.square(v)))) for q, v in rms[p].items()}
        m = {q: float(np.mean(v)) for q, v in rms[p].items()}
        rec["rms"][p] = {"rms": r, "mean": m}
        say(f"  {p:9s} size rms {r['size']:4.1f} % (mean {m['size']:+5.1f}), e1 rms "
            f"{r['e1']:5.1f} % (mean {m['e1']:+5.1f})")
    write_results(args.out, say, rec, script=__file__)


if __name__ == "__main__":
    main()
