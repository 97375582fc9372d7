"""Time of each stage of ``correct_file`` on a 4096 x 4096 FITS file: the
measurement behind :func:`lsst_bfdrift.correction.batch.stage_weights`.

The field of ``benchmarks/performance/bench_task.py`` (sky 1200 e, 400 stars) written
as a float32 FITS image in electrons; :func:`~lsst_bfdrift.correction.batch.correct_file`
run with a progress callback that notes when each stage (read, correct,
maps, write) reports last (a stage's time runs from the previous stage's
last report); the Task is warmed up first on the same file
(kernels compiled, operators built), then ``--repeat`` runs per
configuration (default, ``compute_geometry=False``, ``geometry_method='exact'``),
alternated; medians in seconds. Run from the repository root::

    python benchmarks/performance/stage_timings.py [--repeat 3]

Prints and writes ``benchmarks/performance/stage_timings_results.txt`` / ``.json``.
"""

import argparse
import os
import platform
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from bench_task import star_field  # noqa: E402

CONFIGS = {"default": {}, "no maps": {"compute_geometry": False},
           "exact maps": {"geometry_method": "exact"}}


def timed_run(src, dst, config):
    """Seconds per stage of one ``correct_file``: from the previous stage's
    last report (the call, for the first) to this stage's last report, so
    that the work between stages (the Task's input checks) counts for the
    stage that follows, as a progress bar shows it."""
    from lsst_bfdrift.correction.batch import correct_file

    last = {}

    def progress(stage, fraction):
        last[stage] = time.perf_counter()

    t0 = time.perf_counter()
    correct_file(src, dst, config=config, overwrite=True, progress=progress)
    out, prev = {}, t0
    for stage, t in sorted(last.items(), key=lambda kv: kv[1]):
        out[stage] = t - prev
        prev = t
    return out


def main():
    from astropy.io import fits

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(HERE, "stage_timings_results"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = os.path.join(tmp, "in.fits"), os.path.join(tmp, "out.fits")
        hdu = fits.PrimaryHDU(star_field(4096, 400).astype(np.float32))
        hdu.header["BUNIT"] = "electron"
        hdu.writeto(src)
        for cfg in CONFIGS.values():
            timed_run(src, dst, cfg)  # warm-up
        runs = {name: [] for name in CONFIGS}
        for _ in range(args.repeat):
            for name, cfg in CONFIGS.items():
                runs[name].append(timed_run(src, dst, cfg))
    med = {name: {stage: float(np.median([r.get(stage, 0.0) for r in rs]))
                  for stage in ("read", "correct", "maps", "write")}
           for name, rs in runs.items()}
    lines = [f"correct_file on a 4096 x 4096 float32 FITS file (400 stars), median of "
             f"{args.repeat} runs per configuration, alternated, after a warm-up; "
             f"{os.cpu_count()} cores ({platform.machine()}, {platform.python_version()}), "
             f"1-min load average {os.getloadavg()[0]:.2f} at the end (1 to 2: this job alone)"]
    for name, st in med.items():
        lines.append(f"  {name:10s} " + "  ".join(f"{k} {v:6.2f} s" for k, v in st.items())
                     + f"  total {sum(st.values()):6.2f} s")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(args.out, lines, {"repeat": args.repeat, "medians": med}, script=__file__,
                  indent=2)


if __name__ == "__main__":
    main()
