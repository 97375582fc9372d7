"""lsst_bfdrift: the electrostatic brighter-fatter model of thick CCDs.

The system of Rasmussen 2015 (JINST), built as a data flow of subpackages,
each importing only from those before it:

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
``calibration``
    PTC, a-matrix fits of the model, diagnosis of what it lacks;
``validation``
    star catalogues and residual brighter-fatter slopes;
``cli``
    the ``bfdrift`` command.

The names below are the package's main entry points; everything else is in
its subpackage.
"""

__version__ = "0.1.0"

from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters
from lsst_bfdrift.physics.drift import drift_lines
from lsst_bfdrift.physics.boundaries import pixel_boundaries
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.templates.template import (DistortionTemplate, TemplateSettings, build_template,
                                             load_default_template)
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.geometry.superpose import MomentMaps, moment_maps
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.utils.errors import (BfdriftError, ComputationError, FieldValidationError,
                                       FitError, InputAttributeError, InputError,
                                       InputFileError, InputKeyError, InputNotFoundError,
                                       InputTypeError, OutputExistsError, TemplateFileError)

__all__ = ["__version__", "SensorModel", "SensorParameters", "drift_lines", "pixel_boundaries",
           "pixel_polygons", "polygon_moments", "DistortionTemplate", "TemplateSettings",
           "build_template", "load_default_template", "import_galsim_sensor", "MomentMaps",
           "moment_maps", "BrighterFatterDriftConfig", "BrighterFatterDriftTask",
           "BfdriftError", "InputError", "InputTypeError", "InputKeyError", "InputAttributeError",
           "InputFileError", "InputNotFoundError", "TemplateFileError", "FieldValidationError",
           "OutputExistsError", "FitError", "ComputationError"]
