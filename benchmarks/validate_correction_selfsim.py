"""Correction methods on stars simulated photon by photon with moving boundaries.

Truth: the same photons binned on square pixels (paired, so the comparison is
free of photon noise in the truth). Prints, for each method, the residual
size excess after correction as a fraction of the uncorrected growth, with
its error over the stars, and writes ``benchmarks/selfsim_results.txt``.

    python benchmarks/validate_correction_selfsim.py [--stars 8] [--flux 1e6]
"""

import argparse
import os
import sys

import galsim
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402
from lsst_bfdrift.stars import StarSimulation, image_moments, shoot_photons  # noqa: E402
from lsst_bfdrift.template import load_default_template  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--stars", type=int, default=8)
    ap.add_argument("--flux", type=float, default=1e6)
    ap.add_argument("--fwhm", type=float, default=0.7)
    a = ap.parse_args()
    t = load_default_template()
    rng = np.random.default_rng(9)
    out = {}
    methods = ("drift", "astier23", "coulton18")
    tasks = {m: BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        method=m, compute_geometry=False)) for m in methods}
    for k in range(a.stars):
        x, y = shoot_photons(galsim.Moffat(beta=3.5, fwhm=a.fwhm), int(a.flux), seed=100 + k)
        off = rng.uniform(-0.5, 0.5, 2)
        sim = StarSimulation(t, stamp_size=31, update_every=1000)
        sim.add(x + 15 + off[0], y + 15 + off[1])
        img, truth = sim.image, sim.nominal_image
        t0 = image_moments(truth, weight_sigma=3)["T"]
        ti = image_moments(img, weight_sigma=3)["T"]
        out.setdefault("uncorrected dT/T", []).append((ti - t0) / t0)
        for m in methods:
            tc = image_moments(tasks[m].run(img).exposure, weight_sigma=3)["T"]
            out.setdefault(m, []).append((tc - t0) / (ti - t0))
    lines = [f"{a.stars} Moffat stars, FWHM {a.fwhm} arcsec, {a.flux:.3g} e, bundled template; "
             "residual size excess / uncorrected growth (mean +- error of the mean):"]
    for k, v in out.items():
        lines.append(f"  {k:18s} {np.mean(v):+.4f} +- {np.std(v, ddof=1) / np.sqrt(len(v)):.4f}")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    with open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "selfsim_results.txt"),
              "w") as fh:
        fh.write(text)


if __name__ == "__main__":
    main()
