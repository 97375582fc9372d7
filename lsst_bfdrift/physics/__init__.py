"""The electrostatic drift model.

Takes sensor parameters (:class:`SensorParameters`); gives the field terms
(backdrop field, periodic channel-stop and clock dipoles, images, truncated
dipoles, guard ring, bloom stop, charge dipoles), drift lines, the pixel
boundaries found by bisection, pixel polygons with the paper's shoelace
moments, the large fixed patterns (tearing, bamboo, edge roll-off), and
where photons convert (silicon's absorption length at a temperature, the
depth distributions of the bands).
"""


from lsst_bfdrift.physics.fields import *  # noqa: F401,F403
from lsst_bfdrift.physics.sensor import *  # noqa: F401,F403
from lsst_bfdrift.physics.absorption import *  # noqa: F401,F403
from lsst_bfdrift.physics.drift import *  # noqa: F401,F403
from lsst_bfdrift.physics.depth import *  # noqa: F401,F403
from lsst_bfdrift.physics.boundaries import *  # noqa: F401,F403
from lsst_bfdrift.physics.polygons import *  # noqa: F401,F403
from lsst_bfdrift.physics.features import *  # noqa: F401,F403
from lsst_bfdrift.physics.patterns import *  # noqa: F401,F403
