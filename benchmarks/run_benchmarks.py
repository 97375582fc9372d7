"""Benchmarks of the engine (issue 2): template build and 4k x 4k superposition.

Run from the repository root::

    python benchmarks/run_benchmarks.py [--size 4096] [--out benchmarks/results]

Prints the figures and writes ``<out>.json`` and ``<out>.txt`` (quoted by
``docs/benchmarks.rst``). Timings are wall-clock seconds on this machine;
the machine's core count is recorded with them.
"""

import argparse
import json
import os
import platform
import resource
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from lsst_bfdrift.superpose import moment_maps  # noqa: E402
from lsst_bfdrift.template import TemplateSettings, build_template, load_default_template  # noqa: E402,E501


def _timed(fn, *a, **k):
    t0 = time.perf_counter()
    out = fn(*a, **k)
    return out, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=4096, help="side of the charge image")
    ap.add_argument("--out", default=os.path.join("benchmarks", "results"))
    args = ap.parse_args()
    rows = {"machine": {"cores": os.cpu_count(), "python": platform.python_version(),
                        "numpy": np.__version__, "platform": platform.platform()}}
    lines = [f"machine: {os.cpu_count()} cores, Python {platform.python_version()}, "
             f"numpy {np.__version__}"]

    # 1. default template build (21 x 21, 8 samples, tol 1e-4 px), serial vs 2 processes
    times = {}
    for workers in (1, 2):
        tpl, dt = _timed(build_template, settings=TemplateSettings(workers=workers))
        times[workers] = dt
        a00 = tpl.summary()["A00"]
    rows["template_build"] = {"seconds_workers1": times[1], "seconds_workers2": times[2],
                              "speedup": times[1] / times[2], "target_seconds": 30.0,
                              "A00": a00}
    lines.append(f"template build 21x21x8, tol 1e-4: {times[1]:.1f} s (1 process), "
                 f"{times[2]:.1f} s (2 processes), ratio {times[1] / times[2]:.2f}x; "
                 f"target <= 30 s")

    # 2. superposition of a size x size charge image into moment maps
    rng = np.random.default_rng(7)
    n = args.size
    charge = rng.poisson(2e4, (n, n)).astype(np.float64)
    tpl = load_default_template()
    _, dt1 = _timed(moment_maps, tpl, charge, workers=1)
    maps, dt2 = _timed(moment_maps, tpl, charge, workers=2)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    rows["superpose"] = {"size": n, "seconds_fft_workers1": dt1, "seconds_fft_workers2": dt2,
                         "pixels_per_second": n * n / dt2, "peak_rss_mb": peak,
                         "image_mb": charge.nbytes / 2**20,
                         "area_sum_minus_npix": float(maps.area.sum() - n * n)}
    lines.append(f"superposition {n}x{n} -> area/centroid/ellipticity maps: {dt1:.1f} s "
                 f"(1 FFT thread), {dt2:.1f} s (2), {n * n / dt2 / 1e6:.2f} Mpix/s, peak RSS "
                 f"{peak:.0f} MB (image {charge.nbytes / 2**20:.0f} MB)")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    with open(args.out + ".json", "w") as fh:
        json.dump(rows, fh, indent=2)
    with open(args.out + ".txt", "w") as fh:
        fh.write(text)


if __name__ == "__main__":
    main()
