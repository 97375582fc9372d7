"""How the brighter-fatter template changes from band to band (issue 45's physics question).

Three parts, for the default sensor (the bundled default template's
parameters):

1. **The area response against the conversion height.** Templates built
   with drift lines starting at one height z (size 9, 8 'tan' samples per
   edge, tol 1e-5 px), for 18 heights from the collection height to the
   entrance window: the change of A00, A01, A10, A11, A02, A20 relative to
   the entrance window's, beside GalSim's rule ``tanh(z / 12 um)``.
2. **How many heights a band needs.** Each band's area changes integrated
   over its depth distribution on those 18 heights (reference) against the
   shared grids of 4, 6, 8 and 12 heights (piecewise linear in z, the
   weights of ``DepthDistribution.node_weights``).
3. **The band templates.** ``build_band_templates`` at the default template's
   settings (21 x 21, 32 samples, 1e-5 px; 8 heights, 7 builds), flat
   photon spectrum: per band, the area changes relative to the u band, the
   mean conversion height, the fraction of photons converted, GalSim's
   factor ``E[tanh(z / 12)]``; and in z and y, a red (CWW_E_ext) against a
   blue (black body 15000 K) source.

Run (about 15 minutes on 2 free cores; 12 minutes at a load of 13-15)::

    OMP_NUM_THREADS=1 python benchmarks/calibration/band_templates.py

Writes ``benchmarks/calibration/band_templates_results.txt`` and ``.json``.
"""

import dataclasses
import os
import sys
import time

import numpy as np

from lsst_bfdrift.physics.depth import (BANDS, conversion_nodes, depth_distribution,
                                        galsim_depth_factor)
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.bands import combine_templates
from lsst_bfdrift.templates.template import (TemplateSettings, build_template,
                                             load_default_template)

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402
LAGS = {"A00": (0, 0), "A01": (0, 1), "A10": (1, 0), "A11": (1, 1), "A02": (0, 2),
        "A20": (2, 0)}
SEDS = {"red (CWW_E_ext)": "CWW_E_ext", "blue (15000 K)": 15000.0}


def area_changes(template):
    """A_ij - 1 at the lags of LAGS ((di, dj) = (serial, parallel))."""
    a = template.moments().area
    c = template.center
    return {k: float(a[c + dj, c + di] - 1.0) for k, (di, dj) in LAGS.items()}


def main():
    meta = load_default_template().meta
    params = SensorParameters.from_dict(meta["params"])
    t, z0 = params.thickness, params.z_collect
    lines, out = [], {"params": params.to_dict()}

    def say(s=""):
        print(s, flush=True)
        lines.append(s)

    load = os.getloadavg()
    say(f"machine: {os.cpu_count()} cores, load average {load[0]:.1f} / {load[1]:.1f} / "
        f"{load[2]:.1f} (1 / 5 / 15 min) at the start")
    out["machine"] = {"cores": os.cpu_count(), "load_start": list(load)}

    # 1. response against height (coarse templates)
    coarse = TemplateSettings(size=9, edge_samples=8, tol=1e-5, spacing="tan")
    heights = conversion_nodes(t, z0, 18, power=2.5)
    say("1. area change at conversion height z relative to the entrance window's "
        "(size 9, 8 tan samples, tol 1e-5)")
    say(f"{'z um':>8} " + " ".join(f"{k:>7}" for k in LAGS) + f" {'tanh(z/12)':>10}")
    resp = {k: [0.0] for k in LAGS}  # at the collection height: no displacement
    t0 = time.perf_counter()
    for z in heights[1:]:
        tpl = build_template(params, dataclasses.replace(coarse, conversion_height=float(z)))
        for k, v in area_changes(tpl).items():
            resp[k].append(v)
    top = {k: v[-1] for k, v in resp.items()}
    for n, z in enumerate(heights):
        say(f"{z:8.2f} " + " ".join(f"{resp[k][n] / top[k]:7.3f}" for k in LAGS)
            + f" {np.tanh(z / 12.0):10.3f}")
    say(f"   ({time.perf_counter() - t0:.0f} s)")
    out["response"] = {"heights": heights.tolist(), "changes": resp}

    # 2. grid convergence
    say()
    say("2. band A_ij - 1 on shared grids of n heights against the 18-height reference "
        "(relative difference, largest over A00..A20)")
    conv = {}
    dists = {b: depth_distribution(b, t) for b in BANDS}
    ref = {b: {k: float(dists[b].node_weights(heights) @ np.array(resp[k])) for k in LAGS}
           for b in BANDS}
    for n in (4, 6, 8, 12):
        nodes = conversion_nodes(t, z0, n)
        row = {}
        for b in BANDS:
            w = dists[b].node_weights(nodes)
            vals = {k: float(w @ np.interp(nodes, heights, resp[k])) for k in LAGS}
            row[b] = max(abs(vals[k] / ref[b][k] - 1.0) for k in LAGS)
        conv[n] = row
        say(f"  n = {n:2d}: " + " ".join(f"{b} {row[b]:.1e}" for b in BANDS))
    out["grid_convergence"] = conv

    # 3. the band templates at the default settings
    say()
    settings = TemplateSettings.from_dict(meta["settings"])
    say(f"3. build_band_templates at the default template's settings (size {settings.size}, "
        f"{settings.edge_samples} samples, tol {settings.tol:g}), 8 heights, flat spectrum")
    t0 = time.perf_counter()
    nodes = conversion_nodes(t, z0, 8)
    built = {}
    for k in range(1, nodes.size):
        built[k] = build_template(params, dataclasses.replace(
            settings, conversion_height=float(nodes[k])))
    say(f"   ({time.perf_counter() - t0:.0f} s for {len(built)} builds)")
    temps = [built.get(k) for k in range(nodes.size)]
    bands = {}
    say(f"{'band':>5} {'mean z':>7} {'conv':>6} {'GalSim':>7} " +
        " ".join(f"{k + '/u':>7}" for k in LAGS))
    for sed_name, sed in [("flat", None)] + list(SEDS.items()):
        for b in BANDS if sed is None else ("z", "y"):
            d = depth_distribution(b, t, sed=sed)
            tpl = combine_templates(temps, d.node_weights(nodes))
            bands.setdefault(sed_name, {})[b] = {
                "changes": area_changes(tpl), "mean_height": d.mean_height,
                "converted_fraction": d.converted_fraction,
                "galsim_factor": galsim_depth_factor(d)}
    u = bands["flat"]["u"]["changes"]
    for sed_name, rows in bands.items():
        if sed_name != "flat":
            say(f"  source {sed_name}:")
        for b, r in rows.items():
            say(f"{b:>5} {r['mean_height']:7.2f} {r['converted_fraction']:6.3f} "
                f"{r['galsim_factor']:7.4f} " +
                " ".join(f"{r['changes'][k] / u[k]:7.4f}" for k in LAGS))
    out["bands"] = bands
    out["nodes"] = nodes.tolist()
    write_results(os.path.join(HERE, "band_templates_results"), lines, out, script=__file__)


if __name__ == "__main__":
    main()
