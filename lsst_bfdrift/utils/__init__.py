"""Shared helpers of every stage: the exception hierarchy, atomic file output,
bundled data, progress bars, the Config/Task framework and the plotting back
end.

Takes nothing from the rest of the package. :mod:`~lsst_bfdrift.utils.plotting`
(matplotlib) is imported only by the figure modules, not here.
"""


from lsst_bfdrift.utils.errors import *  # noqa: F401,F403
from lsst_bfdrift.utils.io import *  # noqa: F401,F403
from lsst_bfdrift.utils.progress import *  # noqa: F401,F403
from lsst_bfdrift.utils.config import *  # noqa: F401,F403
