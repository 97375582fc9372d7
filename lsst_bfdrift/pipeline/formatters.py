"""Butler formatters of the package's storage classes (FITS files, no afw).

``BfdriftExposure`` is an exposure in the LSST Exposure FITS layout (empty
primary, ``IMAGE``, ``MASK`` with ``MP_*`` plane cards, ``VARIANCE``, any
further HDUs kept), held in memory as
:class:`~lsst_bfdrift.images.exposure.MaskedExposure`. ``BfdriftGeometryMaps``
is a dict of 2-d maps (``AREA``, ``CENTROID_X``, ...), one image HDU each.
Both are declared in ``butler_seed.yaml``.
"""

import numpy as np
from astropy.io import fits
from lsst.daf.butler import FormatterV2

from lsst_bfdrift.images.exposure import MaskedExposure, read_exposure, write_exposure
from lsst_bfdrift.utils.errors import InputTypeError
from lsst_bfdrift.utils.io import open_fits

__all__ = ["ExposureFormatter", "GeometryMapsFormatter", "read_maps", "write_maps"]


class ExposureFormatter(FormatterV2):
    """Read and write :class:`~lsst_bfdrift.images.exposure.MaskedExposure` as FITS."""

    default_extension = ".fits"
    supported_extensions = frozenset({".fits"})
    can_read_from_local_file = True

    def read_from_local_file(self, path, component=None, expected_size=-1):
        return read_exposure(path)

    def write_local_file(self, in_memory_dataset, uri):
        if not isinstance(in_memory_dataset, MaskedExposure):
            raise InputTypeError("BfdriftExposure datasets are MaskedExposure objects, got "
                                 f"{type(in_memory_dataset).__name__}")
        write_exposure(uri.ospath, in_memory_dataset, overwrite=True)


def write_maps(path, maps):
    """Write a dict of 2-d maps (and scalar header values) as FITS.

    Parameters
    ----------
    path : str
    maps : dict
        Name -> 2-d array (one image HDU each, ``EXTNAME`` = name upper-cased)
        or scalar (a card of the primary header).
    """
    if not isinstance(maps, dict):
        raise InputTypeError(f"geometry maps are a dict of arrays, got {type(maps).__name__}")
    primary = fits.PrimaryHDU()
    hdus = [primary]
    for name, value in maps.items():
        if np.ndim(value) == 2:
            hdus.append(fits.ImageHDU(np.asarray(value), name=name.upper()))
        else:
            primary.header[f"HIERARCH {name.upper()}"] = value
    fits.HDUList(hdus).writeto(path, overwrite=True, checksum=True)


def read_maps(path):
    """Read what :func:`write_maps` wrote: a dict name (lower case) -> array or value."""
    out = {}
    with open_fits(path) as hdul:
        for key in hdul[0].header:
            if key not in ("SIMPLE", "BITPIX", "NAXIS", "EXTEND", "CHECKSUM", "DATASUM"):
                out[key.lower()] = hdul[0].header[key]
        for hdu in hdul[1:]:
            out[hdu.name.lower()] = np.array(hdu.data)
    return out


class GeometryMapsFormatter(FormatterV2):
    """Read and write the geometry maps (a dict of 2-d arrays) as FITS."""

    default_extension = ".fits"
    supported_extensions = frozenset({".fits"})
    can_read_from_local_file = True

    def read_from_local_file(self, path, component=None, expected_size=-1):
        return read_maps(path)

    def write_local_file(self, in_memory_dataset, uri):
        write_maps(uri.ospath, in_memory_dataset)
