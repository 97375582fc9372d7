"""lsst_bfdrift: electrostatic brighter-fatter model of thick CCDs.

Implements the drift model of Rasmussen 2015 (JINST): electrostatic field
terms, drift lines, pixel boundaries by bisection, portable pixel-distortion
templates used as Green's functions, and polygon moments.
"""

__version__ = "0.1.0"

from .fields import *  # noqa: F401,F403
from .sensor import SensorModel, SensorParameters  # noqa: F401
from .drift import drift_lines, landing_pixels  # noqa: F401
from .boundaries import BoundaryGrid, pixel_boundaries  # noqa: F401
from .geometry import polygon_moments, points_in_polygons, pixel_polygons, locate_points  # noqa: F401,E501
from .config import ChoiceField, Config, ConfigurableField, Field, Struct, Task  # noqa: F401
from .task import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: F401
