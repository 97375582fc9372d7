"""How much of its depth rule galsim.SiliconSensor applies: the box short-cuts.

galsim.SiliconSensor scales a pixel's boundary distortions by
tanh(z / 12 um) of the photon's conversion height z, but only for photons
that land between the pixel's inscribed box and its bounding box
(``Silicon::insidePixel``: a photon inside the inscribed box of the
*unscaled* distorted polygon is inside, one outside its bounding box is
outside, both without the scaled test; read in GalSim's BSD-licensed
source, no code copied). Where an edge is shifted straight, the two boxes
meet at the shifted edge and the scale never acts.

This script emulates that test for the aggressor pixel of GalSim's own
sensor files (uniform points over the pixel and its surroundings, the
per-pixel polygons of ``import_galsim_sensor``): the area change seen at
scale f, against f (the rule without the short-cuts), and its mean over the
conversion heights of 1000 nm photons and of each band's flat spectrum,
against GalSim's stated mean tanh(z / 12 um). GalSim's measured flats
(``benchmarks/calibration/chromatic_stars_<itl|e2v>_results.json``, photons
counted over a pixel holding charge, each band its own exposure) are
printed beside: data the package did not make. Run::

    python benchmarks/simulation/galsim_depth_rule.py [--points 4000000]
"""

import argparse
import json
import os
import shlex
import sys

import numba
import numpy as np

from lsst_bfdrift.physics.depth import BANDS, depth_distribution, galsim_depth_factor
from lsst_bfdrift.physics.polygons import inside_polygon
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.utils.io import write_json, write_text

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
SENSORS = {"lsst_itl_50_8": "itl", "lsst_e2v_50_8": "e2v"}
#: GalSim's zfit (um) and the sensor thickness of its LSST files (um)
ZFIT, THICKNESS = 12.0, 100.0


@numba.njit(cache=True)
def _inside(sx, sy, px, py):
    out = np.empty(px.shape[0], np.bool_)
    for k in range(px.shape[0]):
        out[k] = inside_polygon(px[k], py[k], sx, sy)
    return out


def galsim_boxes(px, py):
    """Bounding box and GalSim's inscribed box (xmin, xmax, ymin, ymax) of a
    pixel polygon: each vertex bounds the inscribed box on the side it faces
    from the bounding box's centre."""
    outer = (px.min(), px.max(), py.min(), py.max())
    cx, cy = 0.5 * (outer[0] + outer[1]), 0.5 * (outer[2] + outer[3])
    x0, x1, y0, y1 = outer
    for x, y in zip(px, py):
        dx, dy = x - cx, y - cy
        if dx >= abs(dy):
            x1 = min(x1, x)
        if dx <= -abs(dy):
            x0 = max(x0, x)
        if dy >= abs(dx):
            y1 = min(y1, y)
        if dy <= -abs(dx):
            y0 = max(y0, y)
    return outer, (x0, x1, y0, y1)


def area_response(sensor, points, seed, scales):
    """(A(f) - 1) / (A(1) - 1) of the aggressor pixel at each scale f, with and
    without GalSim's box short-cuts (Monte Carlo over ``points``)."""
    t = import_galsim_sensor(sensor, match="transfers")
    c = t.center
    x, y = t.polygons(charge=2e4, per_pixel=True)
    px, py = x[c, c], y[c, c]
    # the nominal square, sampled like the polygon
    nx, ny = (v[c, c] for v in t.polygons(charge=1e-9 * t.charge, per_pixel=True))
    rng = np.random.default_rng(seed)
    xs, ys = rng.uniform(-0.7, 0.7, points), rng.uniform(-0.7, 0.7, points)
    (ox0, ox1, oy0, oy1), (ix0, ix1, iy0, iy1) = galsim_boxes(px, py)
    inner = (xs > ix0) & (xs < ix1) & (ys > iy0) & (ys < iy1)
    band = (xs > ox0) & (xs < ox1) & (ys > oy0) & (ys < oy1) & ~inner
    cell = 1.4 * 1.4

    def area(f, boxes):
        sx, sy = nx + f * (px - nx), ny + f * (py - ny)
        if not boxes:
            return _inside(sx, sy, xs, ys).mean() * cell
        ins = inner.copy()
        ins[band] = _inside(sx, sy, xs[band], ys[band])
        return ins.mean() * cell

    out = {}
    for boxes in (True, False):
        a1 = area(1.0, boxes)
        out["boxes" if boxes else "rule"] = np.array([(area(f, boxes) - 1.0) / (a1 - 1.0)
                                                      for f in scales])
    out["band_share"] = float(band.mean() / (band | inner).mean())
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=4_000_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", default=os.path.join(HERE, "galsim_depth_rule_results"))
    args = ap.parse_args(argv)
    scales = np.linspace(0.0, 1.0, 21)
    lines, out = [], {"points": args.points, "scales": scales, "sensors": {}}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    say("aggressor pixel of GalSim's sensor file; area change at boundary scale f over "
        "its value at f = 1, Monte Carlo of GalSim's inside test "
        f"({args.points} points, seed {args.seed})")
    for sensor, short in SENSORS.items():
        res = area_response(sensor, args.points, args.seed, scales)
        rec = out["sensors"][sensor] = {"area_response": res, "sources": {}}
        say(f"== {sensor}: photons in the box band: {100 * res['band_share']:.2f} % of the "
            "pixel's")
        for label, row, fmt in (("f", scales, "6.2f"), ("rule", res["rule"], "6.3f"),
                                ("with boxes", res["boxes"], "6.3f")):
            say(f"  {label:10s}" + "".join(f"{v:{fmt}}" for v in row[::2]))
        measured = {}
        path = os.path.join(REPO, "benchmarks", "calibration",
                            f"chromatic_stars_{short}_results.json")
        if os.path.isfile(path):
            with open(path) as fh:
                flats = json.load(fh)["sensors"][sensor]["flats"]
            measured["1000nm"] = (flats["1000nm"]["a00"] / flats["achromatic"]["a00"],
                                  abs(flats["1000nm"]["a00"] / flats["achromatic"]["a00"])
                                  * np.hypot(flats["1000nm"]["a00_err"] / flats["1000nm"]["a00"],
                                             flats["achromatic"]["a00_err"]
                                             / flats["achromatic"]["a00"]))
            ar = flats["bands"]["u"]
            for b in BANDS:
                fb = flats["bands"][b]
                ratio = fb["measured"] / ar["measured"]
                measured[b] = (ratio, abs(ratio) * np.hypot(fb["measured_err"] / fb["measured"],
                                                            ar["measured_err"] / ar["measured"]))
        say("  a00 factor of the flats (1000 nm: / achromatic; bands: / u): GalSim's stated "
            "mean tanh, with its box short-cuts, GalSim's flats")
        base = {}
        for src in (1000.0, *BANDS):
            d = depth_distribution(src, THICKNESS)
            rule = galsim_depth_factor(d, zfit=ZFIT)
            boxed = d.expectation(lambda z: np.interp(np.tanh(np.asarray(z) / ZFIT), scales,
                                                      res["boxes"]))
            key = "1000nm" if src == 1000.0 else src
            if key == "u":
                base = {"rule": rule, "boxes": boxed}
            if key != "1000nm":
                rule, boxed = rule / base["rule"], boxed / base["boxes"]
            m = measured.get(key)
            rec["sources"][key] = {"mean_tanh": rule, "with_boxes": boxed, "measured": m}
            say(f"  {key:>6s}: {rule:.4f}  {boxed:.4f}  " + (
                f"{m[0]:.4f} +- {m[1]:.4f} ({(m[0] - boxed) / m[1]:+.1f} sigma from the boxes, "
                f"{(m[0] - rule) / m[1]:+.1f} from the stated rule)" if m else "(not measured)"))
    text = "\n".join(lines)
    cmd = shlex.join(["python", os.path.relpath(os.path.abspath(__file__), REPO)]
                     + (argv if argv is not None else sys.argv[1:]))
    write_text(args.out + ".txt", f"# command: {cmd}\n# machine: {os.cpu_count()} cores\n"
               + text + "\n")
    write_json(args.out + ".json", {"command": cmd, **out}, indent=1,
               default=lambda o: o.tolist() if hasattr(o, "tolist") else float(o))
    return 0


if __name__ == "__main__":
    sys.exit(main())
