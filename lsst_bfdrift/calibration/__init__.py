"""Tuning the model to a sensor's characterization data.

Takes measured area coefficients a_ij (from :mod:`lsst_bfdrift.ptc`) and,
optionally, star fields (catalogs from :mod:`lsst_bfdrift.catalogs`); gives
the electrostatic model's a_ij and its fit (:mod:`~lsst_bfdrift.calibration.acoeff_model`),
the calibrated template with its uncertainty
(:func:`~lsst_bfdrift.calibration.tuning.calibrate`), and the joint fit of
flats and star fields (:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`)
or spot-projector series (:func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`),
and LSST's two routes from the same a-matrix with their products
(:mod:`~lsst_bfdrift.calibration.routes`, :mod:`~lsst_bfdrift.calibration.lsst_products`).
"""


from lsst_bfdrift.calibration.fitting import *  # noqa: F401,F403
from lsst_bfdrift.calibration.acoeff_model import *  # noqa: F401,F403
from lsst_bfdrift.calibration.sensor_fit import *  # noqa: F401,F403
from lsst_bfdrift.calibration.fit_model import *  # noqa: F401,F403
from lsst_bfdrift.calibration.tuning import *  # noqa: F401,F403
from lsst_bfdrift.calibration.star_result import *  # noqa: F401,F403
from lsst_bfdrift.calibration.star_fit import *  # noqa: F401,F403
from lsst_bfdrift.calibration.spot_bias import *  # noqa: F401,F403
from lsst_bfdrift.calibration.spot_fit import *  # noqa: F401,F403
from lsst_bfdrift.calibration.astier23_model import *  # noqa: F401,F403
from lsst_bfdrift.calibration.lsst_products import *  # noqa: F401,F403
from lsst_bfdrift.calibration.routes import *  # noqa: F401,F403
