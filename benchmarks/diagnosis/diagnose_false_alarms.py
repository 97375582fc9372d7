"""False-alarm rate of the diagnosis on effect-free GalSim flat sets (issue 15).

Reads the sets written by ``benchmarks/diagnosis/galsim_flat_sets.py`` (GalSim's own
pixel areas; sensors, sizes, ladders and seeds varied), runs
:func:`lsst_bfdrift.diagnosis.effects_fit.diagnose` with the default
threshold and the bundled electrostatic basis on each, and counts a false
alarm when an effect is added or the residual is called unexplained. Also
reports the chi2/dof and p-value distribution of the base fit (a
Kolmogorov-Smirnov test of the p-values against uniform: calibrated errors
give uniform p-values) and how often the edge signature is named.

    python benchmarks/diagnosis/galsim_flat_sets.py --n-sets 50   # first (about 1 h on 2 cores)
    python benchmarks/diagnosis/diagnose_false_alarms.py [--cache /work/flatcache] [--append]

``--append`` keeps the rows of the existing results file and diagnoses only
the sets it does not hold (for adding sets without redrawing the old ones;
rows whose set is also in the cache are checked against a fresh run of the
first ``--check`` of them, so a changed diagnosis shows). Writes
``benchmarks/diagnosis/diagnose_false_alarms_results.txt`` and ``.json``.
"""

import argparse
import glob
import io
import json
import os
import platform
import sys
import time

import numpy as np
from scipy import stats

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.calibration.acoeff_model import load_default_basis  # noqa: E402
from lsst_bfdrift.diagnosis.effects_fit import diagnose, observations_from_pairs  # noqa: E402

OUT = os.path.join(HERE, "diagnose_false_alarms_results")


def run_set(path, basis):
    d = np.load(path)
    cfg = json.loads(str(d["config"]))
    pairs = [(f[0].astype(float), f[1].astype(float)) for f in d["flats"]]
    t0 = time.time()
    res = diagnose(observations_from_pairs(pairs, max_lag=3, exptimes=d["exptime"]), basis)
    base = res.steps[0]
    return {"set": cfg["index"], "sensor": cfg["sensor"], "size": cfg["size"],
            "pairs": len(pairs), "levels": len(cfg["levels"]),
            "top": cfg["levels"][-1], "chi2_dof": base["chi2_dof"], "dof": base["dof"],
            "p_value": base["p_value"], "effects_added": res.effects_added,
            "unexplained": res.unexplained,
            "false_alarm": bool(res.effects_added or res.unexplained),
            "edge_named": bool(res.edge and res.edge["detected"]),
            "seconds": time.time() - t0}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/work/flatcache")
    ap.add_argument("--append", action="store_true",
                    help="keep the existing file's rows; diagnose only the sets it lacks")
    ap.add_argument("--check", type=int, default=2,
                    help="with --append: rediagnose this many kept sets found in the cache")
    args = ap.parse_args(argv)
    paths = sorted(glob.glob(os.path.join(args.cache, "set_*.npz")))
    if not paths:
        raise SystemExit(f"no sets in {args.cache}: run benchmarks/diagnosis/galsim_flat_sets.py "
                         "first")
    basis = load_default_basis()
    kept = {}
    if args.append and os.path.isfile(OUT + ".json"):
        with open(OUT + ".json") as fh:
            kept = {r["set"]: dict(r, kept=True) for r in json.load(fh)["sets"]}
    index = {p: int(os.path.basename(p)[4:7]) for p in paths}
    checks = []
    for p in [p for p in paths if index[p] in kept][:args.check]:
        r, old = run_set(p, basis), kept[index[p]]
        checks.append({"set": index[p], "chi2_dof_kept": old["chi2_dof"],
                       "chi2_dof_now": r["chi2_dof"], "p_kept": old["p_value"],
                       "p_now": r["p_value"], "same_decision":
                       r["false_alarm"] == old["false_alarm"]})
    paths = [p for p in paths if index[p] not in kept]
    out = io.StringIO()

    def say(s=""):
        print(s, flush=True)
        out.write(s + "\n")

    say(f"Diagnosis false alarms on {len(paths) + len(kept)} effect-free GalSim flat sets "
        f"({platform.machine()}, {os.cpu_count()} cores)"
        + (f"; {len(kept)} rows kept from the previous results file (marked *), "
           f"{len(paths)} sets diagnosed in this run" if kept else ""))
    for c in checks:
        say(f"  check: set {c['set']} rediagnosed now: chi2/dof {c['chi2_dof_now']:.3f} "
            f"(kept row {c['chi2_dof_kept']:.3f}), p {c['p_now']:.3f} ({c['p_kept']:.3f}), "
            f"same decision: {c['same_decision']}")
    say("set  sensor         size pairs lv  top(ke) chi2/dof    p     added / unexplained  edge")
    rows = []
    for r in sorted(kept.values(), key=lambda r: r["set"]):
        rows.append(r)
        say(f"{r['set']:3d}* {r['sensor']:14s} {r['size']:4d} {r['pairs']:5d} {r['levels']:2d} "
            f"{r['top'] / 1e3:7.1f} {r['chi2_dof']:8.3f} {r['p_value']:6.3f}  "
            f"{','.join(r['effects_added']) or '-':>12s} / {str(r['unexplained']):5s}  "
            f"{'named' if r['edge_named'] else '-'}")
    for p in paths:
        r = run_set(p, basis)
        rows.append(r)
        say(f"{r['set']:3d}  {r['sensor']:14s} {r['size']:4d} {r['pairs']:5d} {r['levels']:2d} "
            f"{r['top'] / 1e3:7.1f} {r['chi2_dof']:8.3f} {r['p_value']:6.3f}  "
            f"{','.join(r['effects_added']) or '-':>12s} / {str(r['unexplained']):5s}  "
            f"{'named' if r['edge_named'] else '-'}")
    n = len(rows)
    fa = sum(r["false_alarm"] for r in rows)
    pv = np.array([r["p_value"] for r in rows])
    ks = stats.kstest(pv, "uniform")
    lo, hi = stats.beta.ppf([0.025, 0.975], fa + 0.5, n - fa + 0.5)  # Jeffreys interval
    summary = {"n_sets": n, "false_alarms": int(fa), "rate": fa / n,
               "rate_95": [float(lo), float(hi)],
               "chi2_dof_median": float(np.median([r["chi2_dof"] for r in rows])),
               "chi2_dof_range": [float(min(r["chi2_dof"] for r in rows)),
                                  float(max(r["chi2_dof"] for r in rows))],
               "p_uniform_ks": float(ks.pvalue),
               "edge_named": int(sum(r["edge_named"] for r in rows)),
               "sensors": sorted({r["sensor"] for r in rows}),
               "sizes": sorted({r["size"] for r in rows})}
    say()
    say(f"false alarms: {fa} of {n} = {fa / n:.1%} (95 % interval {lo:.1%} - {hi:.1%}); "
        f"target <= 5 %")
    say(f"base fit chi2/dof: median {summary['chi2_dof_median']:.3f}, range "
        f"{summary['chi2_dof_range'][0]:.3f} - {summary['chi2_dof_range'][1]:.3f}; p-values "
        f"against uniform: KS p = {ks.pvalue:.2f}")
    say(f"edge signature named in {summary['edge_named']} of {n} sets (GalSim's open edges)")
    write_results(OUT, out.getvalue().removesuffix("\n").split("\n"),
                  {"summary": summary, "checks": checks, "sets": rows}, script=__file__)


if __name__ == "__main__":
    main()
