"""Simulated data with moving pixel boundaries.

Takes a template (or a GalSim sensor); gives flat fields and their
covariances, flat pairs with injected non-BF effects (the effect library's
forward models), stars drawn with moving boundaries, and paired
galsim.SiliconSensor images, sky-like fields and spot-projector series
(BF on and off), chromatic ones with photon wavelengths per LSST band.
"""


from lsst_bfdrift.simulation.effects import *  # noqa: F401,F403
from lsst_bfdrift.simulation.flats import *  # noqa: F401,F403
from lsst_bfdrift.simulation.stars import *  # noqa: F401,F403
from lsst_bfdrift.simulation.galsim_twins import *  # noqa: F401,F403
from lsst_bfdrift.simulation.skysim import *  # noqa: F401,F403
from lsst_bfdrift.simulation.spots import *  # noqa: F401,F403
from lsst_bfdrift.simulation.chromatic import *  # noqa: F401,F403
