"""How much area response the calibrated model puts beyond GalSim's window (lags >= 4).

GalSim's sensor files stop about 4 px from the aggressor, so their a_ij
vanish beyond lag 4; a physical model's do not. For each GalSim sensor
fitted by ``parameter_lags.py`` (its ``parameter_lags_results.json``), the
model's a_ij at the fitted parameters and GalSim's own, lags 0-9, and their
sums with the lag weights of the sum rule (1, 2 on the axes, 4 off them):
plain, and weighted by r^2 (the size response of a wide PSF), inside lag 4
and beyond it. The r^2 weight is that of a PSF much wider than the lags;
the stars of the peers benchmark (docs/benchmarks.rst, "This package's
route against LSST's") hardly see this far field: cropped to GalSim's
window, the calibrated template corrects them to 0.1-0.2 % of the size
slope of the whole one (``peers_links_results``). Run::

    python benchmarks/calibration/far_field.py

Writes ``benchmarks/calibration/far_field_results.txt`` and ``.json``.
"""

import json
import os
import sys

import numpy as np

from lsst_bfdrift.calibration.fit_model import default_start, model_acoeffs
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs
from lsst_bfdrift.templates.refine import lag_multiplicity

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402
REPO = os.path.dirname(os.path.dirname(HERE))
L = 9


def main():
    with open(os.path.join(HERE, "parameter_lags_results.json")) as fh:
        fits = json.load(fh)["fits"]
    w = lag_multiplicity(L)
    i = np.arange(L + 1)
    r2 = np.add.outer(i ** 2, i ** 2)
    far = np.maximum.outer(i, i) >= 4
    lines, out = [], {"max_lag": L, "sensors": {}}
    for label, fit in fits.items():
        if not label.startswith("GalSim "):
            continue
        sensor = label.split()[1]
        rec = out["sensors"][sensor] = {"params": fit["values"]}
        for name, a in (("galsim", galsim_acoeffs(sensor, L)),
                        ("model", model_acoeffs(default_start().replace(**fit["values"]), L))):
            rec[name] = {"near": float(np.sum((w * a)[~far])), "far": float(np.sum((w * a)[far])),
                         "r2_near": float(np.sum((w * a * r2)[~far])),
                         "r2_far": float(np.sum((w * a * r2)[far]))}
            s = rec[name]
            lines.append(f"{sensor:15s} {name:6s} sum lags<4 {s['near']:+.3e}, >=4 {s['far']:+.3e}; "
                         f"r2-weighted <4 {s['r2_near']:+.3e}, >=4 {s['r2_far']:+.3e} per e")
        rec["r2_far_ratio"] = rec["model"]["r2_far"] / rec["galsim"]["r2_far"]
        lines.append(f"{sensor:15s} model / GalSim, r2-weighted beyond lag 3: "
                     f"{rec['r2_far_ratio']:.2f}")
        print("\n".join(lines[-3:]), flush=True)
    write_results(os.path.join(HERE, "far_field_results"), lines, out, script=__file__)


if __name__ == "__main__":
    main()
