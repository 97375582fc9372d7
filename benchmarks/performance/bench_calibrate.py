"""Wall time of one a-matrix calibration (``calibrate``, the issue's <= 60 s target).

Two inputs, alternated, ``--repeat`` times each, medians reported:

* the measured ITL a-matrix of ``shared/data/measured`` (9 x 9 lags, a00
  from its sum rule included);
* GalSim's own a-matrix of lsst_e2v_50_8 (9 x 9 lags, 2 % errors).

Each run: the candidates' Jacobian at the start (package data for the default start), the parameter choice, the
fit, the exact template build (21 x 21 pixels, 32 samples per edge), the
area refinement and the parameter modes (two small builds per free parameter). Prints the machine and writes
``benchmarks/performance/bench_calibrate_results.txt`` / ``.json``::

    python benchmarks/performance/bench_calibrate.py [--repeat 3]
"""

import argparse
import os
import platform
import statistics
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.ptc.acoeffs import AcoeffTable, read_acoeff_table  # noqa: E402
from lsst_bfdrift.calibration.tuning import calibrate  # noqa: E402
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs  # noqa: E402

ITL = os.path.join(HERE, "..", "..", "..", "shared", "data", "measured",
                   "itl_covariances_21oct19.txt")


def inputs():
    itl = read_acoeff_table(ITL)
    itl.exclude_a00 = False  # a00 in the fit (this file's a00 is its sum rule)
    a = galsim_acoeffs("lsst_e2v_50_8", 8)
    e2v = AcoeffTable(a, 0.02 * np.abs(a) + 1e-10, source="galsim:lsst_e2v_50_8")
    return {"measured ITL": itl, "GalSim e2v": e2v}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(HERE, "bench_calibrate_results"))
    args = ap.parse_args(argv)
    machine = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
               f"Python {platform.python_version()}")
    tables = inputs()
    runs = {k: [] for k in tables}
    calibrate(tables["measured ITL"], build=False, allow_poor_fit=True, max_evaluations=2)
    for r in range(args.repeat):
        for name, table in tables.items():  # alternated
            res = calibrate(table, allow_poor_fit=True)
            runs[name].append({"seconds": res.seconds, "n_evaluations": res.fit.n_evaluations,
                               "names": res.fit.names, "chi2": res.fit.chi2,
                               "dof": res.fit.dof, "jacobian_source": res.jacobian_source,
                               "load_average": os.getloadavg()[0]})
            print(f"run {r + 1} {name}: {res.seconds['total']:.1f} s "
                  f"({res.fit.n_evaluations} model evaluations)", flush=True)
    lines = [f"calibrate() wall time, {machine}; {args.repeat} runs per input, alternated, "
             "medians (target <= 60 s)"]
    out = {"machine": machine, "repeat": args.repeat, "inputs": {}}
    for name, rs in runs.items():
        med = {k: statistics.median(r["seconds"].get(k, 0.0) for r in rs)
               for k in ("jacobian", "fit", "build", "refine", "modes", "total")}
        nev = statistics.median(r["n_evaluations"] for r in rs)
        lines.append(f"  {name:13s} total {med['total']:5.1f} s (Jacobian {med['jacobian']:.1f}, "
                     f"fit {med['fit']:.1f}, build {med['build']:.1f}, refine "
                     f"{med['refine']:.1f}, parameter modes {med['modes']:.1f}); {nev:.0f} model "
                     "evaluations; free "
                     f"{', '.join(rs[0]['names'])}; chi2 {rs[0]['chi2']:.1f} / {rs[0]['dof']} dof; "
                     f"start Jacobian: {rs[0]['jacobian_source']}")
        out["inputs"][name] = {"median_seconds": med, "median_evaluations": nev, "runs": rs}
    loads = [r["load_average"] for rs in runs.values() for r in rs]
    lines.append(f"  load average (1 min) after the runs: {min(loads):.1f}-{max(loads):.1f} "
                 "(2 = both cores busy)")
    text = "\n".join(lines)
    print(text)
    write_results(args.out, lines, out, script=__file__, json_default=float, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
