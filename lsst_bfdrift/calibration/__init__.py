"""Tuning the model to a sensor's characterization data (stage 5).

Takes flat pairs, PTC files, a-matrix tables and star fields; gives star
catalogues and their size- and shape-flux slopes, photon-transfer
covariances and their model fits, the electrostatic model fitted to the
measured area coefficients a_ij, and the diagnosis of what the base model
lacks (with a Markdown report).
"""


from lsst_bfdrift.calibration.fitting import *  # noqa: F401,F403
from lsst_bfdrift.calibration.ptc import *  # noqa: F401,F403
from lsst_bfdrift.calibration.data import *  # noqa: F401,F403
from lsst_bfdrift.calibration.cp_pipe import *  # noqa: F401,F403
from lsst_bfdrift.calibration.inputs import *  # noqa: F401,F403
from lsst_bfdrift.calibration.acoeff_fit import *  # noqa: F401,F403
from lsst_bfdrift.calibration.sensor_fit import *  # noqa: F401,F403
from lsst_bfdrift.calibration.tuning import *  # noqa: F401,F403
from lsst_bfdrift.calibration.catalog import *  # noqa: F401,F403
from lsst_bfdrift.calibration.star_slopes import *  # noqa: F401,F403
from lsst_bfdrift.calibration.flat_observations import *  # noqa: F401,F403
from lsst_bfdrift.calibration.diagnosis import *  # noqa: F401,F403
from lsst_bfdrift.calibration.report import *  # noqa: F401,F403
