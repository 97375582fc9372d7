# command: python benchmarks/calibration/band_temperature.py
"""The sensor's temperature in the band templates: a00 per band at 300 K and at 173 K (issue 45).

GalSim's absorption table, which the band templates use by default, is
silicon at 300 K; an LSST sensor runs at about 173 K (-100 C), where red
photons convert deeper (:func:`~lsst_bfdrift.physics.absorption.absorption_length`
scales the table with the Rajkanan, Singh & Shewchun model; the script
first prints the table, the model's own 300 K lengths over it, and the
scaled lengths over it at each temperature). For the default sensor (the
bundled default template's parameters, 100 um), this script builds templates with drift lines starting at ``--nodes`` conversion
heights (size 9, 8 samples per edge, tol 1e-5 px), and for each band and
temperature integrates A00 - 1 over the band's depth distribution (flat
photon spectrum, piecewise linear in the height:
:meth:`~lsst_bfdrift.physics.depth.DepthDistribution.node_weights`).
Printed per band and temperature: the mean conversion height, the fraction
of photons converted, and a00 relative to the u band's; then y / u against
LSSTCam's (about 0.94, DMTN-336). Writes
``benchmarks/calibration/band_temperature_results.txt`` / ``.json``::

    python benchmarks/calibration/band_temperature.py [--temperatures 300 223 173] [--nodes 12]
"""

import argparse
import dataclasses
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common

from _common import write_results  # noqa: E402

from lsst_bfdrift.physics.absorption import absorption_length, rajkanan_alpha  # noqa: E402
from lsst_bfdrift.physics.depth import BANDS, conversion_nodes, depth_distribution  # noqa: E402
from lsst_bfdrift.physics.sensor import SensorParameters  # noqa: E402
from lsst_bfdrift.templates.template import (TemplateSettings, build_template,  # noqa: E402
                                             load_default_template)

#: LSSTCam's a00 in y relative to u (DMTN-336: about 6 % weaker).
LSSTCAM_Y_OVER_U = 0.94


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--temperatures", type=float, nargs="+", default=[300.0, 223.0, 173.0])
    ap.add_argument("--nodes", type=int, default=12)
    ap.add_argument("--out", default=os.path.join(HERE, "band_temperature_results"))
    args = ap.parse_args(argv)
    lines, rec = [], {"temperatures": args.temperatures, "bands": {}}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    load = os.getloadavg()
    say(f"machine: {os.cpu_count()} cores, load average {load[0]:.1f} (1 min) at the start")
    wl = np.array([450.0, 500, 600, 700, 800, 900, 950, 1000, 1050])
    table = absorption_length(wl)
    model = 1e4 / rajkanan_alpha(wl, 300.0)
    say("absorption length (um): GalSim's table at 300 K; the Rajkanan model's own 300 K value "
        "over the table's; the table scaled to each temperature over the table")
    say("  nm     table  model/table  " + "  ".join(f"{'%g K' % t:>8s}" for t in
                                                    args.temperatures))
    rec["absorption"] = {}
    for k, w in enumerate(wl):
        ratios = [float(absorption_length(w, temperature=t) / table[k])
                  for t in args.temperatures]
        rec["absorption"][f"{w:g}"] = {"table_um": float(table[k]),
                                       "model_over_table": float(model[k] / table[k]),
                                       "scaled_over_table": ratios}
        say(f"  {w:5g} {table[k]:8.3f} {model[k] / table[k]:11.2f}  "
            + "  ".join(f"{r:8.2f}" for r in ratios))
    params = SensorParameters.from_dict(load_default_template().meta["params"])
    settings = TemplateSettings(size=9, edge_samples=8, tol=1e-5, workers=2)
    z = conversion_nodes(params.thickness, params.z_collect, args.nodes)
    t0 = time.time()
    a00 = np.zeros(z.size)  # A00 - 1 at each height (the collection height: none)
    for k in range(1, z.size):
        t = build_template(params, dataclasses.replace(settings, conversion_height=float(z[k])))
        a00[k] = t.summary()["A00"] - 1.0
    rec["heights_um"], rec["a00_minus_1"] = z.tolist(), a00.tolist()
    say(f"default sensor ({params.thickness:g} um, collection height {params.z_collect:g} um): "
        f"A00 - 1 at {z.size} conversion heights built in {time.time() - t0:.0f} s (size 9, "
        "8 samples, tol 1e-5)")
    say("band  " + "  ".join(f"{'T = %g K' % t:>30s}" for t in args.temperatures))
    say("      " + "  ".join(f"{'height um':>10s}{'converted':>10s}{'a00 / u':>10s}"
                            for _ in args.temperatures))
    per = {}
    for band in BANDS:
        row = []
        for temp in args.temperatures:
            d = depth_distribution(band, params.thickness, temperature=temp)
            val = float(np.dot(d.node_weights(z), a00))
            per[(band, temp)] = (d.mean_height, d.converted_fraction, val)
            row.append((d.mean_height, d.converted_fraction, val))
        rec["bands"][band] = {f"{t:g}": {"mean_height_um": m, "converted": c, "a00_minus_1": v}
                              for t, (m, c, v) in zip(args.temperatures, row)}
        say(f"{band:4s}  " + "  ".join(
            f"{m:10.2f}{c:10.3f}{v / per[('u', t)][2]:10.3f}"
            for t, (m, c, v) in zip(args.temperatures, row)))
    rec["y_over_u"] = {}
    for temp in args.temperatures:
        r = per[("y", temp)][2] / per[("u", temp)][2]
        rec["y_over_u"][f"{temp:g}"] = r
        say(f"a00 y / u at {temp:g} K: {r:.3f} (LSSTCam about {LSSTCAM_Y_OVER_U})")
    write_results(args.out, lines, rec, script=__file__)


if __name__ == "__main__":
    main()
