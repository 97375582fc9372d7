"""Diagnosis of what the brighter-fatter model lacks, from a sensor's flats.

Takes flat pairs, a PTC or an a-matrix and the calibrated model; gives the
observables the base model cannot produce (:mod:`~lsst_bfdrift.diagnosis.findings`),
the effects of the library (:mod:`~lsst_bfdrift.simulation.effects`) that
explain them, fitted with their significance
(:mod:`~lsst_bfdrift.diagnosis.effects_fit`), what each costs the correction
(:mod:`~lsst_bfdrift.diagnosis.consequence`) and a Markdown report
(:mod:`~lsst_bfdrift.diagnosis.report`).
"""


from lsst_bfdrift.diagnosis.observations import *  # noqa: F401,F403
from lsst_bfdrift.diagnosis.findings import *  # noqa: F401,F403
from lsst_bfdrift.diagnosis.effects_fit import *  # noqa: F401,F403
from lsst_bfdrift.diagnosis.consequence import *  # noqa: F401,F403
from lsst_bfdrift.diagnosis.report import *  # noqa: F401,F403
