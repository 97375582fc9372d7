"""Images into electrons: the first step of every route through the package.

Takes any accepted image (a FITS path, an LSST Exposure file, CCDData,
NDData, a MaskedArray, an ndarray or an afw-like Exposure); gives it in
electrons with its bad pixels, metadata, gain and saturation level by one
unit rule, one gain rule and one saturation rule
(:func:`~lsst_bfdrift.images.electrons.to_electrons`), reads and writes the
LSST Exposure layout without losing an HDU, a mask plane or a header
(:mod:`~lsst_bfdrift.images.exposure`), and gives an image's robust levels
and the plateau of a clipped one (:mod:`~lsst_bfdrift.images.levels`).
"""


from lsst_bfdrift.images.exposure import *  # noqa: F401,F403
from lsst_bfdrift.images.levels import *  # noqa: F401,F403
from lsst_bfdrift.images.electrons import *  # noqa: F401,F403
