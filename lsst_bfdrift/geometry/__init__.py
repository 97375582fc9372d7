"""Superposition of a template over a charge image (stage 3).

Takes a template and a charge image (e); gives the final pixel polygons and
their moment maps: area, centroid shift and second moments / ellipticity per
pixel (the Green's-function step, exact shoelace moments).
"""


from lsst_bfdrift.geometry.superpose import *  # noqa: F401,F403
