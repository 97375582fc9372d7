"""4096 x 4096 CCD through BrighterFatterDriftTask: drift and the geometry maps against astier23.

Part 1 (issues 5 and 17), in one process, the Tasks' calls alternated:
``astier23`` (correction only), ``drift`` (correction only), ``default``
(drift with the geometry maps, ``geometry_method='linear'``) and
``drift+exact maps`` (``geometry_method='exact'``) and ``floor of default``
(drift plus the least work any FFT route to the five maps needs:
:class:`MapsFloor`) on the field below; then
drift against astier23 on a crowded field (4000 stars) and a 1e5 e flat.
Each Task's first call on the field (kernels compiled beforehand on a
64 x 64 cut-out, as in part 2) and the median and min-max of ``--repeat``
warm calls; peak memory of one call above the input as traced by
``tracemalloc`` (numpy arrays; FFT library buffers are not traced), in
units of the float64 image; for the default Task also how much of the
image the exact fallback covered. Part 1 also records the linearised maps'
largest error against the exact maps (same samples) on a 1024 x 1024
cut-out of each field, in units of each map's signal.

Part 2: each configuration runs in its own subprocess. Memory is the peak RSS
(``ru_maxrss``) of that process minus its RSS just before ``task.run`` (the
input image and the imported libraries are the baseline), in units of the
image's size (float64). The children also count the applications of the
swept-area operator (``SweptAreas.__call__`` and batched window stacks,
``SweptAreas.apply_stack``) and the FFTs (``rfft2`` / ``irfft2`` calls,
kernel transforms included) made inside :mod:`lsst_bfdrift.templates.swept` and
:mod:`lsst_bfdrift.correction.solvers` during ``task.run``. The Task keeps its
operators (kernel transforms) between calls, for every method alike. Run from the repository
root. ``warm`` is the median of seven more calls on the same image in the same
process (operators and work arrays kept by the Task, memory pools warm),
with their spread (min-max); ``drift+geometry`` is the Task's default::

    python benchmarks/performance/bench_task.py [--size 4096] [--repeat 5]

Prints the tables and writes ``benchmarks/performance/bench_task_results.json`` / ``.txt``.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time
import tracemalloc

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402


CHILD = r"""
import json, os, resource, sys, time
import numpy as np
from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.correction import solvers as C
count = dict(ops=0, ffts=0)
_call = C.SweptAreas.__call__
def _counted_call(self, q, **kw):
    count["ops"] += 1
    return _call(self, q, **kw)
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


def star_field(n, n_stars, seed=1):
    """Sky of 1200 e and ``n_stars`` Gaussian stars (sigma 1.5 px) of 1e4 to 1.5e6 e."""
    rng = np.random.default_rng(seed)
    img = rng.poisson(1200.0, (n, n)).astype(np.float64)
    yy, xx = np.mgrid[-8:9, -8:9]
    for _ in range(n_stars):
        x, y = rng.integers(20, n - 20, 2)
        f = 10 ** rng.uniform(4, np.log10(1.5e6))
        img[y - 8:y + 9, x - 8:x + 9] += f * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2) / (
            2 * np.pi * 1.5**2)
    return img


def alternated(tasks, img, repeat):
    """First call, warm calls alternated, traced peak memory of each Task."""
    from lsst_bfdrift.geometry import linear

    out = {}
    for name, task in tasks.items():
        task.run(img[:64, :64])  # compile outside the timing
    for name, task in tasks.items():
        t0 = time.perf_counter()
        task.run(img)
        out[name] = {"first": time.perf_counter() - t0, "warm": []}
    for _ in range(repeat):
        for name, task in tasks.items():
            t0 = time.perf_counter()
            task.run(img)
            out[name]["warm"].append(time.perf_counter() - t0)
    for name, task in tasks.items():
        info = {}
        orig = linear.linear_moment_maps

        def spy(*a, **k):
            k["info"] = info
            return orig(*a, **k)

        from lsst_bfdrift.correction import task as task_mod
        task_mod.linear_moment_maps = spy
        tracemalloc.start()
        tracemalloc.reset_peak()
        res = task.run(img)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        task_mod.linear_moment_maps = orig
        del res
        r = out[name]
        r.update(median=float(np.median(r["warm"])), min=min(r["warm"]), max=max(r["warm"]),
                 peak_x_image=peak / img.nbytes)
        if info:
            r.update(exact_fraction=info["exact_fraction"],
                     canvas_fraction=info["canvas_fraction"], windows=info["windows"],
                     geometry=info["method"])
    return out


class MapsFloor:
    """Drift's correction plus the least extra work of first-order maps made
    by FFT convolution: per block of the correction's pass, three more
    kernel products and inverse transforms (the maps' three fields beyond
    the swept areas; the image's transform is the pass's own, computed here
    once beforehand and not timed), and the five maps written (area float64,
    four float32). No bound, no exact windows, no combination of fields:
    a floor for ``default``, not a method."""

    def __init__(self, task, img):
        from scipy import fft as sp_fft

        from lsst_bfdrift.geometry.first_order import linear_kernels

        self.task, self.fft = task, sp_fft
        ny, nx = img.shape
        ops = task._operators(np.float32)
        halo = (task.template.size + 1) // 2 + 2
        strip = task.config.strip or 512
        self.blocks = []
        for r0 in range(0, ny, strip):
            r1 = min(r0 + strip, ny)
            a, z = max(r0 - halo, 0), min(r1 + halo, ny)
            op = ops((z - a, nx))
            pad = np.zeros(op.fshape, np.float32)
            pad[:z - a, :nx] = img[a:z]
            spectra = linear_kernels(task.template).edge_spectra(op.fshape, np.float32, 2)
            self.blocks.append((r0, r1, r0 - a, op.fshape, sp_fft.rfft2(pad, workers=2),
                                spectra))

    def run(self, img):
        if img.shape[0] < 1024:  # the compile call of alternated()
            return self.task.run(img)
        res = self.task.run(img)
        ny, nx = img.shape
        area = np.empty((ny, nx))
        maps = np.empty((4, ny, nx), np.float32)
        for r0, r1, off, fshape, fq, spectra in self.blocks:
            prod = np.empty_like(fq)
            fields = []
            for k in range(3):
                np.multiply(fq, spectra[k], out=prod)
                fields.append(self.fft.irfft2(prod, fshape, workers=2, overwrite_x=True))
            rows = slice(off, off + r1 - r0)
            area[r0:r1] = fields[0][rows, :nx]
            area[r0:r1] += 1.0
            for k in range(4):
                maps[k, r0:r1] = fields[k % 3][rows, :nx]
        return res, area, maps


def map_errors(img, template):
    """Largest abs(linear - exact) over each map's signal (max abs(exact - nominal))."""
    from lsst_bfdrift.geometry import LINEAR_MAPS, linear_moment_maps, moment_maps

    exact = moment_maps(template, img, samples=8, workers=2)
    info = {}
    lin = linear_moment_maps(template, img, samples=8, workers=2, info=info)
    raw = linear_moment_maps(template, img, samples=8, workers=2, fallback=False)
    nominal = dict(area=1.0, dx=0.0, dy=0.0, e1=0.0, e2=0.0)
    out = {}
    for k in LINEAR_MAPS:
        s = np.abs(getattr(exact, k) - nominal[k]).max()
        out[k] = dict(maps=float(np.abs(getattr(lin, k) - getattr(exact, k)).max() / s),
                      linear_only=float(np.abs(getattr(raw, k) - getattr(exact, k)).max() / s))
    out["exact_fraction"] = info["exact_fraction"]
    return out


def part1(size, repeat, load):
    from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    from lsst_bfdrift.templates.template import load_default_template

    def task(method="drift", **kw):
        return BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
            method=method, workers=2, **kw))

    results = {}
    img = star_field(size, 400)
    results["field"] = alternated({
        "astier23": task("astier23", compute_geometry=False),
        "drift": task(compute_geometry=False),
        "default": task(),
        "drift+exact maps": task(geometry_method="exact"),
        "floor of default": MapsFloor(task(compute_geometry=False), img)}, img, repeat)
    crowded = star_field(size, 4000, seed=2)
    results["crowded"] = alternated({"astier23": task("astier23", compute_geometry=False),
                                     "drift": task(compute_geometry=False)}, crowded, repeat)
    flat = np.random.default_rng(3).poisson(1e5, (size, size)).astype(np.float64)
    results["flat"] = alternated({"astier23": task("astier23", compute_geometry=False),
                                  "drift": task(compute_geometry=False)}, flat, repeat)
    t = load_default_template()
    c = min(1024, size)
    results["errors"] = {"field": map_errors(img[:c, :c], t),
                         "crowded": map_errors(crowded[:c, :c], t),
                         "flat": map_errors(flat[:c, :c], t)}
    lines = [f"Part 1: {size}x{size}, one process, calls alternated, median (min-max) of "
             f"{repeat} warm calls and the first call; {os.cpu_count()} cores "
             f"({platform.machine()}, {platform.python_version()}); 1-min load average "
             f"{load[0]:.2f} before, {os.getloadavg()[0]:.2f} after (1 to 2: this job alone)"]
    for field in ("field", "crowded", "flat"):
        rows = results[field]
        base = rows["astier23"]
        title = {"field": "400 stars", "crowded": "4000 stars", "flat": "flat 1e5 e"}[field]
        lines.append(f"  {title}:")
        for name, r in rows.items():
            extra = ""
            if "canvas_fraction" in r:
                extra = (f"  exact fallback: {r['exact_fraction']:.2%} of the image flagged, "
                         f"{r['canvas_fraction']:.2%} computed exactly ({r['windows']} windows)")
            lines.append(
                f"    {name:17s} warm {r['median']:6.3f} s ({r['min']:.3f}-{r['max']:.3f}) = "
                f"{r['median'] / base['median']:5.2f}x astier23 "
                f"({r['min'] / base['max']:.2f}-{r['max'] / base['min']:.2f}); first "
                f"{r['first']:6.3f} s = {r['first'] / base['first']:5.2f}x; "
                f"peak {r['peak_x_image']:4.1f} x image{extra}")
    lines.append("  linearised maps against the exact ones (8 samples), largest error over the "
                 "signal, on the 1024 x 1024 cut-outs (maps returned / linear alone):")
    for field, errs in results["errors"].items():
        lines.append(f"    {field:8s} " + "  ".join(
            f"{k} {errs[k]['maps']:.1e}/{errs[k]['linear_only']:.1e}"
            for k in ("area", "dx", "dy", "e1", "e2"))
            + f"  (exact on {errs['exact_fraction']:.1%})")
    return results, lines


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(HERE, "bench_task_results"))
    args = ap.parse_args()
    rows = {}
    load = os.getloadavg()
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
        code = CHILD.format(size=args.size, method=method, geometry=geometry,
                            extra=extra, repeat=7)
        out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                             text=True).stdout.strip().splitlines()[-1]
        rows[name] = json.loads(out)
    # part 2 first: a child's ru_maxrss starts from its parent's peak, which
    # part 1's images would raise
    alt, alt_lines = part1(args.size, args.repeat, load)
    base = rows["astier23"]["seconds"]
    wbase = rows["astier23"]["warm_seconds"]
    lines = alt_lines + [f"Part 2: {args.size}x{args.size} image, {os.cpu_count()} cores, "
                         "one process per configuration"]
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
    write_results(args.out, lines, {"size": args.size, "cores": os.cpu_count(),
                                    "load_average_before": load[0],
                                    "load_average_after": os.getloadavg()[0],
                                    "alternated": alt, "runs": rows},
                  script=__file__, indent=2)


if __name__ == "__main__":
    main()
