"""Validation of the corrections.

Takes exposures, star catalogs and templates; gives star catalogs
(photutils), catalog-level shape corrections, residual size-flux slopes on
the sky and on paired GalSim stars, and the reproduction of Rasmussen 2015's
figures.
"""


from lsst_bfdrift.validation.shape_correction import *  # noqa: F401,F403
from lsst_bfdrift.validation.sky import *  # noqa: F401,F403
from lsst_bfdrift.validation.stars import *  # noqa: F401,F403
from lsst_bfdrift.validation.paper_figures import *  # noqa: F401,F403
