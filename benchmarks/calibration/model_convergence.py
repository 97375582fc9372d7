"""How far the model's a_ij at the calibration fit's settings lie from their converged values.

The electrostatic model's a_ij
(:func:`~lsst_bfdrift.calibration.acoeff_model.electrostatic_acoeffs`,
``definition='alpha'``, 1e4 e aggressor, bisection tol 2e-6 px, as
:func:`~lsst_bfdrift.calibration.fit_model.model_acoeffs` computes them for
the fit) are areas of polygons through samples of the traced boundaries.
Next to the aggressor the boundaries bend sharply into its corners, so the
polygons' areas depend on where the samples lie. For three sensor
parameter sets (the bundled template's, with a 1 um charge cloud, and a
deeper channel with a stronger barrier), lags 0-3 are computed with:

* the fit's settings: 16 uniformly spaced samples per edge for lags 0-1,
  6 'tan' samples beyond;
* 'ends' spacing (Chebyshev nodes, dense at the corners) with 16 / 6,
  24 / 8 and 32 / 12 samples;
* 256 uniform / 48 uniform samples: a dense check made another way;

each against a reference of 'ends' spacing with 128 / 48 samples, with
the time of one evaluation (one process, numba's default threads)::

    python benchmarks/calibration/model_convergence.py

Writes ``benchmarks/calibration/model_convergence_results.txt`` and ``.json``.
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import Lines, settings_record, write_results  # noqa: E402

from lsst_bfdrift.calibration.acoeff_model import electrostatic_acoeffs  # noqa: E402
from lsst_bfdrift.calibration.fit_model import CHARGE, default_start  # noqa: E402

#: (label, near spacing, far spacing, near samples, far samples)
SETTINGS = (("fit settings (uniform 16 / tan 6)", "uniform", "tan", 16, 6),
            ("ends 16 / 6", "ends", "ends", 16, 6),
            ("ends 24 / 8", "ends", "ends", 24, 8),
            ("ends 32 / 12", "ends", "ends", 32, 12),
            ("uniform 256 / uniform 48", "uniform", "uniform", 256, 48))
REFERENCE = ("reference (ends 128 / 48)", "ends", "ends", 128, 48)
NAMES = [f"a{i}{j}" for i in range(4) for j in range(4)]


def acoeffs(params, near, far, ns, nf):
    t = time.perf_counter()
    a = electrostatic_acoeffs(params, max_lag=3, charge=CHARGE, tol=2e-6, near_samples=ns,
                              far_samples=nf, definition="alpha", near_spacing=near,
                              far_spacing=far)
    return a, time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=os.path.join(HERE, "model_convergence_results"))
    args = ap.parse_args()
    say = Lines()
    start = default_start()
    sensors = {"bundled template's sensor": start,
               "with a 1 um charge cloud": start.replace(charge_cloud=1.0),
               "channel 1 um deep, xi0 x 1.5": start.replace(channel_depth=1.0,
                                                              xi0=1.5 * start.xi0)}
    record = {"settings": settings_record(args), "sensors": {}}
    say("model a_ij, lags 0-3 (definition 'alpha', 1e4 e aggressor, tol 2e-6 px): "
        "(value / reference - 1) in %, [i serial, j parallel]; time of one evaluation")
    acoeffs(start, "uniform", "tan", 4, 2)  # compile
    for name, params in sensors.items():
        ref, t_ref = acoeffs(params, *REFERENCE[1:])
        say(f"{name}: reference {REFERENCE[0]}, {t_ref:.2f} s; a00 {ref[0, 0]:.4e}, "
            f"a01 {ref[0, 1]:.4e}, a10 {ref[1, 0]:.4e}, a11 {ref[1, 1]:.4e} per e")
        rows = {}
        for label, near, far, ns, nf in SETTINGS:
            a, dt = acoeffs(params, near, far, ns, nf)
            err = (a / ref - 1.0) * 100.0
            worst = int(np.argmax(np.abs(err)))
            say(f"  {label:34s} {dt:5.2f} s  a00 {err[0, 0]:+6.2f}  a01 {err[0, 1]:+6.2f}  "
                f"a10 {err[1, 0]:+6.2f}  a11 {err[1, 1]:+6.2f}  worst of lags 0-3 "
                f"{NAMES[worst]} {err.ravel()[worst]:+6.2f} %")
            rows[label] = {"seconds": dt, "error_percent": err, "worst": NAMES[worst]}
        record["sensors"][name] = {"reference": ref, "reference_seconds": t_ref, "rows": rows}
    say("a_ij measured by cp_pipe on a full CCD: a00 to ~1.3 %, the nearest lags to a few %")
    write_results(args.out, say, record, script=__file__)


if __name__ == "__main__":
    main()
