"""GalSim SiliconSensor star fields shared by the star tests (drawn once per session)."""

import functools

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.simulation.skysim import simulate_star_field
from tests._shared import shared

#: strengths of the paired fields: the same photons, diffusion and noise, only BF differs
STRENGTHS = (0.0, 5.0, 10.0)


@functools.lru_cache(maxsize=None)
def paired_fields():
    """Three 320 x 320 fields of 22 stars with BF strength 0, 5 and 10 (seeded).

    The sky is collected through the sensor in 13 x 13 px (+3 px margin) around
    each star, with about 50 boundary updates per star (library defaults: 17 x 17
    and 1000), which keeps the drawing at about 2.2x the time of sky added afterwards
    (3.1x with 100 updates; more with the defaults).
    """
    return shared("paired_fields", lambda: simulate_star_field(
        (320, 320), 22, strength=STRENGTHS, flux=(2e4, 1.5e6), sky_radius=6, updates=50,
        min_nrecalc=1e4, seed=20157))


@functools.lru_cache(maxsize=None)
def galsim_template():
    """The template of GalSim's lsst_itl_50_8 sensor (strength 1)."""
    return import_galsim_sensor("lsst_itl_50_8")
