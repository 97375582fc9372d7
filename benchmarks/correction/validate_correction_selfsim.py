"""Correction methods on stars simulated photon by photon with moving boundaries.

Truth: the same photons binned on square pixels (paired, so the comparison is
free of photon noise in the truth); the simulation and the corrections use
the same (bundled) template, so what remains is the error of the correction
model itself. For each PSF width, prints for every method the residual size
excess after correction as a fraction of the uncorrected growth (mean and
error over the stars), with two size measures: adaptive moments (HSM, the
measure of ``bfdrift validate-stars``) and fixed Gaussian-weight moments
(sigma = 3 px). The "paired" lines give the per-star differences between
two methods on the same images, free of the star-to-star scatter. Writes
``benchmarks/correction/validate_correction_selfsim_results.txt``::

    python benchmarks/correction/validate_correction_selfsim.py [--grid 4] [--flux 1e6] \
        [--fwhm 0.6 0.7 0.9] [--psf moffat kolmogorov]
"""

import argparse
import os
import sys

import galsim
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402
from lsst_bfdrift.simulation.stars import StarSimulation, image_moments, shoot_photons  # noqa: E402
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402
from lsst_bfdrift.validation.stars import star_moments as _moments  # noqa: E402

VARIANTS = {"drift": dict(method="drift"),  # default density 'fv4'
            "drift cubic4": dict(method="drift", density="cubic4"),
            "drift mean2": dict(method="drift", density="mean2"),
            "astier23": dict(method="astier23"),
            "coulton18": dict(method="coulton18")}
MEASURES = {"adaptive": lambda a: _moments(a, 0.0)[0],
            "fixed s=3": lambda a: image_moments(a, weight_sigma=3)["T"]}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--grid", type=int, default=4,
                    help="sub-pixel centres on a grid x grid lattice (grid^2 stars per width)")
    ap.add_argument("--flux", type=float, default=1e6)
    ap.add_argument("--fwhm", type=float, nargs="+", default=[0.6, 0.7, 0.9])
    ap.add_argument("--psf", nargs="+", default=["moffat", "kolmogorov"],
                    choices=["moffat", "kolmogorov"])
    a = ap.parse_args()
    t = load_default_template()
    tasks = {m: BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False, **kw)) for m, kw in VARIANTS.items()}
    g = (np.arange(a.grid) + 0.5) / a.grid - 0.5
    offsets = [(ox, oy) for ox in g for oy in g]  # balanced over the pixel phase
    lines = [f"{len(offsets)} stars (Moffat beta 3.5, Kolmogorov) of {a.flux:.3g} e per PSF and "
             f"width, centres on a "
             f"{a.grid} x {a.grid} sub-pixel grid, bundled template "
             "in the simulation and the corrections, 1000 boundary updates per star; residual "
             "size excess / uncorrected growth (mean +- error of the mean)"]
    for psf, fwhm in [(p, w) for p in a.psf for w in a.fwhm]:
        res = {(ms, m): [] for ms in MEASURES for m in VARIANTS}
        unc = {ms: [] for ms in MEASURES}
        for k, off in enumerate(offsets):
            prof = (galsim.Kolmogorov(fwhm=fwhm) if psf == "kolmogorov"
                    else galsim.Moffat(beta=3.5, fwhm=fwhm))
            x, y = shoot_photons(prof, int(a.flux), seed=100 + k)
            sim = StarSimulation(t, stamp_size=31, update_every=int(a.flux // 1000))
            sim.add(x + 15 + off[0], y + 15 + off[1])
            img, truth = sim.image, sim.nominal_image
            corrected = {m: task.run(img).exposure for m, task in tasks.items()}
            for ms, f in MEASURES.items():
                t0, ti = f(truth), f(img)
                unc[ms].append((ti - t0) / t0)
                for m, c in corrected.items():
                    res[(ms, m)].append((f(c) - t0) / (ti - t0))
        for ms in MEASURES:
            u = np.array(unc[ms])
            lines.append(f"{psf} FWHM {fwhm} arcsec, {ms} moments: uncorrected dT/T "
                         f"{u.mean():+.5f} +- {u.std(ddof=1) / np.sqrt(len(u)):.5f}")
            for m in VARIANTS:
                v = np.array(res[(ms, m)])
                lines.append(f"  {m:14s} {100 * v.mean():+6.2f} +- "
                             f"{100 * v.std(ddof=1) / np.sqrt(len(v)):.2f} %")
            for m in ("drift", "drift cubic4", "drift mean2"):
                d = np.array(res[(ms, m)]) - np.array(res[(ms, "astier23")])
                lines.append(f"  paired {m} - astier23 {100 * d.mean():+6.2f} +- "
                             f"{100 * d.std(ddof=1) / np.sqrt(len(d)):.2f} %")
        print("\n".join(lines[-(2 * (len(VARIANTS) + 3)):]), flush=True)
    write_results(os.path.join(HERE, "validate_correction_selfsim_results"), lines,
                  script=__file__)


if __name__ == "__main__":
    main()
