"""Reproduce Rasmussen 2015: numbers, results files and the docs figures.

Runs :func:`lsst_bfdrift.validation.paper_figures.reproduce` at full resolution (31 x 31
calibrated template with 32 samples per edge, the 5 x 5 V_BSS / xi_CK ratio
scan and every fixed-pattern feature), then writes

* ``benchmarks/reproduce/make_reproduce_figures_results.json`` (the same content as
  ``bfdrift reproduce --json``, plus the ``command`` that wrote it) and
  ``benchmarks/reproduce/make_reproduce_figures_results.txt``
  (one ``key: value`` line each, plus the run time);
* every figure of ``docs/simulations.rst`` into ``docs/_static/reproduce/``.

Usage (from the repository root)::

    python scripts/make_reproduce_figures.py
"""

import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")
sys.path.insert(0, ROOT)  # this checkout's lsst_bfdrift

from lsst_bfdrift.utils.io import atomic_output  # noqa: E402
from lsst_bfdrift.utils.progress import ProgressBar  # noqa: E402
from lsst_bfdrift.validation.paper_figures import reproduce, write_figures  # noqa: E402


def main():
    t0 = time.perf_counter()
    tables = {}
    with ProgressBar(25 + 5, "reproduce") as bar:
        numbers, tpl, scan = reproduce(progress=bar, tables=tables)
    v_bss, xi_ck, ratio = scan
    numbers["ratio_scan"] = {"v_bss": v_bss.tolist(), "xi_ck": xi_ck.tolist(),
                             "ratio_01_10": ratio.tolist()}
    seconds = time.perf_counter() - t0
    out = os.path.join(ROOT, "docs", "_static", "reproduce")
    files = write_figures(numbers, tpl, scan, tables, out)
    # the results files start with the command that wrote them (benchmarks/README.md)
    command = " ".join(["python", "scripts/make_reproduce_figures.py"] + sys.argv[1:])
    bench = os.path.join(ROOT, "benchmarks", "reproduce")
    with atomic_output(os.path.join(bench, "make_reproduce_figures_results.json")) as tmp:
        with open(tmp, "w") as fh:
            json.dump({"command": command, **numbers}, fh, indent=2, default=float)
    lines = [f"{k:>20s}: {v}" for k, v in numbers.items()]
    lines.append(f"{'seconds':>20s}: {seconds:.0f} (computation, 2-core machine shared with "
                 "other jobs)")
    with atomic_output(os.path.join(bench, "make_reproduce_figures_results.txt")) as tmp:
        with open(tmp, "w") as fh:
            fh.write(f"# command: {command}\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))
    print("figures:", ", ".join(os.path.basename(f) for f in files))


if __name__ == "__main__":
    main()
