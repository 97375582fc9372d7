"""Reading template FITS files: verified HDUs, the bands of a multi-band file, table checks.

Shared by :class:`~lsst_bfdrift.templates.template.DistortionTemplate` (one
template) and :class:`~lsst_bfdrift.templates.bands.MultiBandTemplate`
(one per band).
"""

import os
import warnings

import numpy as np
from astropy.io import fits
from astropy.table import Table

from lsst_bfdrift.physics.depth import normalize_band
from lsst_bfdrift.utils.errors import InputNotFoundError, InputTypeError, TemplateFileError
from lsst_bfdrift.utils.io import astropy_message, not_fits_reason

__all__ = ["read_template_fits", "template_file_bands", "check_template_table", "band_key"]


def band_key(source):
    """Name of a band or wavelength in a multi-band template file.

    An LSST band gives its letter
    (:func:`~lsst_bfdrift.physics.depth.normalize_band`: ``'r'``, ``'r_57'``,
    ``'LSST_r'``); a wavelength (nm, a number, an astropy Quantity or
    ``'700nm'``) gives e.g. ``'700nm'``.
    """
    if isinstance(source, str):
        s = source.strip().lower()
        if s.endswith("nm"):
            try:
                return f"{float(s[:-2]):g}nm"
            except ValueError:
                pass
        return normalize_band(source)
    if hasattr(source, "unit"):
        import astropy.units as u

        source = source.to_value(u.nm, equivalencies=u.spectral())
    if isinstance(source, bool) or not isinstance(source, (int, float, np.number)):
        raise InputTypeError(f"a band name or a wavelength in nm is needed, got {source!r}")
    return f"{float(source):g}nm"


def read_template_fits(path):
    """Read and verify a template FITS file: ``(path, {EXTNAME: (header, data)})``.

    Every HDU's checksum is verified; tables are astropy Tables, images
    float64 arrays, the primary is under ``'PRIMARY'``. Raises
    TemplateFileError (InputNotFoundError for a missing file), naming it.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputNotFoundError(f"template file {path} does not exist")
    if os.path.isdir(path):
        raise TemplateFileError(f"{path}: is a directory; accepted: a template FITS file")
    reason = not_fits_reason(path)
    if reason is not None:
        raise TemplateFileError(f"{path}: cannot read template file: {reason}; accepted: "
                                "a template FITS file (bfdrift template build, "
                                "import-galsim)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            # open the file ourselves so that it is closed even when
            # astropy raises while reading (corrupt or truncated files)
            with open(path, "rb") as fh, fits.open(fh, memmap=False, checksum=True) as hdul:
                hdul.verify("exception")
                out = {"PRIMARY": (hdul[0].header.copy(), None)}
                for h in hdul[1:]:
                    data = Table(h.data) if isinstance(h, fits.BinTableHDU) else \
                        np.array(h.data, dtype=np.float64)
                    out[h.name] = (h.header.copy(), data)
    except Exception as exc:  # astropy raises many kinds for broken files
        raise TemplateFileError(f"{path}: cannot read template file "
                                f"({astropy_message(exc)})") from exc
    return path, out


def template_file_bands(path, hdus):
    """Bands of a multi-band template file (from its primary ``BFBANDS``), () for one band."""
    raw = hdus["PRIMARY"][0].get("BFBANDS")
    if raw is None:
        return ()
    if not isinstance(raw, str) or not raw.strip():
        raise TemplateFileError(f"{path}: BFBANDS is {raw!r}; accepted: comma-separated band "
                                "names", path)
    return tuple(b.strip() for b in raw.split(","))


#: Columns of the TEMPLATE table (see :meth:`DistortionTemplate.to_table`).
_TABLE_COLUMNS = ("di", "dj", "edge", "c0x", "c0y", "c1x", "c1y", "normal", "tangent")


def check_template_table(path, table, meta):
    """Refuse a checksum-valid but malformed template file, naming it."""
    if not isinstance(meta, dict):
        raise TemplateFileError(f"BFMETA is JSON but not an object ({type(meta).__name__}); "
                                "accepted: a JSON object", path)
    missing = [c for c in _TABLE_COLUMNS if c not in table.colnames]
    if missing:
        raise TemplateFileError(f"TEMPLATE table lacks column(s) {missing}; accepted: columns "
                                f"{list(_TABLE_COLUMNS)}", path)
    if len(table) == 0:
        raise TemplateFileError("TEMPLATE table has no rows; accepted: 4 rows (edges) per "
                                "pixel of an N x N neighbourhood", path)
    for col in ("di", "dj"):
        try:
            v = np.asarray(table[col], dtype=float)
        except (TypeError, ValueError) as exc:
            raise TemplateFileError(f"column {col!r} is not numeric ({exc})", path) from exc
        bad = ~(np.isfinite(v) & (v == np.round(v)))
        if bad.any():
            raise TemplateFileError(f"column {col!r} holds non-integer pixel offsets (first: "
                                    f"{float(v[bad][0])}); accepted: integer offsets", path)
