"""Spot slopes measured on GalSim spot series, against their BF-free twins and the
prediction of each sensor's true template (issue 42, items 1 and 3).

For each GalSim sensor model (default lsst_itl_50_8, lsst_e2v_50_8 and
lsst_itl_50_32):

1. a spot series drawn by galsim.SiliconSensor
   (:func:`~lsst_bfdrift.simulation.spots.simulate_spot_series`): a 5 x 5
   grid of Gaussian spots of sigma 1.5 px, 6 exposures whose mean spot flux
   runs from 1e4 e to the flux that puts 9e4 e in the peak pixel (1.3e6 e),
   read noise 5 e, a 1000 e bias pedestal, pixels clipped at 8.5e4 e above
   it (``SATURATE``: the spots of the last exposure whose peak pixel reaches
   it are flagged saturated, left out and counted), with the paired BF-free
   twins (same photons and noise);
2. the spot measurement (:class:`~lsst_bfdrift.catalogs.spot_series.SpotSeries`):
   the slopes of sigma_x, sigma_y, size = ln T, e1 and e2 against flux, with
   errors from the spot-to-spot and image-to-image scatter; the twins
   measured on the same grid with the same weight;
3. the truth of this design: the slope of the paired difference, BF minus
   twin, row by row (no pixel noise of its own: its error is the scatter of
   the differences);
4. the prediction of the sensor's true template (its file imported with
   ``match='transfers'``) by the drift forward model over the measured spots
   (:func:`~lsst_bfdrift.catalogs.spot_slopes.predict_spot_slopes`).

Prints, per sensor and quantity, the measured slope with its error, the
twins' slope (zero within its error if the measurement is unbiased), the
paired truth, the prediction, and measured / predicted and paired /
predicted; writes ``benchmarks/calibration/spots_measure_results.txt`` /
``.json``::

    python benchmarks/calibration/spots_measure.py [--sensors lsst_itl_50_8 ...]
        [--grid 5 5] [--n-images 6] [--sigma 1.5] [--profile gaussian]
"""

import argparse
import os
import sys
import time
import zlib

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.catalogs.spot_series import SpotSeries  # noqa: E402
from lsst_bfdrift.catalogs.spot_slopes import fit_spot_slope  # noqa: E402
from lsst_bfdrift.catalogs.spots import SPOT_QUANTITIES  # noqa: E402
from lsst_bfdrift.simulation.spots import simulate_spot_series  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402

#: Clip level above the bias (e): the saturation of the simulated sensor.
FULL_WELL = 8.5e4
#: Bias pedestal (e), removed by the spots' local background.
BIAS = 1000.0


def _col(cat, name):
    return np.asarray(getattr(cat[name], "value", cat[name]), float)


def paired_slopes(bf, twin):
    """Slopes of BF minus twin, row by row (rows used in both), with the spot fit."""
    c1, c2 = bf.catalog, twin.catalog
    use = np.asarray(c1["use"]) & np.asarray(c2["use"])
    out = {}
    for q in SPOT_QUANTITIES:
        f = fit_spot_slope(np.asarray(c1["spot"])[use], np.asarray(c1["image"])[use],
                           _col(c1, "flux")[use], (_col(c1, q) - _col(c2, q))[use],
                           _col(c1, f"{q}_err")[use], scale_errors=True)
        out[q] = {"slope": f["slope"], "slope_err": f["slope_err"]}
    return out


def run_sensor(sensor, args):
    seed = zlib.crc32(f"spots:{sensor}".encode()) % 100000
    t0 = time.time()
    sim = simulate_spot_series(sensor=sensor, grid=tuple(args.grid), pitch=args.pitch,
                               sigma=args.sigma, profile=args.profile, n_images=args.n_images,
                               flux_min=1e4, peak_max=9e4, read_noise=5.0, bias=BIAS,
                               full_well=FULL_WELL, twin=True, updates=args.updates, seed=seed)
    t_sim = time.time() - t0
    sat = FULL_WELL + BIAS
    t0 = time.time()
    bf = SpotSeries(sim["images"], exptimes=sim["exptimes"], saturation=sat)
    twin = SpotSeries(sim["twins"], exptimes=sim["exptimes"], saturation=sat, grid=bf.grid)
    measured, null = bf.fit(), twin.fit()
    paired = paired_slopes(bf, twin)
    t_meas = time.time() - t0
    t0 = time.time()
    tpl = import_galsim_sensor(sensor, match="transfers")
    t_import = time.time() - t0
    t0 = time.time()
    pred = bf.predict(tpl, measured=measured)
    t_pred = time.time() - t0
    rows = {}
    for q in SPOT_QUANTITIES:
        m, p, t, z = measured[q], pred[q]["slope"], paired[q], null[q]
        rows[q] = {"measured": m["slope"], "measured_err": m["slope_err"],
                   "err_formal": m["err_formal"], "err_image": m["err_image"],
                   "err_spot": m["err_spot"], "tau": m["tau"], "chi2_dof": m["chi2_dof"],
                   "twin": z["slope"], "twin_err": z["slope_err"],
                   "paired": t["slope"], "paired_err": t["slope_err"], "predicted": p,
                   "measured_over_predicted": m["slope"] / p,
                   "measured_over_predicted_err": m["slope_err"] / abs(p),
                   "paired_over_predicted": t["slope"] / p,
                   "paired_over_predicted_err": t["slope_err"] / abs(p)}
    excl = measured["excluded"]
    return {"seed": seed, "levels": sim["levels"].value.tolist(),
            "exptimes": sim["exptimes"].value.tolist(),
            "weight_sigma": bf.grid.weight_sigma, "n_spots": len(bf.grid),
            "rows_used": measured["n_points"], "rows": excl["rows"],
            "saturated": excl["saturated"], "edge": excl["edge"],
            "saturated_per_image": [im["saturated"] for im in excl["images"]],
            "slopes": rows,
            "seconds": {"simulation": t_sim, "measurement": t_meas, "import": t_import,
                        "prediction": t_pred}}


def report(sensor, r):
    lines = [f"{sensor}: {r['n_spots']} spots x {len(r['levels'])} images, mean spot flux "
             f"{r['levels'][0]:.3g}-{r['levels'][-1]:.3g} e, fixed weight sigma "
             f"{r['weight_sigma']:g} px; {r['rows_used']} of {r['rows']} rows used, "
             f"{r['saturated']} saturated (per image {r['saturated_per_image']}), "
             f"{r['edge']} at the edge; simulation {r['seconds']['simulation']:.0f} s, "
             f"measurement {r['seconds']['measurement']:.1f} s, prediction "
             f"{r['seconds']['prediction']:.1f} s",
             "  slope per 1e5 e   measured (err: formal / image / spot)       BF-free twin"
             "             paired BF-twin           predicted   meas/pred        paired/pred"]
    for q, s in r["slopes"].items():
        lines.append(
            f"  {q:8s} {s['measured']:+.3e} +- {s['measured_err']:.1e} ({s['err_formal']:.1e} / "
            f"{s['err_image']:.1e} / {s['err_spot']:.1e})  {s['twin']:+.2e} +- "
            f"{s['twin_err']:.1e}  {s['paired']:+.3e} +- {s['paired_err']:.1e}  "
            f"{s['predicted']:+.3e}  {s['measured_over_predicted']:6.3f} +- "
            f"{s['measured_over_predicted_err']:.3f}  {s['paired_over_predicted']:6.3f} +- "
            f"{s['paired_over_predicted_err']:.3f}")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+",
                    default=["lsst_itl_50_8", "lsst_e2v_50_8", "lsst_itl_50_32"])
    ap.add_argument("--grid", type=int, nargs=2, default=[5, 5])
    ap.add_argument("--pitch", type=float, default=40.0)
    ap.add_argument("--n-images", type=int, default=6)
    ap.add_argument("--sigma", type=float, default=1.5)
    ap.add_argument("--profile", default="gaussian", choices=("gaussian", "moffat"))
    ap.add_argument("--updates", type=float, default=300.0)
    ap.add_argument("--out", default=os.path.join(HERE, "spots_measure_results"))
    args = ap.parse_args(argv)
    out = {"settings": {"grid": args.grid, "pitch": args.pitch, "n_images": args.n_images,
                        "sigma": args.sigma, "profile": args.profile, "updates": args.updates,
                        "flux_min": 1e4, "peak_max": 9e4, "full_well": FULL_WELL, "bias": BIAS,
                        "read_noise": 5.0, "template": "import_galsim_sensor(match='transfers')",
                        "units": "slopes per 1e5 e: px for sigma_x, sigma_y; fractional for "
                                 "size = ln T; change of e1, e2"},
           "sensors": {}}
    lines = []
    for sensor in args.sensors:
        r = run_sensor(sensor, args)
        out["sensors"][sensor] = r
        block = report(sensor, r)
        print("\n".join(block), flush=True)
        lines += block
    write_results(args.out, lines, out, script=__file__, json_default=float)


if __name__ == "__main__":
    main()
