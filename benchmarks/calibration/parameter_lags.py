"""Which lags each model parameter moves, how the parameters correlate, and where the fits miss.

Issue 41 asks which physics the electrostatic model lacks to match real
a-matrices within their errors. This script states what the model's
parameters can and cannot do at lags 0..``--lags``:

1. **Lags per parameter** (the start Jacobian of the package data,
   :func:`~lsst_bfdrift.calibration.fit_model.start_jacobian`, no fitting): each
   candidate's derivative d a_ij / d p times a step of 10 % of its range, in
   units of cp_pipe-scale errors (3 % of |a_ij| plus 1e-9 per electron of
   the GalSim ITL a-matrix); the lags it moves most, and its share of the
   serial (a_i0) against the parallel (a_0j) axis, the anisotropy that e1
   follows.
2. **Linear degeneracy** at the start: the correlation matrix of the
   parameters if all were fitted to those errors (cosines of the weighted
   Jacobian columns through the inverse normal matrix), the pairs above
   0.9, and the condition number.
3. **Fits**: ``calibrate(..., build=False)`` of the a-matrices of the GalSim
   sensor files (noise-free, lags 0..3, the errors above) and of the
   measured ITL covariances (``../shared/data/measured``): chi2, the pulls
   (data minus model over error) per lag, the fitted parameters with their
   errors and bounds, and the correlations of the fitted parameters above
   0.9.

The pattern of the pulls that no parameter removes is what the model lacks.
Run::

    python benchmarks/calibration/parameter_lags.py [--lags 3] [--sensors ...] [--no-fits]

Writes ``benchmarks/calibration/parameter_lags_results.txt`` and ``.json``.
"""

import argparse
import os
import platform
import sys
import time
import warnings

import numpy as np

from lsst_bfdrift.calibration.fit_model import CANDIDATES, default_start, start_jacobian
from lsst_bfdrift.calibration.tuning import CalibrationWarning, calibrate, measured_acoeffs
from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.ptc.inputs import read_calibration_input
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402
REPO = os.path.dirname(os.path.dirname(HERE))
MEASURED = os.path.join(REPO, "..", "shared", "data", "measured", "itl_covariances_21oct19.txt")
#: cp_pipe-scale errors: relative part and floor (per electron).
REL_ERROR, ERROR_FLOOR = 0.03, 1e-9


def lag_list(mask):
    """(i, j) of the lags a mask holds, in row order."""
    return [(int(i), int(j)) for i, j in zip(*np.nonzero(mask))]


def lags_per_parameter(J, sigma, lags, say):
    """Part 1: the lags each parameter moves (in errors) and its serial/parallel share."""
    rec = {}
    say("1. lags per parameter: d a_ij for a step of 10 % of the range, in errors "
        "(3 % + 1e-9/e of the GalSim ITL a-matrix)")
    for k, (name, (lo, hi)) in enumerate(CANDIDATES.items()):
        d = J[..., k] * 0.1 * (hi - lo) / sigma
        order = sorted(lags, key=lambda ij: -abs(d[ij]))
        serial = sum(abs(d[i, 0]) for i in range(1, d.shape[0]))
        parallel = sum(abs(d[0, j]) for j in range(1, d.shape[1]))
        share = serial / (serial + parallel) if serial + parallel else float("nan")
        rec[name] = {"effect_in_errors": d.tolist(),
                     "largest": [{"lag": list(ij), "errors": float(d[ij])} for ij in order[:4]],
                     "serial_share": float(share)}
        say(f"   {name:18s} " + ", ".join(f"a{i}{j} {d[i, j]:+7.1f}" for i, j in order[:4])
            + f"; serial share of the axis lags {share:.2f}")
    return rec


def linear_correlations(J, sigma, lags, say):
    """Part 2: the correlation of all candidates fitted together at the start (linear)."""
    names = list(CANDIDATES)
    A = np.array([[J[i, j, k] / sigma[i, j] for k in range(len(names))] for i, j in lags])
    scale = np.linalg.norm(A, axis=0)
    keep = scale > 0
    An = A[:, keep] / scale[keep]
    N = An.T @ An
    cond = float(np.linalg.cond(N))
    cov = np.linalg.pinv(N)
    d = np.sqrt(np.abs(np.diag(cov)))
    corr = cov / np.outer(d, d)
    kept = [n for n, k in zip(names, keep) if k]
    pairs = [(kept[a], kept[b], float(corr[a, b])) for a in range(len(kept))
             for b in range(a + 1, len(kept)) if abs(corr[a, b]) > 0.9]
    say(f"2. all {len(kept)} candidates fitted together at the start (linear, {len(lags)} lags): "
        f"normal-matrix condition number {cond:.2e}; correlations above 0.9: "
        + (", ".join(f"{a}/{b} {r:+.3f}" for a, b, r in pairs) or "none"))
    return {"names": kept, "correlation": corr.tolist(), "condition": cond,
            "strong_pairs": [{"a": a, "b": b, "rho": r} for a, b, r in pairs]}


def report_fit(label, table, say):
    """Part 3: one calibration fit, its pulls, parameters and strong correlations."""
    t0 = time.time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        res = calibrate(table, build=False, allow_poor_fit=True)
    f = res.fit
    pulls = np.where(table.mask(), (table.a - res.model) / table.sigma, np.nan)
    names = list(f.names)
    corr = np.asarray(f.correlation)
    pairs = [(names[a], names[b], float(corr[a, b])) for a in range(len(names))
             for b in range(a + 1, len(names)) if abs(corr[a, b]) > 0.9]
    say(f"   {label}: chi2 {f.chi2:.1f} for {f.dof} dof ({time.time() - t0:.0f} s); "
        f"fitted {', '.join(f'{n} {f.values[n]:.4g} +- {f.errors[n]:.2g}' for n in names)}"
        + (f"; at bound {f.at_bound}" if f.at_bound else ""))
    say("      pulls (data - model)/error, rows i (serial), columns j (parallel):")
    for i in range(pulls.shape[0]):
        say("        " + " ".join("   .  " if not np.isfinite(v) else f"{v:+6.1f}"
                                  for v in pulls[i]))
    say("      correlations above 0.9: "
        + (", ".join(f"{a}/{b} {r:+.3f}" for a, b, r in pairs) or "none"))
    return {"chi2": float(f.chi2), "dof": int(f.dof), "values": dict(f.values),
            "errors": dict(f.errors), "at_bound": list(f.at_bound), "pulls": pulls.tolist(),
            "names": names, "correlation": corr.tolist(),
            "strong_pairs": [{"a": a, "b": b, "rho": r} for a, b, r in pairs]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--lags", type=int, default=3)
    ap.add_argument("--sensors", nargs="+",
                    default=["lsst_itl_50_8", "lsst_e2v_50_8", "lsst_itl_50_32",
                             "lsst_e2v_50_32"])
    ap.add_argument("--no-fits", action="store_true", help="parts 1 and 2 only (seconds)")
    ap.add_argument("--out", default=os.path.join(HERE, "parameter_lags_results"))
    args = ap.parse_args(argv)
    lines = []

    def say(s):
        print(s, flush=True)
        lines.append(s)

    say(f"machine: {platform.machine()}, {os.cpu_count()} cores; lags 0..{args.lags}")
    L = args.lags
    ref = galsim_acoeffs("lsst_itl_50_8", L)
    sigma = REL_ERROR * np.abs(ref) + ERROR_FLOOR
    lags = lag_list(np.ones_like(ref, bool))
    _, J, source = start_jacobian(default_start(), CANDIDATES, L)
    say(f"start Jacobian from {source}")
    out = {"lags": L,
           "errors": {"relative": REL_ERROR, "floor": ERROR_FLOOR},
           "per_parameter": lags_per_parameter(J, sigma, lags, say),
           "linear": linear_correlations(J, sigma, lags, say), "fits": {}}
    if not args.no_fits:
        say("3. fits (build=False), pulls and correlations")
        inputs = []
        for s in args.sensors:
            a = galsim_acoeffs(s, L)
            inputs.append((f"GalSim {s} noise-free",
                           AcoeffTable(a, REL_ERROR * np.abs(a) + ERROR_FLOOR,
                                       source=f"GalSim {s} a-matrix")))
        if os.path.exists(MEASURED):
            inputs.append(("measured ITL covariances",
                           measured_acoeffs(read_calibration_input([MEASURED]))))
        for label, table in inputs:
            out["fits"][label] = report_fit(label, table, say)
    write_results(args.out, lines, out, script=__file__, json_default=float)


if __name__ == "__main__":
    main()
