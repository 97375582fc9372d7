"""lsst_bfdrift: the electrostatic brighter-fatter model of thick CCDs.

The system of Rasmussen 2015 (JINST), built as a data flow of subpackages,
each importing only from those before it:

``utils``
    errors, atomic file output, progress bars, the Config/Task framework;
``images``
    any accepted image into electrons (one unit, gain and saturation rule)
    and the LSST Exposure file layout;
``physics``
    field terms, drift lines, pixel boundaries by bisection, polygons;
``templates``
    portable distortion templates (the Green's function) and GalSim import;
``geometry``
    superposition of a template over a charge image: pixel geometry maps;
``correction``
    the flux-conserving correction and :class:`BrighterFatterDriftTask`;
``simulation``
    flats and stars with moving boundaries, GalSim-made twins;
``ptc``
    flat pairs, photon transfer curves, covariances and a-matrix tables;
``catalogs``
    star catalogs and their size- and shape-flux slopes;
``calibration``
    the model fitted to a-matrices and star fields: calibrated templates;
``diagnosis``
    what the model lacks, from the flats, and what it costs;
``validation``
    residual brighter-fatter slopes of corrected stars, the paper's figures;
``pipeline``
    the PipelineTask for ``pipetask`` on a Butler repository;
``cli``
    the ``bfdrift`` command.

The names below are the package's main entry points; everything else is in
its subpackage, and the exceptions are in :mod:`lsst_bfdrift.utils.errors`.
"""

from lsst_bfdrift.utils.version import __version__
from lsst_bfdrift.utils.errors import BfdriftError
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters
from lsst_bfdrift.physics.drift import drift_lines
from lsst_bfdrift.physics.boundaries import pixel_boundaries
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.templates.template import (DistortionTemplate, TemplateSettings, build_template,
                                             load_default_template)
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.geometry.superpose import MomentMaps, moment_maps
from lsst_bfdrift.correction.solvers import correct_image
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.ptc.inputs import read_calibration_input
from lsst_bfdrift.calibration.tuning import calibrate
from lsst_bfdrift.calibration.star_fit import calibrate_with_stars
from lsst_bfdrift.calibration.spot_fit import calibrate_with_spots

__all__ = ["__version__", "BfdriftError", "to_electrons", "SensorModel", "SensorParameters",
           "drift_lines", "pixel_boundaries", "pixel_polygons", "polygon_moments",
           "DistortionTemplate", "TemplateSettings", "build_template", "load_default_template",
           "import_galsim_sensor", "MomentMaps", "moment_maps", "correct_image",
           "BrighterFatterDriftConfig", "BrighterFatterDriftTask", "read_calibration_input",
           "calibrate", "calibrate_with_stars", "calibrate_with_spots"]
