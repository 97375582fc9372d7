"""Where the drift solver's time goes, against astier23 (issue 5 performance).

Complements ``bench_task.py`` (one process per configuration) with
in-process figures on the same 4096 x 4096 field (sky 1200 e, 400 stars):

1. the two Tasks alternated eight times (warm): median and fastest call of
   each and their ratios;
2. the windowed series (``sparse_series``) split into its first-order pass
   (the astier23 pass, keeping the swept areas and gathering the cell
   statistics), the activity test and the windows, median of five calls,
   with the number of windows and the fraction of the image they cover, and
   the astier23 pass alone (``correct_half_shift``) in the same loop;
3. the crowded field (4000 stars) and the 1e5 e flat of ``bench_task.py``:
   the windowed series (first tier, then the second,
   :mod:`lsst_bfdrift.correction.tiles`, or the dense fallback) split into
   its parts, against the astier23 pass and the dense series;
4. the compiled edge transfer on a 64 x 64 window, one thread against the
   parallel kernel (median per call).

Run from the repository root::

    python benchmarks/performance/profile_drift.py

Prints and writes ``benchmarks/performance/profile_drift_results.txt``.
"""

import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402
from lsst_bfdrift.correction import _edge_kernels as E
from lsst_bfdrift.correction import solvers as C
from lsst_bfdrift.correction import series as S
from lsst_bfdrift.templates.swept import OperatorCache  # noqa: E402
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402


def star_field(n=4096, seed=1):
    """The field of bench_task.py."""
    rng = np.random.default_rng(seed)
    img = rng.poisson(1200.0, (n, n)).astype(np.float64)
    yy, xx = np.mgrid[-8:9, -8:9]
    for _ in range(400):
        x, y = rng.integers(20, n - 20, 2)
        f = 10 ** rng.uniform(4, np.log10(1.5e6))
        img[y - 8:y + 9, x - 8:x + 9] += f * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2) / (
            2 * np.pi * 1.5**2)
    return img


def timed(f, *a, **k):
    t0 = time.perf_counter()
    out = f(*a, **k)
    return out, time.perf_counter() - t0


def main():
    lines = [f"4096 x 4096 field of bench_task.py, {os.cpu_count()} cores, 2 FFT threads"]
    img = star_field()
    t = load_default_template()
    # 1. alternating Tasks
    tasks = {m: BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        method=m, compute_geometry=False, workers=2)) for m in ("drift", "astier23")}
    for task in tasks.values():
        task.run(img)
    times = {m: [] for m in tasks}
    for _ in range(8):
        for m, task in tasks.items():
            times[m].append(timed(task.run, img)[1])
    md = {m: float(np.median(v)) for m, v in times.items()}
    mn = {m: float(np.min(v)) for m, v in times.items()}
    lines.append(f"1. Tasks alternated 8 times: drift median {md['drift']:.3f} s (fastest "
                 f"{mn['drift']:.3f} s), astier23 median {md['astier23']:.3f} s (fastest "
                 f"{mn['astier23']:.3f} s); ratio of medians {md['drift'] / md['astier23']:.2f}x, "
                 f"of fastest calls {mn['drift'] / mn['astier23']:.2f}x")
    # 2. parts of the windowed series
    ops = OperatorCache(t, workers=2, dtype=np.float32)
    blk = np.zeros(img.shape, bool)
    parts = {"first-order pass (with the cell statistics)": [], "activity test": [],
             "windows": []}
    wrapped = {"first-order pass (with the cell statistics)": "first_order_terms",
               "activity test": "active_from_stats", "windows": "_window_terms"}
    orig = {k: getattr(S, v) for k, v in wrapped.items()}
    acc = {}

    def wrap(name):
        def g(*a, **k):
            out, dt = timed(orig[name], *a, **k)
            acc[name] = acc.get(name, 0.0) + dt
            return out
        return g

    for k, v in wrapped.items():
        setattr(S, v, wrap(k))
    try:
        totals, half = [], []
        for r in range(6):
            acc.clear()
            info = {}
            _, dt = timed(S.sparse_series, img, blk, ops, noise_tol=0.05, density="fv4",
                          info=info)
            _, dh = timed(C.correct_half_shift, img, t, blocked=blk, workers=2,
                          dtype=np.float32, strip=512, cache=ops)
            if r:  # the first call builds the window operators
                totals.append(dt)
                half.append(dh)
                for k in parts:
                    parts[k].append(acc.get(k, 0.0))
    finally:
        for k, v in wrapped.items():
            setattr(S, v, orig[k])
    lines.append(f"2. windowed series, median of 5 calls: total {np.median(totals):.3f} s = "
                 + ", ".join(f"{k} {np.median(v):.3f} s" for k, v in parts.items())
                 + f"; {info['windows']} windows covering {100 * info['window_fraction']:.1f} %"
                 f" of the image; astier23 pass alone (correct_half_shift) {np.median(half):.3f} s"
                 f" (ratio {np.median(totals) / np.median(half):.2f}x)")
    # 3. crowded field and bright flat (bench_task.py's): where the time goes
    from bench_task import star_field as bench_field
    fields = {"crowded field (4000 stars)": bench_field(4096, 4000, seed=2),
              "flat 1e5 e": np.random.default_rng(3).poisson(1e5, (4096, 4096)).astype(float)}
    kw = dict(density="fv4", noise_tol=0.05, start="series", dtype=np.float32, strip=512,
              workers=2)
    wrapped3 = {"first-order pass": (S, "first_order_terms"),
                "second-tier bound": (S, "cell_bound"),
                "second tier (bound, windows and the rest)": (S, "_second_tier"),
                "windows": (S, "_window_terms"), "dense series": (C, "_series_block")}
    orig3 = {k: getattr(m, v) for k, (m, v) in wrapped3.items()}

    def wrap3(name):
        def g(*a, **k):
            out, dt = timed(orig3[name], *a, **k)
            acc[name] = acc.get(name, 0.0) + dt
            return out
        return g

    for k, (m, v) in wrapped3.items():
        setattr(m, v, wrap3(k))
    try:
        for title, field in fields.items():
            cache = OperatorCache(t, workers=2, dtype=np.float32)
            C.correct_image(field, t, sparse=True, cache=cache, **kw)  # operators built
            C.correct_half_shift(field, t, workers=2, dtype=np.float32, strip=512, cache=cache)
            sparse, half, dense, parts3 = [], [], [], {k: [] for k in wrapped3}
            for _ in range(3):
                acc.clear()
                info = {}
                sparse.append(timed(C.correct_image, field, t, sparse=True, cache=cache,
                                    info=info, **kw)[1])
                for k in wrapped3:
                    parts3[k].append(acc.get(k, 0.0))
                half.append(timed(C.correct_half_shift, field, t, workers=2,
                                  dtype=np.float32, strip=512, cache=cache)[1])
                dense.append(timed(C.correct_image, field, t, cache=cache, **kw)[1])
            h = np.median(half)
            lines.append(
                f"3. {title}, 4096 x 4096, median of 3 calls: drift (windowed, solver "
                f"{info['solver']}, tier {info.get('tier')}) {np.median(sparse):.3f} s = "
                f"{np.median(sparse) / h:.2f}x the astier23 pass ({h:.3f} s); dense series "
                f"{np.median(dense):.3f} s = {np.median(dense) / h:.2f}x; of drift: "
                + ", ".join(f"{k} {np.median(v):.3f} s" for k, v in parts3.items()
                            if np.median(v) > 0)
                + (f"; second tier: {100 * info['active_fraction']:.1f} % of the cells "
                   f"active, {info['windows']} windows covering "
                   f"{100 * info['window_fraction']:.1f} % of the image"
                   if info.get("tier") == 2 and info.get("window_fraction") is not None
                   else "")
                + (f" ({info['reason']})" if info.get("reason") else ""))
    finally:
        for k, (m, v) in wrapped3.items():
            setattr(m, v, orig3[k])
    # 4. small-window edge transfer, one thread against the parallel kernel
    rng = np.random.default_rng(3)
    f = rng.uniform(0, 1e4, (64, 64))
    b = np.zeros(f.shape, bool)
    sv = rng.normal(size=(64, 65)).astype(np.float32)
    sh = rng.normal(size=(65, 64)).astype(np.float32)
    res = {}
    for name, kern in (("one thread", E.fused_serial), ("parallel", E.fused_parallel)):
        out = np.empty(f.shape)
        kern(sv, sh, f, b, b.any(axis=1), E.density_weight("fv4"), out)
        res[name] = np.median([timed(kern, sv, sh, f, b, b.any(axis=1),
                                     E.density_weight("fv4"), out)[1] for _ in range(50)])
    lines.append(f"4. edge transfer on a 64 x 64 window, median of 50 calls: one thread "
                 f"{1e3 * res['one thread']:.3f} ms, parallel {1e3 * res['parallel']:.3f} ms")
    load = os.getloadavg()[0]
    lines.append(f"load average {load:.1f} at the end")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(os.path.join(HERE, "profile_drift_results"), lines, script=__file__)


if __name__ == "__main__":
    main()
