"""Superposition of a template over a charge image.

Takes a template and a charge image (e); gives the final pixel polygons and
their moment maps: area, centroid shift and second moments / ellipticity per
pixel (the Green's-function step): exact shoelace moments
(:mod:`~lsst_bfdrift.geometry.superpose`) or maps to first order in the
charge (:mod:`~lsst_bfdrift.geometry.first_order`) with exact moments where
the first order is not enough (:mod:`~lsst_bfdrift.geometry.linear`).
"""


from lsst_bfdrift.geometry.superpose import *  # noqa: F401,F403
from lsst_bfdrift.geometry.first_order import *  # noqa: F401,F403
from lsst_bfdrift.geometry.linear import *  # noqa: F401,F403
from lsst_bfdrift.geometry.bounds import *  # noqa: F401,F403
