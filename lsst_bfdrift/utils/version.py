"""The package's version, read from its installed metadata.

``setup.cfg`` is the one place the version is written; the package, the
FITS cards (``BFVERS``) and the docs read it from here.
"""

from importlib import metadata

__all__ = ["__version__"]

try:
    __version__ = metadata.version("lsst_bfdrift")
except metadata.PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"
