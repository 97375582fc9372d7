"""Write the package data ``lsst_bfdrift/data/start_jacobian.json``.

The model's a_ij at the default start of :func:`lsst_bfdrift.calibration.tuning.calibrate`
(the bundled template's sensor) and their forward differences for every
candidate parameter, lags 0-10. ``calibrate`` reads them instead of
spending one model evaluation per candidate (about 15 s) on every call.
Rerun after changing the bundled template's parameters, the candidates or
the model's a_ij; a stale file is ignored (the values are then computed)::

    python scripts/make_start_jacobian.py
"""

import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from lsst_bfdrift.calibration.fit_model import (START_JACOBIAN_FILE,  # noqa: E402
                                                write_start_jacobian)
from lsst_bfdrift.utils.io import data_path  # noqa: E402


def main():
    t0 = time.perf_counter()
    path = data_path(START_JACOBIAN_FILE)
    d = write_start_jacobian(path)
    print(f"{path}: lags 0-{d['max_lag']}, {len(d['jacobian'])} candidates, "
          f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
