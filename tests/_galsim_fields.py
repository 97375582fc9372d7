"""GalSim SiliconSensor star fields shared by the star tests (drawn once per process)."""

import functools

from lsst_bfdrift.skysim import simulate_star_field
from lsst_bfdrift.template import DistortionTemplate

#: strengths of the paired fields: the same photons, diffusion and noise, only BF differs
STRENGTHS = (0.0, 3.0, 6.0)


@functools.lru_cache(maxsize=None)
def paired_fields():
    """Three 320 x 320 fields of 22 stars with BF strength 0, 3 and 6 (seeded)."""
    return simulate_star_field((320, 320), 22, strength=STRENGTHS, flux=(2e4, 1.5e6),
                               seed=20157)


@functools.lru_cache(maxsize=None)
def galsim_template():
    """The template of GalSim's lsst_itl_50_8 sensor (strength 1)."""
    return DistortionTemplate.from_galsim("lsst_itl_50_8")
