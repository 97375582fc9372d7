"""Star catalogs and their brighter-fatter slopes.

Takes an image in electrons; gives its stars (photutils detection, flags,
adaptive second moments: :mod:`~lsst_bfdrift.catalogs.catalog`) and the
size- and shape-flux relations of a catalog with their errors
(:mod:`~lsst_bfdrift.catalogs.slopes`). The star-field calibration and the
validation both use them.
"""


from lsst_bfdrift.catalogs.catalog import *  # noqa: F401,F403
from lsst_bfdrift.catalogs.slopes import *  # noqa: F401,F403
