"""The brighter-fatter correction (stage 4).

Takes a template and an exposure; gives the flux-conserving correction
(drift series with its higher-order terms where they matter, and the
astier23 and coulton18 baselines), the :class:`BrighterFatterDriftTask` that
wires it with the geometry maps, and the batch route over many files.
"""


from lsst_bfdrift.correction.solvers import *  # noqa: F401,F403
from lsst_bfdrift.correction.series import *  # noqa: F401,F403
from lsst_bfdrift.correction.checks import *  # noqa: F401,F403
from lsst_bfdrift.correction.task import *  # noqa: F401,F403
from lsst_bfdrift.correction.batch import *  # noqa: F401,F403
