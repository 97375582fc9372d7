"""Geometry maps of a 4096 x 4096 CCD: full template against resampled edges.

Times :func:`lsst_bfdrift.geometry.superpose.moment_maps` (area, centroid shift,
second moments and e1/e2 of every pixel's final polygon) with the bundled
default template (21 x 21, 32 samples per edge) used as it is, and with its
edge profiles resampled to fewer samples (``samples=k``, moment-preserving,
:func:`~lsst_bfdrift.geometry.superpose.resample_template`), in double and single
precision FFTs. Every configuration runs in its own process, one after the
other in one run (compare ratios only; CPU seconds, ``time.process_time`` of
the process, depend less on other jobs than wall-clock seconds); memory is the peak RSS
(``ru_maxrss``) minus the RSS just before the call (image and libraries
loaded), in units of the float64 image.

Accuracy: each configuration's maps against the full computation (32
samples, float64) on the same image: max and rms of the difference divided
by the max and rms of the map's brighter-fatter signal (``area - 1``,
``dx``, ``dy``, ``e1``, ``e2``). Two images: sky (1000 e) with 400 Gaussian
stars of 1e4 to 1.5e6 e (sigma 1.5 px, peak up to ~1.1e5 e per pixel), and a
Poisson flat of 1e5 e. Run from the repository root::

    python benchmarks/performance/bench_geometry.py [--size 4096]

Prints a table and writes ``benchmarks/performance/bench_geometry_results.json`` / ``.txt``.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402


CHILD = r"""
import json, os, resource, sys, time
import numpy as np
from lsst_bfdrift.templates.template import load_default_template
import lsst_bfdrift.geometry.superpose as S
n, kind, samples, dtype, tmp = {size}, {kind!r}, {samples!r}, {dtype!r}, {tmp!r}
mm = S.moment_maps
kw = dict(workers=2, samples=samples, dtype=np.dtype(dtype))
rng = np.random.default_rng(1)
if kind == "stars":
    img = rng.poisson(1000.0, (n, n)).astype(np.float64)
    yy, xx = np.mgrid[-8:9, -8:9]
    for k in range(400):
        x, y = rng.integers(20, n - 20, 2)
        f = 10 ** rng.uniform(4, np.log10(1.5e6))
        img[y - 8:y + 9, x - 8:x + 9] += (f * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2)
                                          / (2 * np.pi * 1.5**2))
else:
    img = rng.poisson(1e5, (n, n)).astype(np.float64)
tpl = load_default_template()
mm(tpl, img[:64, :64], **kw)   # compiled kernels loaded outside the timing
base = int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
c0, t0 = time.process_time(), time.perf_counter()
maps = mm(tpl, img, **kw)
dt, cpu = time.perf_counter() - t0, time.process_time() - c0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
names = ("area", "dx", "dy", "e1", "e2")
nominal = dict(area=1.0, dx=0.0, dy=0.0, e1=0.0, e2=0.0)
ref_path = os.path.join(tmp, kind + "_{{}}.npy")
acc = {{}}
if samples is None and dtype == "float64":
    for k in names:
        np.save(ref_path.format(k), getattr(maps, k))
else:
    for k in names:
        ref = np.load(ref_path.format(k))
        d = getattr(maps, k) - ref
        sig = ref - nominal[k]
        acc[k] = dict(max=float(np.abs(d).max() / np.abs(sig).max()),
                      rms=float(np.sqrt(np.mean(d**2) / np.mean(sig**2))),
                      signal_max=float(np.abs(sig).max()))
print(json.dumps(dict(seconds=dt, cpu_seconds=cpu, peak_rss_mb=peak - base, image_mb=img.nbytes / 2**20,
                      accuracy=acc, area_sum_minus_npix=float(maps.area.sum() - n * n))))
"""


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--out", default=os.path.join(HERE, "bench_geometry_results"))
    args = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="bench_geometry_")
    # (label, image, samples, dtype); the full float64 run of each image comes
    # first: it writes the reference maps
    runs = [("full 32, float64", "stars", None, "float64"),
            ("full 32, float32", "stars", None, "float32"),
            ("samples 8, float64", "stars", 8, "float64"),
            ("samples 8, float32 (Task)", "stars", 8, "float32"),
            ("samples 6, float32", "stars", 6, "float32"),
            ("samples 4, float32", "stars", 4, "float32"),
            ("full 32, float64", "flat", None, "float64"),
            ("samples 8, float32 (Task)", "flat", 8, "float32"),
            ("samples 6, float32", "flat", 6, "float32"),
            ("samples 4, float32", "flat", 4, "float32")]
    rows = []
    try:
        for label, kind, samples, dtype in runs:
            code = CHILD.format(size=args.size, kind=kind, samples=samples,
                                dtype=dtype, tmp=tmp)
            proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
            if proc.returncode:
                sys.exit(f"{kind} {label} failed:\n{proc.stderr[-3000:]}")
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            r.update(label=label, image=kind, samples=samples, dtype=dtype)
            rows.append(r)
            print(f"  done: {kind} {label}: {r['seconds']:.1f} s", file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    load = os.getloadavg()[0]
    lines = [f"{args.size}x{args.size} image, {os.cpu_count()} cores, 2 FFT threads, "
             f"default template (21x21, 32 samples per edge); load average {load:.1f} at the end"]
    for kind in ("stars", "flat"):
        sel = [r for r in rows if r["image"] == kind]
        base, cbase = sel[0]["seconds"], sel[0]["cpu_seconds"]
        title = ("sky 1000 e + 400 stars 1e4-1.5e6 e" if kind == "stars"
                 else "flat 1e5 e (Poisson)")
        lines.append(f"{title}: wall and CPU seconds (speed-up against the first line), "
                     f"memory; max (rms) |map - full 32 float64| / max (rms) |signal|")
        for r in sel:
            acc = r["accuracy"]
            err = "  ".join(f"{k} {acc[k]['max']:.1e} ({acc[k]['rms']:.1e})" for k in acc)
            lines.append(f"  {r['label']:26s} {r['seconds']:5.1f} s ({base / r['seconds']:5.2f}x), "
                         f"CPU {r['cpu_seconds']:5.1f} s ({cbase / r['cpu_seconds']:5.2f}x)  "
                         f"peak RSS - baseline {r['peak_rss_mb']:5.0f} MB = "
                         f"{r['peak_rss_mb'] / r['image_mb']:4.1f} x image"
                         + (f"  {err}" if err else "  (reference)"))
        sig = next((r["accuracy"] for r in sel if r["accuracy"]), {})
        if sig:
            lines.append("  signal max: " + "  ".join(f"{k} {v['signal_max']:.3g}"
                                                      for k, v in sig.items()))
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(args.out, lines, {"size": args.size, "cores": os.cpu_count(),
                                    "load_average": load, "runs": rows},
                  script=__file__, indent=2)


if __name__ == "__main__":
    main()
