"""Portable distortion templates.

Takes a sensor model (or GalSim's sensor files); gives the
:class:`DistortionTemplate` of one aggressor pixel (corner and edge-sample
displacements, FITS I/O with checksums), its swept-area operators (the FFT
kernels of the correction) and the import from GalSim. Per-band templates
(conversions at each band's depths) and multi-band files are in
:mod:`~lsst_bfdrift.templates.bands`. GalSim I/O depends on the template,
never the reverse. The build configuration is an
``lsst.pex.config`` Config (:mod:`~lsst_bfdrift.templates.build_config`).
"""


from lsst_bfdrift.templates.template import *  # noqa: F401,F403
from lsst_bfdrift.templates.swept import *  # noqa: F401,F403
from lsst_bfdrift.templates.galsim_io import *  # noqa: F401,F403
from lsst_bfdrift.templates.galsim_export import *  # noqa: F401,F403
from lsst_bfdrift.templates.refine import *  # noqa: F401,F403
from lsst_bfdrift.templates.edge_shifts import *  # noqa: F401,F403
from lsst_bfdrift.templates.build_config import *  # noqa: F401,F403
from lsst_bfdrift.templates.template_io import *  # noqa: F401,F403
from lsst_bfdrift.templates.bands import *  # noqa: F401,F403
