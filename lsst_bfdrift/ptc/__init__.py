"""Measuring a sensor's flats: photon transfer, covariances and a-matrices.

Takes flat pairs (FITS), PTC text files, a-matrix tables and cp_pipe's PTC
dataset; gives the pairs' covariances against signal and their fits with
the Astier et al. 2019 models (:mod:`~lsst_bfdrift.ptc.covariances`,
:mod:`~lsst_bfdrift.ptc.full_model`), the
observables of a flat set (:mod:`~lsst_bfdrift.ptc.observables`), tables of
area coefficients a_ij with their errors, orientation and sum rule
(:mod:`~lsst_bfdrift.ptc.acoeffs`), and one
:class:`~lsst_bfdrift.ptc.data.CalibrationData` of whichever input a user
brings (:func:`~lsst_bfdrift.ptc.inputs.read_calibration_input`).
"""


from lsst_bfdrift.ptc.covariances import *  # noqa: F401,F403
from lsst_bfdrift.ptc.full_model import *  # noqa: F401,F403
from lsst_bfdrift.ptc.observables import *  # noqa: F401,F403
from lsst_bfdrift.ptc.acoeffs import *  # noqa: F401,F403
from lsst_bfdrift.ptc.data import *  # noqa: F401,F403
from lsst_bfdrift.ptc.cp_pipe import *  # noqa: F401,F403
from lsst_bfdrift.ptc.inputs import *  # noqa: F401,F403
