"""How much of the crowded field's second tier an exact activity test would save.

On the crowded field of ``benchmarks/performance/bench_task.py`` (4096 x 4096, 4000
stars), the second tier of the windowed series
(:mod:`lsst_bfdrift.correction.tiles`) computes the higher-order terms in
windows around the cells its a-priori bound marks. This script computes the
dense series' own higher-order terms, marks the cells where they exceed
half the tolerance (an oracle no solver has), and runs the second tier with
the bound's cells and with the oracle's, calls alternated, medians of
``--repeat``: the windows' area and the second tier's time for each::

    python benchmarks/performance/crowded_windows.py [--repeat 3]

Writes ``benchmarks/performance/crowded_windows_results.txt`` and ``.json``.
"""

import argparse
import os
import platform
import sys
import time

import numpy as np
from scipy import ndimage

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from bench_task import star_field  # noqa: E402
from lsst_bfdrift.correction import series as S  # noqa: E402
from lsst_bfdrift.correction.solvers import correct_image  # noqa: E402
from lsst_bfdrift.templates.swept import OperatorCache  # noqa: E402
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402

NOISE_TOL = 0.05
CELL = 16


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(HERE, "crowded_windows_results"))
    args = ap.parse_args(argv)
    img = star_field(4096, 4000, seed=2)
    t = load_default_template()
    ops = OperatorCache(t, workers=2, dtype=np.float32)
    blk = np.zeros(img.shape, bool)
    dense = correct_image(img, t, order=3, density="fv4", noise_tol=NOISE_TOL, start="series",
                          workers=2, dtype=np.float32, cache=ops, strip=512,
                          check_range=False)[0]
    first = S.first_order_terms(img, blk, ops, strip=512, cubic="fv4", cell=CELL)[0]
    m = img.shape[0] // CELL
    terms = np.abs(dense - first).reshape(m, CELL, m, CELL).max(axis=(1, 3))
    tol = S.tolerance(img, NOISE_TOL).reshape(m, CELL, m, CELL).min(axis=(1, 3))
    oracle = terms > 0.5 * ndimage.minimum_filter(tol, 3)
    orig = S._second_tier
    res = {name: {"seconds": []} for name in ("bound", "oracle")}
    try:
        for _ in range(args.repeat):
            for name, res_ in res.items():
                info = {}

                def tier(*a, _name=name, **kw):
                    def act(stats, arrays, blocked, refine=True, _act=a[7]):
                        marked, p, lim = _act(stats, arrays, blocked, refine)
                        return (marked if _name == "bound" else oracle), p, lim
                    t0 = time.perf_counter()
                    out = orig(*a[:7], act, *a[8:], **kw)
                    res_["seconds"].append(time.perf_counter() - t0)
                    return out

                S._second_tier = tier
                S.sparse_series(img, blk, ops, noise_tol=NOISE_TOL, density="fv4", strip=512,
                                info=info)
                res_.update(windows=info["windows"], window_fraction=info["window_fraction"],
                            active_fraction=info["active_fraction"])
    finally:
        S._second_tier = orig
    lines = [f"crowded field 4096 x 4096 (4000 stars), noise_tol {NOISE_TOL}, cells of {CELL} px; "
             f"second tier, calls alternated, median of {args.repeat}; {os.cpu_count()} cores "
             f"({platform.machine()}), 1-min load average {os.getloadavg()[0]:.2f} at the end"]
    for name, r in res.items():
        r["median_seconds"] = float(np.median(r["seconds"]))
        lines.append(f"  {name:6s}: {r['active_fraction']:6.2%} of the cells marked, "
                     f"{r['windows']:4d} windows over {r['window_fraction']:6.2%} of the image, "
                     f"{r['median_seconds']:.2f} s")
    lines.append(f"  oracle / bound time: {res['oracle']['median_seconds'] / res['bound']['median_seconds']:.2f}")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(args.out, lines, res, script=__file__)
    return 0


if __name__ == "__main__":
    sys.exit(main())
