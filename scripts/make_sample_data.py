"""Regenerate the bundled sample data (run from the repository root).

* ``lsst_bfdrift/data/sample_star.fits``: a 64 x 64 image in electrons of a
  bright Moffat star (FWHM 0.7 arcsec at 0.2 arcsec/px, flux 1.5e6 e, centre
  offset (0.25, 0.25) px) on a 1000 e sky, Poisson noise, seed 20151.
The default template is made by ``python benchmarks/calibration/calibrate_default.py
--write`` (the model calibrated to the measured ITL a-matrix).

Usage: ``python scripts/make_sample_data.py``
"""

import argparse
import os
import sys

import galsim
import numpy as np
from astropy.io import fits

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = os.path.join(HERE, "..", "lsst_bfdrift", "data")
sys.path.insert(0, os.path.join(HERE, ".."))  # this checkout's lsst_bfdrift, not an installed one


def make_star(path):
    rng = galsim.BaseDeviate(20151)
    psf = galsim.Moffat(beta=3.5, fwhm=0.7).withFlux(1.5e6)
    img = galsim.ImageD(64, 64, scale=0.2)
    psf.drawImage(img, offset=(0.25, 0.25), method="phot", rng=rng)
    img.addNoise(galsim.PoissonNoise(rng, sky_level=1000.0))
    data = img.array + 1000.0
    hdr = fits.Header()
    hdr["BUNIT"] = "electron"
    hdr["COMMENT"] = "lsst_bfdrift sample: Moffat FWHM 0.7 arcsec, 1.5e6 e, sky 1000 e"
    fits.PrimaryHDU(data.astype(np.float32), header=hdr).writeto(path, overwrite=True,
                                                                 checksum=True)
    print("wrote", path)


if __name__ == "__main__":
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    make_star(os.path.join(DATA, "sample_star.fits"))
