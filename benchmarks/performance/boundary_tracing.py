"""Boundary tracing against an earlier version of the package: the cost of a model's a_ij.

Every ``bfdrift calibrate`` of the electrostatic model evaluates the model's
a_ij (:func:`lsst_bfdrift.calibration.fit_model.model_acoeffs`: pixel boundaries
of a quadrant around a 1e4 e aggressor, bisected to 2e-6 px) tens of
times, and every template build traces boundaries the same way. This script
times the same work in this tree and in an earlier revision (``--against``,
checked out into a temporary git worktree), side by side in one run:

* Part 1: ``model_acoeffs`` at the bundled template's parameters, lags 0-3
  (what the fit evaluates) and 0-9, in two persistent worker processes (one
  per tree, numba compiled and warm), calls alternated, ``--repeat`` each;
  medians and ratios; the largest difference of the a_ij between the trees
  (relative to a00), which the bisection tolerance bounds.
* Part 2: ``bfdrift calibrate`` end to end (a fresh process per call:
  imports, numba's cache, fit, template build, refinement) on the measured
  ITL a-matrix of ``shared/``, alternated, ``--calibrate-repeat`` each.

Run from the repository root (2 cores)::

    python benchmarks/performance/boundary_tracing.py [--against b85363e]

Writes ``benchmarks/performance/boundary_tracing_results.txt`` and ``.json``.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import REPO, Lines, settings_record, write_results  # noqa: E402

WORKER = r"""
import json, sys, time
import numpy as np
from lsst_bfdrift.calibration.fit_model import default_start, model_acoeffs
start = default_start()
model_acoeffs(start, 3)  # compile and warm
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    lag = int(line)
    t = time.perf_counter()
    a = model_acoeffs(start, lag)
    print(json.dumps({"seconds": time.perf_counter() - t, "a": a.tolist()}), flush=True)
"""

MEASURED = os.path.join(REPO, "..", "shared", "data", "measured", "itl_covariances_21oct19.txt")


def _env(tree, threads):
    env = dict(os.environ, PYTHONPATH=tree, OMP_NUM_THREADS="1")
    if threads:
        env["NUMBA_NUM_THREADS"] = str(threads)
    return env


def _worker(tree, threads):
    p = subprocess.Popen([sys.executable, "-c", WORKER], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, text=True, env=_env(tree, threads), cwd=tree)
    assert json.loads(p.stdout.readline())["ready"]
    return p


def _ask(p, lag):
    p.stdin.write(f"{lag}\n")
    p.stdin.flush()
    return json.loads(p.stdout.readline())


def _calibrate(tree, threads, out):
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import sys; from lsst_bfdrift.cli import main; "
                    "sys.exit(main(sys.argv[1:]))", "calibrate", MEASURED, "--out", out,
                    "--overwrite", "--quiet"], check=True, env=_env(tree, threads), cwd=tree,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", default="b85363e", help="earlier revision (git ref)")
    ap.add_argument("--repeat", type=int, default=7, help="model evaluations per tree and lag")
    ap.add_argument("--calibrate-repeat", type=int, default=3,
                    help="bfdrift calibrate runs per tree (0: skip part 2)")
    ap.add_argument("--threads", type=int, default=0,
                    help="NUMBA_NUM_THREADS of the workers (0: numba's default, the cores)")
    ap.add_argument("--out", default=os.path.join(HERE, "boundary_tracing_results"))
    args = ap.parse_args()
    say = Lines(note=f"{platform.machine()}, Python {platform.python_version()}")
    rev = subprocess.run(["git", "-C", REPO, "rev-parse", "--short", args.against], check=True,
                         capture_output=True, text=True).stdout.strip()
    head = subprocess.run(["git", "-C", REPO, "rev-parse", "--short", "HEAD"], check=True,
                          capture_output=True, text=True).stdout.strip()
    dirty = bool(subprocess.run(["git", "-C", REPO, "status", "--porcelain", "lsst_bfdrift"],
                                capture_output=True, text=True).stdout.strip())
    names = {"this tree": f"{head}{' + changes' if dirty else ''}", "earlier": rev}
    record = {"settings": settings_record(args), "trees": names, "model_acoeffs": {},
              "calibrate": {}}
    with tempfile.TemporaryDirectory() as tmp:
        old = os.path.join(tmp, "earlier")
        subprocess.run(["git", "-C", REPO, "worktree", "add", "--detach", "-q", old, rev],
                       check=True)
        try:
            trees = {"this tree": REPO, "earlier": old}
            say(f"this tree {names['this tree']} against {rev}; numba threads "
                f"{args.threads or 'default (' + str(os.cpu_count()) + ')'}")
            say("Part 1: model_acoeffs at the bundled template's parameters (1e4 e aggressor, "
                f"tol 2e-6 px), warm workers, calls alternated, median (min-max) of {args.repeat}")
            workers = {k: _worker(t, args.threads) for k, t in trees.items()}
            for lag in (3, 9):
                times = {k: [] for k in trees}
                values = {}
                for _ in range(args.repeat):
                    for k, p in workers.items():
                        r = _ask(p, lag)
                        times[k].append(r["seconds"])
                        values[k] = np.array(r["a"])
                med = {k: float(np.median(v)) for k, v in times.items()}
                diff = np.abs(values["this tree"] - values["earlier"]).max() \
                    / abs(values["earlier"][0, 0])
                for k in trees:
                    say(f"  lags 0-{lag}  {k:9s} {med[k]:6.3f} s ({min(times[k]):.3f}-"
                        f"{max(times[k]):.3f})")
                say(f"  lags 0-{lag}  earlier / this tree {med['earlier'] / med['this tree']:.2f}x;"
                    f" largest a_ij difference {diff:.1e} of |a00|")
                record["model_acoeffs"][f"lag{lag}"] = {"seconds": times, "median": med,
                                                        "ratio": med["earlier"] / med["this tree"],
                                                        "max_diff_over_a00": float(diff)}
            for p in workers.values():
                p.stdin.close()
                p.wait()
            if args.calibrate_repeat > 0:
                say("Part 2: bfdrift calibrate on the measured ITL a-matrix (fresh process per "
                    f"call), alternated, median (min-max) of {args.calibrate_repeat}")
                times = {k: [] for k in trees}
                for k, t in trees.items():  # numba's cache of each tree, written once
                    _calibrate(t, args.threads, os.path.join(tmp, f"warm_{len(k)}.fits"))
                for i in range(args.calibrate_repeat):
                    for k, t in trees.items():
                        times[k].append(_calibrate(t, args.threads,
                                                   os.path.join(tmp, f"t{i}_{len(k)}.fits")))
                med = {k: float(np.median(v)) for k, v in times.items()}
                for k in trees:
                    say(f"  {k:9s} {med[k]:6.1f} s ({min(times[k]):.1f}-{max(times[k]):.1f})")
                say(f"  earlier / this tree {med['earlier'] / med['this tree']:.2f}x")
                record["calibrate"] = {"seconds": times, "median": med,
                                       "ratio": med["earlier"] / med["this tree"]}
        finally:
            subprocess.run(["git", "-C", REPO, "worktree", "remove", "--force", old], check=False)
    load = os.getloadavg()
    say(f"1-min load average after: {load[0]:.2f}")
    write_results(args.out, say, record, script=__file__)


if __name__ == "__main__":
    main()
