"""Closure test: PTC fit of simulated flats against the template's a_ij.

Run from the repository root::

    python benchmarks/simulation/flat_closure.py [--out benchmarks/simulation/flat_closure_results]

For each responsivity (the paper's -1e-5 and -3.3e-5 per e, as d ln A00 / Q
of the bundled template, rescaled), independent stacks of periodic flats are
filled to a series of signal levels
(:func:`lsst_bfdrift.simulation.flats.simulate_ptc_levels`), the per-pair
covariances are fitted with the full model of Astier et al. 2019
(:func:`lsst_bfdrift.ptc.full_model.fit_covariance_model`: a_ij free; gain 1, b_ij and n_ij 0
fixed at their true values, then again with gain and n_ij free),
the fitted a_ij are corrected for the discrete filling (divided by
1 - 1/n) and compared with the template's linear response alpha_ij (and,
for the record, with (A_ij - 1)/Q and ln A_ij / Q). Prints and writes
``<out>.txt`` and ``<out>.json``.
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.ptc.full_model import fit_covariance_model  # noqa: E402
from lsst_bfdrift.simulation.flats import (simulate_ptc_levels,  # noqa: E402
                                      template_area_coefficients, with_responsivity)
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402

LAGS = [(0, 0), (1, 0), (0, 1), (1, 1), (2, 0), (0, 2), (2, 1), (1, 2), (2, 2)]


def closure(template, levels, *, steps_per_level=40, n_images=1024, shape=(16, 16), max_lag=3,
            fit_lag=2, seed=None, progress=False, known_gain=True, fit_b=False, table=None):
    """Simulate (unless ``table`` is given), fit and compare.

    ``known_gain``: gain fixed to 1 and noise to 0 (their true values);
    otherwise both are fitted as on real data. Returns a dict of arrays and
    the table.
    """
    tab = table if table is not None else simulate_ptc_levels(
        template, levels, steps_per_level=steps_per_level, n_images=n_images, shape=shape,
        max_lag=max_lag, seed=seed, progress=progress)
    fit = fit_covariance_model(np.asarray(tab["mu"]), np.asarray(tab["cov"]),
                               sigma=np.asarray(tab["cov_err"]), max_lag=fit_lag, fit_b=fit_b,
                               gain=1.0 if known_gain else None, fit_noise=not known_gain)
    f = tab.meta["step_factor"]
    truth = template_area_coefficients(template, max_lag=fit_lag)
    a = fit["a"] / f
    a_err = fit["a_err"] / f
    return {"a": a, "a_err": a_err, "gain": fit["gain"], "gain_err": fit["gain_err"],
            "chi2": fit["chi2"], "dof": fit["dof"], "truth": truth, "table": tab,
            "pull": {k: (a - truth[k]) / a_err for k in ("alpha", "linear", "log")}}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(HERE, "flat_closure_results"))
    ap.add_argument("--n-images", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=2015)
    args = ap.parse_args()
    base = load_default_template()
    lines, rows = [], {}
    for resp, top in ((-1e-5, 3e4), (-3.3e-5, 1e4)):
        tpl = with_responsivity(base, resp)
        levels = np.linspace(top / 10, top, 10)
        t0 = time.perf_counter()
        r = closure(tpl, levels, n_images=args.n_images, seed=args.seed, progress=True)
        dt = time.perf_counter() - t0
        # the same data fitted as real data would be: gain and n_ij free
        rf = closure(tpl, None, table=r["table"], known_gain=False)
        lines.append(f"responsivity d lnA00/Q = {resp:g} per e; 10 independent levels "
                     f"{levels[0]:.0f}..{levels[-1]:.0f} e, {args.n_images} flats of 16x16 each, "
                     f"40 fill steps per level (a / (1 - 1/40)); fit lags <= 2, gain 1, "
                     f"b = n = 0 fixed; "
                     f"gain {r['gain']:.5f} +- {r['gain_err']:.5f} (truth 1), "
                     f"chi2 / dof = {r['chi2']:.1f} / {r['dof']}; {dt:.0f} s")
        lines.append("  lag   fitted a (1/e)           alpha (dA/dQ)  pull   (A-1)/Q     pull"
                     "   lnA/Q       pull")
        row = []
        for di, dj in LAGS:
            a, e = r["a"][di, dj], r["a_err"][di, dj]
            tr = {k: r["truth"][k][di, dj] for k in ("alpha", "linear", "log")}
            pl = {k: r["pull"][k][di, dj] for k in ("alpha", "linear", "log")}
            lines.append(f"  a{di}{dj}  {a: .4e} +- {e:.2e}   {tr['alpha']: .4e} "
                         f"{pl['alpha']:+6.2f}"
                         f"  {tr['linear']: .4e} {pl['linear']:+6.2f}  {tr['log']: .4e} "
                         f"{pl['log']:+6.2f}")
            row.append({"lag": [di, dj], "a": a, "a_err": e,
                        **{f"truth_{k}": v for k, v in tr.items()},
                        **{f"pull_{k}": v for k, v in pl.items()}})
        chi = {k: float(sum(x[f"pull_{k}"] ** 2 for x in row)) for k in ("alpha", "linear", "log")}
        lines.append("  sum of squared pulls over the 9 lags: " + ", ".join(
            f"{k} {v:.1f}" for k, v in chi.items()))
        lines.append(f"  same data, gain and n_ij free: gain {rf['gain']:.5f} +- "
                     f"{rf['gain_err']:.5f}, chi2 / dof = {rf['chi2']:.1f} / {rf['dof']}; pulls "
                     "against alpha: " + ", ".join(
                         f"a{di}{dj} {rf['a'][di, dj]:.4e} +- {rf['a_err'][di, dj]:.2e} "
                         f"({rf['pull']['alpha'][di, dj]:+.2f})" for di, dj in LAGS[:4]))
        rows[str(resp)] = {"levels": levels.tolist(), "gain": r["gain"], "gain_err": r["gain_err"],
                           "chi2": r["chi2"], "dof": r["dof"], "lags": row,
                           "sum_pull2": chi, "seconds": dt,
                           "free_gain_fit": {"gain": rf["gain"], "gain_err": rf["gain_err"],
                                             "chi2": rf["chi2"], "dof": rf["dof"],
                                             "a": rf["a"].tolist(), "a_err": rf["a_err"].tolist(),
                                             "pull_alpha": rf["pull"]["alpha"].tolist()}}
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(args.out, lines, rows, script=__file__, json_default=float, indent=2)


if __name__ == "__main__":
    main()
