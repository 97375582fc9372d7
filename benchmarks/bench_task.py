"""4096 x 4096 CCD through BrighterFatterDriftTask: drift against astier23 (issue 5).

Each configuration runs in its own subprocess. Memory is the peak RSS
(``ru_maxrss``) of that process minus its RSS just before ``task.run`` (the
input image and the imported libraries are the baseline), in units of the
image's size (float64). The children also count the applications of the
swept-area operator (``SweptAreas.__call__`` and batched window stacks,
``SweptAreas.apply_stack``) and the FFTs (``rfft2`` / ``irfft2`` calls,
kernel transforms included) made inside :mod:`lsst_bfdrift.templates.swept` and
:mod:`lsst_bfdrift.correction.solvers` during ``task.run``. The Task keeps its
operators (kernel transforms) between calls, for every method alike. Run from the repository
root. ``warm`` is the median of seven more calls on the same image in the same
process (operators and work arrays kept by the Task, memory pools warm; not
for ``drift+geometry``), with their spread (min-max)::

    python benchmarks/bench_task.py [--size 4096]

Prints a table and writes ``benchmarks/task_results.json`` / ``.txt``.
"""

import argparse
import json
import os
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from lsst_bfdrift.utils.io import write_json, write_text  # noqa: E402

CHILD = r"""
import json, os, resource, sys, time
import numpy as np
sys.path.insert(0, {root!r})
from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.correction import solvers as C
count = dict(ops=0, ffts=0)
_call = C.SweptAreas.__call__
def _counted_call(self, q):
    count["ops"] += 1
    return _call(self, q)
C.SweptAreas.__call__ = _counted_call
from lsst_bfdrift.templates import swept as SW
_sp_fft = SW.sp_fft
class _FFT:
    def __getattr__(self, name):
        f = getattr(_sp_fft, name)
        if name not in ("rfft2", "irfft2"):
            return f
        def counted(*a, **k):
            count["ffts"] += 1
            return f(*a, **k)
        return counted
SW.sp_fft = C.sp_fft = _FFT()
_stack = SW.SweptAreas.apply_stack
def _counted_stack(self, q):
    count["ops"] += 1
    return _stack(self, q)
SW.SweptAreas.apply_stack = _counted_stack
n = {size}
rng = np.random.default_rng(1)
img = rng.poisson(1200.0, (n, n)).astype(np.float64)   # sky
yy, xx = np.mgrid[-8:9, -8:9]
for k in range(400):                                     # stars, 1e4 to 1.5e6 e
    x, y = rng.integers(20, n - 20, 2)
    f = 10 ** rng.uniform(4, np.log10(1.5e6))
    img[y - 8:y + 9, x - 8:x + 9] += f * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2) / (2 * np.pi * 1.5**2)
task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(method={method!r},
                               compute_geometry={geometry}, workers=2, **{extra}))
task.run(img[:64, :64])  # compile/warm up outside the timing
count.update(ops=0, ffts=0)
base = int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
t0 = time.perf_counter()
res = task.run(img)
dt = time.perf_counter() - t0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
counted = dict(count)  # the timed call only
warm = []
for _ in range({repeat}):  # same shape again: FFT plans and memory pools warm
    t0 = time.perf_counter()
    task.run(img)
    warm.append(time.perf_counter() - t0)
print(json.dumps({{"seconds": dt, "peak_rss_mb": peak - base, "baseline_rss_mb": base,
                  "image_mb": img.nbytes / 2**20, "iterations": res.iterations,
                  "converged": res.converged, "operator_calls": counted["ops"],
                  "ffts": counted["ffts"],
                  "warm_seconds": float(np.median(warm)) if warm else None,
                  "warm_min": min(warm) if warm else None, "warm_max": max(warm) if warm else None,
                  "solver": res.header.get("BFSOLVER", "n/a")}}))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--out", default=os.path.join(HERE, "task_results"))
    args = ap.parse_args()
    root = os.path.dirname(HERE)
    rows = {}
    runs = (("astier23", "astier23", False, {}),
            ("astier23 no strips", "astier23", False, {"strip": None}),
            ("astier23 float64", "astier23", False, {"fft_precision": "float64"}),
            ("drift", "drift", False, {}),
            ("drift dense", "drift", False, {"sparse": False}),
            ("drift strip 1024", "drift", False, {"strip": 1024}),
            ("drift no strips", "drift", False, {"strip": None}),
            ("drift old solver", "drift", False, {"fft_precision": "float64", "start": "image",
                                                  "noise_tol": None, "strip": None,
                                                  "sparse": False}),
            ("drift+geometry", "drift", True, {}))
    for name, method, geometry, extra in runs:
        code = CHILD.format(root=root, size=args.size, method=method, geometry=geometry,
                            extra=extra, repeat=0 if geometry else 7)
        out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                             text=True).stdout.strip().splitlines()[-1]
        rows[name] = json.loads(out)
    base = rows["astier23"]["seconds"]
    wbase = rows["astier23"]["warm_seconds"]
    lines = [f"{args.size}x{args.size} image, {os.cpu_count()} cores"]
    for name, r in rows.items():
        ws = r["warm_seconds"]
        warm = "" if ws is None else (f"; warm {ws:5.2f} s ({ws / wbase:5.2f}x, "
                                      f"{r['warm_min']:.2f}-{r['warm_max']:.2f} s)")
        lines.append(f"{name:17s} {r['seconds']:7.2f} s  ({r['seconds'] / base:5.2f}x astier23)  "
                     f"peak RSS - baseline {r['peak_rss_mb']:6.0f} MB = "
                     f"{r['peak_rss_mb'] / r['image_mb']:4.1f}"
                     f" x image  operator calls {r['operator_calls']:3d}  FFTs {r['ffts']:3d}"
                     f"  iterations {r['iterations']} converged {r['converged']} solver {r['solver']}{warm}")
    ns = rows["astier23 no strips"]
    lines.append(f"drift / astier23 no strips: {rows['drift']['seconds'] / ns['seconds']:.2f}x first "
                 f"call, {rows['drift']['warm_seconds'] / ns['warm_seconds']:.2f}x warm")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_json(args.out + ".json", {"size": args.size, "cores": os.cpu_count(), "runs": rows},
               indent=2)
    write_text(args.out + ".txt", text)


if __name__ == "__main__":
    main()
