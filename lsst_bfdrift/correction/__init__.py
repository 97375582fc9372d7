"""The brighter-fatter correction.

Takes a template and an image in electrons; gives the flux-conserving
correction (drift series with its higher-order terms where they matter,
and the astier23 and coulton18 baselines) with its recommended settings
(:mod:`~lsst_bfdrift.correction.settings`), the steps of a run
(:mod:`~lsst_bfdrift.correction.steps`), the
:class:`BrighterFatterDriftTask` that wires them with the geometry maps, and
the batch route over many files.
"""


from lsst_bfdrift.correction.settings import *  # noqa: F401,F403
from lsst_bfdrift.correction.solvers import *  # noqa: F401,F403
from lsst_bfdrift.correction.series import *  # noqa: F401,F403
from lsst_bfdrift.correction.tiles import *  # noqa: F401,F403
from lsst_bfdrift.correction.checks import *  # noqa: F401,F403
from lsst_bfdrift.correction.steps import *  # noqa: F401,F403
from lsst_bfdrift.correction.task import *  # noqa: F401,F403
from lsst_bfdrift.correction.batch import *  # noqa: F401,F403
