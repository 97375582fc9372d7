# command: python benchmarks/calibration/spots_truth.py
"""Can any template correct both spot sizes? GalSim's own file on its spots (issue 42).

``spots_stars.py`` finds the 1 and 2 px spot series of every sensor in
tension in the many-spot limit: the fit that corrects one size leaves a
few % of the other's size slope. This script asks whether that tension
belongs to the model's physics (a template the fit cannot reach) or to the
data and the correction (no template removes both): it corrects the same
paired spot series (BF minus its BF-free twin, the many-spot limit of
``spots_stars.py``'s ``spots, paired``) with GalSim's own sensor file, in
its two readings (``areas``: every pixel polygon's area GalSim's own;
``transfers``: every edge's swept area what galsim.SiliconSensor moves
across it), and with the a-matrix route's template (flats only, lags 0..3,
cached by ``spots_stars.py``).

Printed per sensor and spot sigma: the uncorrected paired size and e1
slopes per 1e5 e, and the % of them each template leaves (errors from the
spot-to-spot scatter of the paired rows); then, per template, the
difference of the size slope left between the two sizes (2 px minus 1 px,
in % points, with its error). A template that corrects stars must leave
both spot sizes near zero; if GalSim's own file leaves the two sizes apart
by as much as the fitted templates do, no template can close the tension
and the 2 % size target on stars inherits it.

Then, per sensor and size, the same question without GalSim: spots drawn
by the package's own photon-by-photon simulation
(:class:`~lsst_bfdrift.simulation.stars.StarSimulation`) with GalSim's
file (transfers) as the Green's function, on ``--centres`` sub-pixel
centres at the series' top flux, each paired with the same photons on
square pixels, and corrected by drift with the same template: the % of the
size growth (fixed-weight size, the series' weight) left is the
correction's own error at that spot size (a consistency check: simulation
and correction share the template), in both layouts (``shared``: the
template's tiling pixels; ``galsim``: GalSim's assignment rule emulated).

Reads the spot series and the a-matrix calibrations cached by
``spots_stars.py`` under ``--cache`` (draws them when absent, minutes per
series). Writes ``benchmarks/calibration/spots_truth_results.txt`` /
``.json``::

    python benchmarks/calibration/spots_truth.py [--sensors ...] [--sigma 1 2]
"""

import argparse
import os
import sys
import time
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common

from _common import Lines, settings_record, write_results  # noqa: E402
from spots_stars import (BIAS, FULL_WELL, PairedSpotSeries, flats_calibration,  # noqa: E402
                         slopes_left, spot_simulation)

from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402
from lsst_bfdrift.catalogs.spot_series import SpotSeries  # noqa: E402
from lsst_bfdrift.catalogs.spots import fixed_weight_moments  # noqa: E402
from lsst_bfdrift.simulation.stars import StarSimulation  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402

#: Quantities whose paired slopes are compared.
QUANTITIES = ("size", "e1")



def paired_series(sensor, args, sigma):
    """The sensor's paired spot series of one sigma (spots_stars.py's draw and cache)."""
    sim, _ = spot_simulation(sensor, args, sigma)
    bf = SpotSeries([im - BIAS for im in sim["images"]], exptimes=sim["exptimes"],
                    saturation=FULL_WELL)
    twin = SpotSeries([im - BIAS for im in sim["twins"]], exptimes=sim["exptimes"],
                      saturation=FULL_WELL, grid=bf.grid)
    return PairedSpotSeries(bf, twin.catalog), sim["seed"]


def selfsim_left(template, sigma, flux, weight_sigma, radius, *, centres, layout, seed):
    """% of the fixed-weight size growth the drift correction leaves on spots drawn with
    ``template`` itself (mean, error of the mean over ``centres`` x ``centres`` centres)."""
    import galsim

    task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        method="drift", compute_geometry=False), template=template)
    g = (np.arange(centres) + 0.5) / centres - 0.5
    n, c = 41, 20
    left = []
    for k, (ox, oy) in enumerate([(a, b) for a in g for b in g]):
        phot = galsim.Gaussian(sigma=sigma).shoot(int(flux), galsim.BaseDeviate(seed + k))
        sim = StarSimulation(template, stamp_size=n, update_every=max(1, int(flux) // 1000),
                             layout=layout, seed=seed + k)
        sim.add(phot.x + c + ox, phot.y + c + oy)
        img = sim.image
        corr = np.asarray(task.run(img).exposure.data, float)
        size = [fixed_weight_moments(a, weight_sigma=weight_sigma, radius=radius,
                                     center=(c + ox, c + oy))["T"]
                for a in (sim.nominal_image, img, corr)]
        left.append((size[2] - size[0]) / (size[1] - size[0]))
    v = 100 * np.array(left)
    return float(v.mean()), float(v.std(ddof=1) / np.sqrt(v.size))


def run_sensor(sensor, args, say):
    res_a, _ = flats_calibration(sensor, lags=args.lags, cache=args.cache)
    templates = {"flats only": res_a.template,
                 "GalSim file (areas)": import_galsim_sensor(sensor, match="areas"),
                 "GalSim file (transfers)": import_galsim_sensor(sensor, match="transfers")}
    rec = {}
    say(f"{sensor}: % of the paired spot slope left (many-spot limit), errors from the "
        "spot-to-spot scatter")
    for sigma in args.sigma:
        t0 = time.time()
        series, seed = paired_series(sensor, args, sigma)
        before = {q: v for q, v in series.slopes(None, quantities=QUANTITIES).items()
                  if q in QUANTITIES}
        r = rec[f"sigma {sigma:g}"] = {"seed": seed, "uncorrected_per_1e5": before}
        say(f" sigma {sigma:g} px (seed {seed}): uncorrected size {before['size'][0]:+.3e} "
            f"+- {before['size'][1]:.1e}, e1 {before['e1'][0]:+.3e} +- {before['e1'][1]:.1e} "
            "per 1e5 e")
        for name, tpl in templates.items():
            left = r[name] = slopes_left(series, tpl, before, QUANTITIES)
            say(f"  {name:24s} size {left['size'][0]:+6.2f} +- {left['size'][1]:4.2f} %   "
                f"e1 {left['e1'][0]:+7.2f} +- {left['e1'][1]:5.2f} %")
        if args.centres:
            cat = series.catalog
            grid = series.grid
            top = float(np.max(np.asarray(cat["flux"], float)[np.asarray(cat["use"], bool)]))
            r["selfsim"] = {}
            for layout in ("shared", "galsim"):
                m, e = selfsim_left(templates["GalSim file (transfers)"], sigma, top,
                                    grid.weight_sigma, grid.radius, centres=args.centres,
                                    layout=layout, seed=int(1000 * sigma) + 7)
                r["selfsim"][layout] = (m, e)
                say(f"  self-simulated with GalSim's file (transfers), {layout} layout, "
                    f"{args.centres ** 2} spots of {top:.3g} e: size {m:+6.2f} +- {e:4.2f} % "
                    "left by drift with the same file")
        say(f"  ({time.time() - t0:.0f} s)")
    if len(args.sigma) > 1:
        a, b = (f"sigma {s:g}" for s in args.sigma[:2])
        rec["size_left_difference"] = {}
        for name in templates:
            d = rec[b][name]["size"][0] - rec[a][name]["size"][0]
            e = np.hypot(rec[b][name]["size"][1], rec[a][name]["size"][1])
            rec["size_left_difference"][name] = (d, e)
            say(f" {name:25s} size left, {b} minus {a}: {d:+6.2f} +- {e:4.2f} % points")
    return rec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("--sensors", nargs="+",
                    default=["lsst_itl_50_8", "lsst_e2v_50_8", "lsst_itl_50_32"])
    ap.add_argument("--sigma", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--lags", type=int, default=3)
    ap.add_argument("--centres", type=int, default=4,
                    help="self-simulated spots on centres x centres sub-pixel centres (0: none)")
    # the spot design of spots_stars.py (its cache keys)
    ap.add_argument("--grid", type=int, nargs=2, default=[5, 5])
    ap.add_argument("--pitch", type=float, default=40.0)
    ap.add_argument("--n-images", type=int, default=6)
    ap.add_argument("--updates", type=float, default=300.0)
    ap.add_argument("--cache", default="/work/cache/spots_val/cal",
                    help="spots_stars.py's cache prefix (calibrations, spot series)")
    ap.add_argument("--out", default=os.path.join(HERE, "spots_truth_results"))
    args = ap.parse_args(argv)
    out, say = {"settings": settings_record(args), "sensors": {}}, Lines()
    for sensor in args.sensors:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the calibration's poor-fit warning is in its fit
            out["sensors"][sensor] = run_sensor(sensor, args, say)
    write_results(args.out, say, out, script=__file__)


if __name__ == "__main__":
    main()
