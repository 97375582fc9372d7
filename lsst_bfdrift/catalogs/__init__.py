"""Star and spot catalogs and their brighter-fatter slopes.

Takes an image in electrons; gives its stars (photutils detection, flags,
adaptive second moments: :mod:`~lsst_bfdrift.catalogs.catalog`) and the
size- and shape-flux relations of a catalog with their errors
(:mod:`~lsst_bfdrift.catalogs.slopes`). The star-field calibration and the
validation both use them. A spot-projector series (the same spots at many
exposure times) gives its spots measured with one fixed weight
(:mod:`~lsst_bfdrift.catalogs.spots`), their slopes with errors from the
spot-to-spot and image-to-image scatter and a template's prediction of them
(:mod:`~lsst_bfdrift.catalogs.spot_slopes`), held together by
:class:`~lsst_bfdrift.catalogs.spot_series.SpotSeries`.
"""


from lsst_bfdrift.catalogs.catalog import *  # noqa: F401,F403
from lsst_bfdrift.catalogs.slopes import *  # noqa: F401,F403
from lsst_bfdrift.catalogs.spots import *  # noqa: F401,F403
from lsst_bfdrift.catalogs.spot_slopes import *  # noqa: F401,F403
from lsst_bfdrift.catalogs.spot_series import *  # noqa: F401,F403
