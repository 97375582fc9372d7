"""Does a star field measure what a correction leaves? Fields with a brighter-fatter-free twin.

The star route (:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`)
trusts the size-flux slope that a field shows after a drift correction. This
script checks that slope against truth. It redraws the star fields of
``benchmarks/calibrate_stars.py`` (same seeds, so the brighter-fatter image
is identical to that script's cached field) with their twin: the same
photons, diffusion, sky and read noise, collected by galsim.SiliconSensor
with no brighter-fatter effect
(:func:`~lsst_bfdrift.simulation.skysim.simulate_star_field`, ``twin=True``).
Each field is corrected by drift with GalSim's own sensor file (imported
with transfer-matched edges; on paired stars it leaves +0.7 % (ITL) and
+1.9 % (e2v) of the size slope), and both images are measured on the same
detections (:class:`~lsst_bfdrift.calibration.star_fit.StarField`). Printed
per field, per 1e5 e:

* the uncorrected size (ln T) and e1 slopes with their bootstrap errors;
* the corrected slopes and the twin's slopes, as % of the uncorrected:
  the twin has no brighter-fatter effect, so its slope is the field's own
  measurement noise (its star sample, photons and sky), which the
  corrected image shares;
* corrected minus twin, as % of the effect (uncorrected minus twin), with
  the error of a straight-line fit to the per-star differences of ln T
  (or e1) against flux: what the correction leaves, with the field's noise
  cancelled.

A field route that measures corrections right shows corrected minus twin
near the paired stars' residual, whatever the corrected slope itself
shows::

    python benchmarks/field_twins.py [--sensors lsst_itl_50_8 lsst_e2v_50_8]
        [--fields 0 | --fields lsst_itl_50_8=2,3 lsst_e2v_50_8=0] [--cache /tmp/cst]

Writes ``benchmarks/field_twins_results.txt`` / ``.json``. Drawing a
2048 x 2048 field of 800 stars with its twin takes about 24 min on one core
(cached in ``--cache``).
"""

import argparse
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from calibrate_stars import field_seed  # noqa: E402
from lsst_bfdrift.calibration.star_fit import StarField  # noqa: E402
from lsst_bfdrift.calibration.star_slopes import FLUX_UNIT  # noqa: E402
from lsst_bfdrift.simulation.skysim import simulate_star_field  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.utils.io import write_json, write_text  # noqa: E402


def twin_field(sensor, k, args):
    """Field k of ``benchmarks/calibrate_stars.py`` with its BF-free twin (cached)."""
    seed = field_seed(sensor, k)
    path = os.path.join(args.cache, f"twin_{sensor}_{args.field_size}_{args.field_stars}_"
                                    f"{seed}.npz")
    if os.path.isfile(path):
        d = np.load(path)
        return d["bf"], d["truth"], seed, 0.0
    t0 = time.time()
    f = simulate_star_field((args.field_size,) * 2, args.field_stars, sensor=sensor,
                            flux=(1e4, 1.5e6), sky=1000.0, seed=seed, twin=True,
                            progress=True)
    tmp = path + ".tmp.npz"
    np.savez(tmp, bf=f["image"], truth=f["truth_image"])
    os.replace(tmp, path)
    return f["image"], f["truth_image"], seed, time.time() - t0


def difference_slope(flux, q_corr, q_twin):
    """Slope (per 1e5 e) of the per-star difference against flux, with an
    intercept, and its error from the scatter."""
    x = flux / FLUX_UNIT
    d = q_corr - q_twin
    a = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(a, d, rcond=None)
    r = d - a @ coef
    cov = np.linalg.inv(a.T @ a) * np.sum(r * r) / max(x.size - 2, 1)
    return float(coef[1]), float(np.sqrt(cov[1, 1]))


def fields_of(sensor, specs):
    """The field numbers of ``sensor`` in ``--fields`` (k, or SENSOR=k,k)."""
    out = []
    for spec in specs:
        name, _, ks = spec.rpartition("=")
        if name in ("", sensor):
            out += [int(k) for k in ks.split(",") if k]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8"])
    ap.add_argument("--fields", nargs="+", default=["0"],
                    help="field numbers of benchmarks/calibrate_stars.py: k (every sensor) or "
                         "SENSOR=k,k (that sensor)")
    ap.add_argument("--field-stars", type=int, default=800)
    ap.add_argument("--field-size", type=int, default=2048)
    ap.add_argument("--n-boot", type=int, default=100)
    ap.add_argument("--cache", default="/tmp/cst")
    ap.add_argument("--out", default=os.path.join(HERE, "field_twins_results"))
    args = ap.parse_args(argv)
    os.makedirs(args.cache, exist_ok=True)
    lines, rec = [], {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "fields": []}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    say(f"Star fields with a brighter-fatter-free twin ({args.field_size}^2 px, "
        f"{args.field_stars} stars, seeds of benchmarks/calibrate_stars.py), corrected by "
        f"drift with GalSim's own sensor file; slopes per 1e5 e; {rec['machine']}")
    for sensor in args.sensors:
        tpl = import_galsim_sensor(sensor, match="transfers")
        for k in fields_of(sensor, args.fields):
            bf_img, twin_img, seed, cost = twin_field(sensor, k, args)
            t0 = time.time()
            bf = StarField(bf_img, name=f"field{k}")
            # the twin measured on the same detections: the same stars, row by row
            twin = StarField(twin_img, name=f"field{k} twin", detections=bf.detections)
            use = bf.usable & twin.usable
            before = bf.slopes(None, use, n_boot=args.n_boot, seed=1)
            corr = bf.slopes(tpl, use, n_boot=args.n_boot, seed=1)
            free = twin.slopes(None, use, n_boot=args.n_boot, seed=1)
            cat_c = bf.corrected_catalog(tpl)
            flux = np.asarray(bf.catalog["flux"].value)[use]
            row = {"sensor": sensor, "field": k, "seed": seed, "n_stars": int(use.sum()),
                   "draw_seconds": cost}
            say(f"{sensor} field {k} (seed {seed}, {int(use.sum())} stars"
                + (f", drawn in {cost:.0f} s" if cost else ", cached") + ")")
            for q, col in (("size", "T"), ("e1", "e1")):
                qc, qt = (np.asarray(getattr(c[col], "value", c[col]), float)[use]
                          for c in (cat_c, twin.catalog))
                if q == "size":
                    qc, qt = np.log(qc), np.log(qt)
                d, d_err = difference_slope(flux, qc, qt)
                b = before[q][0]
                effect = b - free[q][0]
                row[q] = {"before": before[q], "corrected": corr[q], "twin": free[q],
                          "corrected_minus_twin": (d, d_err), "effect": effect}
                say(f"  {q:4s}: uncorrected {b:+.3e} +- {before[q][1]:.1e}; corrected "
                    f"{corr[q][0]:+.3e} ({100 * corr[q][0] / b:+.1f} +- "
                    f"{100 * corr[q][1] / abs(b):.1f} %); twin {free[q][0]:+.3e} "
                    f"({100 * free[q][0] / b:+.1f} %); corrected - twin per star {d:+.2e} "
                    f"+- {d_err:.1e} ({100 * d / effect:+.1f} +- {100 * d_err / abs(effect):.1f}"
                    " % of the effect)")
            row["measure_seconds"] = time.time() - t0
            rec["fields"].append(row)
    write_text(args.out + ".txt", "\n".join(lines) + "\n")
    write_json(args.out + ".json", rec, indent=1, default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
