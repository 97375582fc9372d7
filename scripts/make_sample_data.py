"""Regenerate the bundled sample data (run from the repository root).

* ``lsst_bfdrift/data/sample_star.fits``: a 64 x 64 image in electrons of a
  bright Moffat star (FWHM 0.7 arcsec at 0.2 arcsec/px, flux 1.5e6 e, centre
  offset (0.25, 0.25) px) on a 1000 e sky, Poisson noise, seed 20151.
* ``lsst_bfdrift/data/default_template.fits``: the default template, built
  from ``lsst_bfdrift/data/default_template_config.json``.

Usage: ``python scripts/make_sample_data.py [--star] [--template]``
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


def make_template(path):
    from lsst_bfdrift.cli.main import read_config
    from lsst_bfdrift.templates.template import build_template
    params, settings = read_config(os.path.join(DATA, "default_template_config.json"))
    build_template(params, settings, progress=True).save(path, overwrite=True)
    print("wrote", path)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--star", action="store_true")
    ap.add_argument("--template", action="store_true")
    a = ap.parse_args()
    if a.star or not (a.star or a.template):
        make_star(os.path.join(DATA, "sample_star.fits"))
    if a.template or not (a.star or a.template):
        make_template(os.path.join(DATA, "default_template.fits"))
