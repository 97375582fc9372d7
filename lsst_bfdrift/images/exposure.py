"""Exposure files in and out: the LSST Exposure layout, astropy CCDData files, plain images.

:func:`read_exposure` reads a FITS file into a :class:`MaskedExposure`, which
keeps every HDU of the file; :func:`write_exposure` writes it back in the same
layout, with the image (and mask and variance) replaced and any extra HDUs
appended. Nothing of the input is dropped.

Layouts (checked against lsst.afw's Exposure FITS writer, see
``docs/pipelines.rst``):

``lsst``
    HDU 0 an empty primary; ``IMAGE``; ``MASK`` (integer bit planes, declared
    by ``MP_<NAME> = bit`` cards in its header); ``VARIANCE``; further HDUs
    (archive tables: PSF, WCS, ...) kept verbatim. Found by the ``IMAGE``
    extension name.
``ccddata``
    What ``astropy.nddata.CCDData.write`` produces: the image in the primary
    HDU, a ``MASK`` extension (0/1) and an ``UNCERT`` extension (with its
    ``UTYPE``). The boolean mask is one plane, read as ``BAD``.
``plain``
    The first 2-d image HDU of the file (a compressed image HDU too); its
    other HDUs are kept as they are.

A file with several image HDUs in none of these layouts (a raw file with one
HDU per amplifier) is refused: the package corrects assembled, post-ISR
images. The extensions ``bfdrift correct`` appends (``FLUX_MOVED``,
``BFFLAGS``, the geometry maps, see :data:`PRODUCT_HDUS`) are not counted as
images, so an output file reads back in its layout.

Mask planes are declared as afw declares them: ``MP_<NAME> = bit`` in the
MASK header, and (newer afw) ``MPD_<NAME> = 'description'``; both are read
and written back. Header metadata of an LSST layout lives in the primary
header when the image HDU has ``INHERIT = T`` (afw's ExposureFitsReader reads
it from there), else in the image header (:meth:`MaskedExposure.metadata`).
"""

import copy
import dataclasses
import os

import numpy as np
from astropy.io import fits
from astropy.nddata import bitfield_to_boolean_mask

from lsst_bfdrift.utils.errors import InputError, InputFileError
from lsst_bfdrift.utils.io import atomic_output, hdu_pixels, open_fits

__all__ = ["MaskedExposure", "read_exposure", "write_exposure", "read_image", "plane_mask",
           "plane_pixels", "add_mask_plane", "header_value", "undeclared_bits", "is_afw_like",
           "fits_header", "BLOCKING_PLANES", "PRODUCT_HDUS"]

#: Mask planes that block the flux exchange by default (LSST's ISR choice).
BLOCKING_PLANES = ("SAT", "BAD", "NO_DATA", "SUSPECT", "UNMASKEDNAN")

#: Extension names of the products ``bfdrift correct`` appends to its outputs
#: (not counted as images of the exposure when a file is read).
PRODUCT_HDUS = ("FLUX_MOVED", "BFFLAGS", "AREA", "CENTROID_X", "CENTROID_Y", "E1", "E2")


@dataclasses.dataclass
class MaskedExposure:
    """An image with its mask planes, variance and every HDU of its file.

    Attributes
    ----------
    image : ndarray
        The 2-d image (its file's dtype: e or ADU, see :meth:`unit`).
    mask : ndarray of int32 or None
        Bit planes, or None without a mask.
    mask_planes : dict
        Plane name -> bit number (the ``MP_*`` cards; ``{'BAD': 0}`` for a
        CCDData boolean mask).
    mask_plane_docs : dict
        Plane name -> description (afw's ``MPD_*`` cards), where given.
    variance : ndarray or None
        Per-pixel variance (image units squared), or None. A CCDData ``UNCERT``
        extension of standard deviations is held here squared.
    header : astropy.io.fits.Header
        The image HDU's header.
    primary_header : astropy.io.fits.Header
        HDU 0's header (the image header itself for 'ccddata' and a primary
        image).
    layout : str
        'lsst', 'ccddata' or 'plain'.
    hdus : list
        Copies of every HDU of the file, in order (written back by
        :func:`write_exposure` with the arrays above put in place).
    image_index, mask_index, variance_index : int or None
        Positions of those HDUs in ``hdus``.
    path : str or None
        The file read.
    """

    image: np.ndarray
    mask: np.ndarray = None
    mask_planes: dict = dataclasses.field(default_factory=dict)
    mask_plane_docs: dict = dataclasses.field(default_factory=dict)
    variance: np.ndarray = None
    header: object = None
    primary_header: object = None
    layout: str = "plain"
    hdus: list = dataclasses.field(default_factory=list)
    image_index: int = 0
    mask_index: int = None
    variance_index: int = None
    path: str = None

    def header_value(self, key, default=None):
        """``key`` from the image header, else the primary header (LSST's INHERIT)."""
        return header_value(key, self.header, self.primary_header, default=default)

    def unit(self):
        """BUNIT of the image (else ``LSST ISR UNITS``), lower case; '' when neither."""
        return str(self.header_value("BUNIT", self.header_value("LSST ISR UNITS", "")) or
                   "").strip().lower()

    def metadata(self):
        """The header that holds the exposure's metadata, as afw reads it.

        The primary header when the image HDU says ``INHERIT = T`` (afw writes
        everything but the WCS there; ExposureFitsReader reads it from there),
        else the image header (CCDData and plain files, and old afw files).
        Keys the Task writes (``LSST ISR BF APPLIED``, ``BF*``) go here.
        """
        if self.primary_header is not None and self.header is not None and \
                self.header.get("INHERIT") is True and self.image_index != 0:
            return self.primary_header
        return self.header

    def copy(self):
        """A deep copy (arrays, headers and HDUs)."""
        return copy.deepcopy(self)


def header_value(key, *headers, default=None):
    """The first value of ``key`` in ``headers`` (None headers skipped)."""
    for h in headers:
        if h is not None and key in h:
            return h[key]
    return default


def fits_header(meta):
    """A FITS header of the values of ``meta`` that FITS can hold.

    Values FITS cannot store (NaN or inf, lists, dicts, non-ASCII text) are
    left out of the header (the Task's output keeps them in its meta); keys
    longer than 8 characters become HIERARCH cards.
    """
    header = fits.Header()
    if not meta:
        return header
    items = meta.cards if isinstance(meta, fits.Header) else \
        [(k, v, None) for k, v in dict(meta).items()]
    for item in items:
        key, value = (item.keyword, item.value) if isinstance(item, fits.Card) else item[:2]
        name = f"HIERARCH {key}" if len(str(key)) > 8 or " " in str(key) else str(key)
        try:
            card = fits.Card(name, value)
            card.verify("exception")
            str(card)  # formats the value: raises on what FITS cannot hold
        except (ValueError, TypeError, fits.VerifyError):
            continue
        header.append(card)
    return header


def plane_mask(mask, planes, names):
    """Boolean mask of the pixels with any of the planes ``names`` set.

    Parameters
    ----------
    mask : ndarray of int
        Bit planes.
    planes : dict
        Plane name -> bit.
    names : sequence of str
        Planes to select; names absent from ``planes`` are skipped.

    Returns
    -------
    ndarray of bool
    """
    bits = [1 << int(planes[n]) for n in names if n in planes]
    if mask is None or not bits:
        return None if mask is None else np.zeros(mask.shape, bool)
    return bitfield_to_boolean_mask(mask, ignore_flags=bits, flip_bits=True,
                                    good_mask_value=False)


def is_afw_like(obj):
    """An object with the shape of an lsst.afw.image.Exposure."""
    return all(hasattr(obj, a) for a in ("image", "mask", "getMetadata")) and \
        hasattr(obj.image, "array") and hasattr(obj.mask, "getMaskPlaneDict")


def plane_pixels(exposure, names):
    """Pixels of an exposure with bit planes that have any of the planes ``names`` set.

    Parameters
    ----------
    exposure : MaskedExposure or lsst.afw.image.Exposure-like
        Other inputs (arrays, NDData, masked arrays) have no named planes.
    names : sequence of str
        Plane names (e.g. ``('SAT',)``).

    Returns
    -------
    ndarray of bool or None
        None when the exposure has no bit-plane mask or defines none of
        ``names``.
    """
    if isinstance(exposure, MaskedExposure):
        mask, planes = exposure.mask, exposure.mask_planes
    elif is_afw_like(exposure):
        mask, planes = np.asarray(exposure.mask.array), exposure.mask.getMaskPlaneDict()
    else:
        return None
    if mask is None or not any(n in planes for n in names):
        return None
    return plane_mask(mask, planes, names)


def undeclared_bits(mask, planes):
    """Bits set in ``mask`` that no plane of ``planes`` declares.

    Parameters
    ----------
    mask : ndarray of int or None
    planes : dict
        Plane name -> bit.

    Returns
    -------
    list of int
        Sorted bit numbers (empty without a mask).
    """
    if mask is None or mask.size == 0:
        return []
    used = int(np.bitwise_or.reduce(mask.astype(np.int64), axis=None))
    declared = {int(b) for b in planes.values()}
    return [b for b in range(63) if used >> b & 1 and b not in declared]


def add_mask_plane(exposure, name, doc=None):
    """Declare plane ``name`` in ``exposure``; its bit.

    The plane takes the lowest bit that no plane declares and no pixel of the
    mask sets (an undeclared bit that is set belongs to somebody: it is never
    reused). A plane already declared keeps its bit.

    Parameters
    ----------
    exposure : MaskedExposure
    name : str
    doc : str, optional
        Description, written as the ``MPD_<name>`` card (afw's convention).

    Returns
    -------
    int

    Raises
    ------
    InputError
        All 31 usable bits of the int32 mask are taken.
    """
    if doc:
        exposure.mask_plane_docs[name] = doc
    if name in exposure.mask_planes:
        return int(exposure.mask_planes[name])
    used = set(int(b) for b in exposure.mask_planes.values())
    used.update(undeclared_bits(exposure.mask, exposure.mask_planes))
    free = [b for b in range(31) if b not in used]
    if not free:
        raise InputError(f"no free bit in the mask for plane {name!r}: bits 0-30 are all "
                         f"declared or set ({sorted(exposure.mask_planes)})")
    exposure.mask_planes[name] = free[0]
    return free[0]


def _is_image(hdu):
    return hdu.is_image and hdu.header.get("NAXIS") == 2 and \
        all(int(hdu.header.get(f"NAXIS{k}", 0) or 0) > 0 for k in (1, 2))


def read_exposure(path):
    """Read a FITS image in the LSST Exposure, CCDData or plain layout.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    MaskedExposure

    Raises
    ------
    InputNotFoundError, InputFileError
        Missing, unreadable or truncated file.
    InputError
        No 2-d image; several image HDUs in no known layout (e.g. one per
        amplifier); a MASK or VARIANCE of another shape than the image; a
        MASK that is not integer.
    """
    path = os.fspath(path)
    with open_fits(path) as hdul:
        names = [h.name.upper() for h in hdul]
        images = [k for k, h in enumerate(hdul) if _is_image(h) and names[k] not in PRODUCT_HDUS]
        if not images:
            raise InputFileError(f"{path}: no 2-d image HDU; accepted: a FITS file with a 2-d "
                                 "image", path)
        if "IMAGE" in names and _is_image(hdul[names.index("IMAGE")]):
            layout, ii = "lsst", names.index("IMAGE")
            mi = names.index("MASK") if "MASK" in names else None
            vi = names.index("VARIANCE") if "VARIANCE" in names else None
        elif images[0] == 0 and ("MASK" in names or "UNCERT" in names):
            layout, ii = "ccddata", 0
            mi = names.index("MASK") if "MASK" in names else None
            vi = names.index("UNCERT") if "UNCERT" in names else None
        else:
            layout, ii, mi, vi = "plain", images[0], None, None
            others = [k for k in images[1:]]
            if others:
                listing = ", ".join(
                    f"{k}: {hdul[k].name or '(no name)'} "
                    f"{hdul[k].header.get('NAXIS2')}x{hdul[k].header.get('NAXIS1')}"
                    for k in images)
                raise InputError(
                    f"{path}: {len(images)} image HDUs ({listing}) in no known layout; "
                    "lsst_bfdrift corrects one assembled, post-ISR image (after bias, dark "
                    "and gain, in electrons): assemble the amplifiers first (LSST ISR), or "
                    "give an Exposure with IMAGE/MASK/VARIANCE extensions")
        image = hdu_pixels(hdul[ii], path, dtype=None)
        mask = variance = None
        planes, docs = {}, {}
        if mi is not None:
            mh = hdul[mi]
            mdata = hdu_pixels(mh, path, dtype=None)
            if mdata.ndim != 2 or mdata.shape != image.shape:
                raise InputError(f"{path}: MASK HDU shape "
                                 f"{mdata.shape} does not match the image {image.shape}")
            if mdata.dtype.kind not in "iub":
                raise InputError(f"{path}: MASK HDU holds {mdata.dtype.name} values; a mask is "
                                 "integer bit planes")
            mask = mdata.astype(np.int32)
            planes = {k[3:]: int(v) for k, v in mh.header.items() if k.startswith("MP_")}
            docs = {k[4:]: str(v) for k, v in mh.header.items() if k.startswith("MPD_")}
            if layout == "ccddata" and not planes:
                planes = {"BAD": 0}
                mask = (mask != 0).astype(np.int32)
        if vi is not None:
            vh = hdul[vi]
            variance = hdu_pixels(vh, path)
            if variance.shape != image.shape:
                raise InputError(f"{path}: {names[vi]} HDU shape {variance.shape} does not "
                                 f"match the image {image.shape}")
            utype = str(vh.header.get("UTYPE", "")).lower()
            if layout == "ccddata" and "stddev" in utype:
                variance = variance ** 2
            elif layout == "ccddata" and "inverse" in utype:
                with np.errstate(divide="ignore"):
                    variance = 1.0 / variance
        try:
            hdus = [_copy_hdu(h) for h in hdul]
        except (ValueError, TypeError, OSError, IndexError) as exc:
            raise InputFileError(f"{path}: truncated or corrupt FITS file: an HDU cannot be "
                                 f"read ({exc}); re-copy or re-write the file", path) from exc
        primary = hdul[0].header.copy()
        return MaskedExposure(image=image, mask=mask, mask_planes=planes, mask_plane_docs=docs,
                              variance=variance,
                              header=hdul[ii].header.copy(), primary_header=primary,
                              layout=layout, hdus=hdus, image_index=ii, mask_index=mi,
                              variance_index=vi, path=path)


def write_exposure(path, exposure, *, extra_hdus=(), overwrite=False, inputs=()):
    """Write ``exposure`` back in its layout, every HDU of its file kept (atomically).

    The image, mask (with its ``MP_*`` cards from ``mask_planes`` and
    ``MPD_*`` cards from ``mask_plane_docs``) and variance replace those of
    the file read, in the same HDUs, dtypes and compression; the image header
    is ``exposure.header`` and an empty primary HDU's header is
    ``exposure.primary_header``; ``extra_hdus`` are appended. An exposure that
    was not read from a file is written in the LSST layout.

    An integer image (e.g. int16 with ``BZERO``) is written as float32: a
    corrected image holds fractions of an electron, and rounding them would
    lose flux (``BZERO``/``BSCALE``/``BLANK`` are dropped from that HDU). Mask
    and variance keep their dtypes.

    Parameters
    ----------
    path : str or path-like
    exposure : MaskedExposure
    extra_hdus : sequence of astropy HDUs, optional
    overwrite : bool, optional
    inputs : sequence of str, optional
        Files the output may not replace.
    """
    hdus = [_copy_hdu(h) for h in exposure.hdus]
    if not hdus:  # built in memory: the LSST layout
        hdus = [fits.PrimaryHDU(header=exposure.primary_header),
                fits.ImageHDU(exposure.image, name="IMAGE")]
        exposure = dataclasses.replace(exposure, image_index=1, mask_index=None,
                                       variance_index=None)
        if exposure.mask is not None:
            hdus.append(fits.ImageHDU(exposure.mask.astype(np.int32), name="MASK"))
            exposure.mask_index = len(hdus) - 1
        if exposure.variance is not None:
            hdus.append(fits.ImageHDU(exposure.variance.astype(np.float32), name="VARIANCE"))
            exposure.variance_index = len(hdus) - 1
    _put(hdus, exposure.image_index, exposure.image, exposure.header, image=True)
    if exposure.image_index != 0 and exposure.primary_header is not None and \
            isinstance(hdus[0], fits.PrimaryHDU) and hdus[0].data is None:
        # the metadata of an LSST layout (INHERIT) lives in the primary header
        hdus[0] = fits.PrimaryHDU(header=exposure.primary_header.copy())
    if exposure.mask is not None:
        if exposure.mask_index is None:
            hdus.append(fits.ImageHDU(exposure.mask.astype(np.int32), name="MASK"))
            exposure = dataclasses.replace(exposure, mask_index=len(hdus) - 1)
        h = hdus[exposure.mask_index]
        for k in [k for k in h.header if k.startswith("MP_")]:
            del h.header[k]
        for name, bit in sorted(exposure.mask_planes.items(), key=lambda kv: kv[1]):
            h.header[f"MP_{name}" if len(name) <= 5 else f"HIERARCH MP_{name}"] = int(bit)
        for name, doc in exposure.mask_plane_docs.items():
            if name in exposure.mask_planes:
                h.header[f"MPD_{name}" if len(name) <= 4 else f"HIERARCH MPD_{name}"] = doc
        _put(hdus, exposure.mask_index, exposure.mask, None)
    if exposure.variance is not None and exposure.variance_index is not None:
        var = exposure.variance
        utype = str(hdus[exposure.variance_index].header.get("UTYPE", "")).lower()
        if exposure.layout == "ccddata" and "stddev" in utype:
            var = np.sqrt(var)
        elif exposure.layout == "ccddata" and "inverse" in utype:
            with np.errstate(divide="ignore"):
                var = 1.0 / var
        _put(hdus, exposure.variance_index, var, None)
    if not isinstance(hdus[0], (fits.PrimaryHDU,)):
        hdus.insert(0, fits.PrimaryHDU(header=exposure.primary_header))
    hdus.extend(extra_hdus)
    with atomic_output(path, overwrite=overwrite, inputs=inputs) as tmp:
        fits.HDUList(hdus).writeto(tmp, overwrite=True, checksum=True)


def _copy_hdu(hdu):
    """A copy of ``hdu`` (data loaded); a compressed HDU keeps its compression settings,
    which ``CompImageHDU.copy`` resets to astropy's defaults."""
    if isinstance(hdu, fits.CompImageHDU):
        return fits.CompImageHDU(
            np.array(hdu.data), header=hdu.header.copy(), name=hdu.name,
            compression_type=hdu.compression_type,
            tile_shape=tuple(int(t) for t in hdu.tile_shape),
            quantize_level=hdu.quantize_level, quantize_method=hdu.quantize_method,
            dither_seed=hdu.dither_seed, hcomp_scale=hdu.hcomp_scale,
            hcomp_smooth=hdu.hcomp_smooth)
    return hdu.copy()


def _put(hdus, index, array, header, *, image=False):
    """Replace HDU ``index``'s data by ``array`` in the HDU's own dtype (and header);
    a compressed HDU stays compressed with the same settings. With ``image``, an
    integer HDU becomes float32 (the corrected image has fractional values)."""
    hdu = hdus[index]
    old = hdu.data
    dtype = old.dtype.newbyteorder("=") if old is not None else np.asarray(array).dtype
    if image and dtype.kind in "iu":
        dtype = np.dtype(np.float32)
    data = np.asarray(array).astype(dtype, copy=False)
    new_header = hdu.header.copy() if header is None else header.copy()
    if header is not None and "EXTNAME" in hdu.header:
        new_header["EXTNAME"] = hdu.header["EXTNAME"]
    if dtype.kind == "f":
        for key in ("BZERO", "BSCALE", "BLANK"):
            new_header.remove(key, ignore_missing=True)
    if image and not isinstance(hdu, fits.CompImageHDU):
        cls = fits.PrimaryHDU if isinstance(hdu, fits.PrimaryHDU) else fits.ImageHDU
        hdus[index] = cls(data=data, header=new_header)
        return
    if isinstance(hdu, fits.CompImageHDU):
        hdus[index] = fits.CompImageHDU(
            data, header=new_header, name=hdu.name, compression_type=hdu.compression_type,
            tile_shape=tuple(int(t) for t in hdu.tile_shape),
            quantize_level=hdu.quantize_level, quantize_method=hdu.quantize_method,
            dither_seed=hdu.dither_seed, hcomp_scale=hdu.hcomp_scale,
            hcomp_smooth=hdu.hcomp_smooth)
    else:
        hdu.header = new_header
        hdu.data = data


def read_image(path, *, hdu=None):
    """Image (float64 copy), mask and header from a FITS file; NaN/inf are masked.

    Parameters
    ----------
    path : str or path-like
    hdu : int, optional
        HDU to read; default the first one holding a 2-d image.

    Returns
    -------
    data : ndarray
    bad : ndarray of bool
    header : astropy.io.fits.Header

    Raises
    ------
    InputNotFoundError, InputFileError
        See :func:`open_fits` and :func:`hdu_pixels` (a truncated file is
        named as such).
    InputError
        No 2-d image HDU.
    """
    path = os.fspath(path)
    with open_fits(path) as hdul:
        if hdu is None:
            hdu = next((k for k, h in enumerate(hdul) if h.is_image
                        and h.header.get("NAXIS") == 2
                        and all(h.header.get(f"NAXIS{n}", 0) > 0 for n in (1, 2))), None)
            if hdu is None:
                raise InputFileError(f"{path}: no 2-d image HDU; accepted: a FITS file with a "
                                     "2-d image", path)
        data = hdu_pixels(hdul[hdu], path)
        header = hdul[hdu].header.copy()
    return data, ~np.isfinite(data), header
