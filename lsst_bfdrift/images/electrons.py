"""Any accepted image into electrons: one unit rule, one gain rule, one saturation rule.

Every command and function that takes an image (``bfdrift correct``,
``maps``, ``validate-sky``, ``calibrate --stars``, the Task, the star
catalogs) reads it with :func:`to_electrons`; the flats of ``bfdrift ptc``
and ``calibrate`` are read with the same unit rule (:func:`image_unit`) and
measure their gain instead of requiring one.

The unit rule
-------------
1. **A stated unit wins.** ``BUNIT`` (else ``LSST ISR UNITS``) of a file or
   exposure, the unit of a CCDData or NDData: electrons (``electron``,
   ``electrons``, ``e``, ``e-``) or ADU (``adu``, ``dn``, ``count``,
   ``counts``), in any case; any other unit (e/s, MJy/sr, ...) is refused.
2. **A gain means ADU.** Without a stated unit, a gain given by the caller
   (``--gain``, ``config.gain``, ``gain=``) or a ``GAIN`` keyword makes the
   image ADU with that gain (the caller's first). A gain given for an image
   that states electrons is refused (one of the two is wrong); a ``GAIN``
   keyword in an image that states electrons is ignored (ISR records gains
   in electron images).
3. **A file that says neither is ADU with an unknown gain**, as raw images
   are: ``ptc`` and ``calibrate`` measure the gain from the flats; the
   commands that need electrons refuse it and name the two ways to state it
   (a gain, or ``BUNIT = 'electron'``; ``--gain 1`` says the same).
4. **An in-memory image without metadata** (ndarray, MaskedArray, NDData
   without unit or GAIN, an afw Exposure without ``LSST ISR UNITS``: post-ISR
   by LSST's convention) is in electrons.

The saturation rule
-------------------
The level (in the image's own unit, converted with the gain) is the one
given by the caller (``--saturation``, ``config.saturation``,
``saturation=``), else the ``SATURATE`` keyword; it must be a positive
finite number, and a boolean or text is refused. Without either, an image
clipped at one level (:func:`~lsst_bfdrift.images.levels.plateau_level`: a
flat top shared by several pixels, 10 sigma above the sky) gives it, with a
warning; else there is none. Pixels at or above the level are saturated.
"""

import dataclasses
import math
import os
import warnings as _warnings

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.nddata import CCDData, NDData
from astropy.utils.exceptions import AstropyUserWarning

from lsst_bfdrift.images.exposure import (BLOCKING_PLANES, MaskedExposure, fits_header,
                                          is_afw_like, plane_mask, plane_pixels, read_exposure,
                                          undeclared_bits)
from lsst_bfdrift.images.levels import plateau_level, plateau_warning
from lsst_bfdrift.utils.errors import InputError

__all__ = ["ImageUnit", "ElectronImage", "image_unit", "gain_value", "saturation_level",
           "to_electrons", "as_float64", "refuse_corrected", "ELECTRON_UNITS", "ADU_UNITS",
           "CORRECTED_KEYS"]

#: BUNIT spellings of a charge image in electrons (compared in lower case).
ELECTRON_UNITS = ("electron", "electrons", "e", "e-")
#: BUNIT spellings of an image in ADU (compared in lower case).
ADU_UNITS = ("adu", "dn", "count", "counts")

#: Keys that say an image was already corrected for the brighter-fatter effect
#: (ip_isr's, then the package's own).
CORRECTED_KEYS = ("LSST ISR BF APPLIED", "BFDRIFT")


@dataclasses.dataclass(frozen=True)
class ImageUnit:
    """The unit of an image as :func:`image_unit` decides it.

    Attributes
    ----------
    unit : str
        ``'electron'`` or ``'adu'``.
    gain : float or None
        e/ADU that converts the image to electrons (1 for electrons); None
        for ADU with an unknown gain (a file that states neither).
    origin : str
        Where the unit came from: ``'BUNIT'`` (a stated unit: BUNIT, LSST
        ISR UNITS or an NDData unit), ``'gain'`` (a gain given or a GAIN
        keyword), ``'none'`` (a file that says neither) or ``'memory'``
        (an in-memory image without metadata).
    note : str
        One sentence that says so, for logs and reports.
    """

    unit: str
    gain: float | None
    origin: str
    note: str

    @property
    def known(self):
        """Whether the image can be converted to electrons (its gain is known)."""
        return self.gain is not None


def gain_value(gain, *, what="gain"):
    """A gain as float e/ADU: a positive finite number or an astropy Quantity in
    electron/adu (None stays None).

    Parameters
    ----------
    gain : float, Quantity or None
    what : str, optional
        How the message names the value (``'--gain'``, ``'config.gain'``, ``'GAIN
        keyword'``).

    Raises
    ------
    InputError
        Not a number (a boolean or text too), not in electron/adu, or not
        positive and finite.
    """
    if gain is None:
        return None
    if isinstance(gain, u.Quantity):
        try:
            gain = float(gain.to_value(u.electron / u.adu))
        except u.UnitConversionError:
            raise InputError(f"{what} {gain} is not in electron/adu") from None
    if isinstance(gain, (bool, np.bool_)) or not isinstance(gain, (int, float, np.number)):
        raise InputError(f"{what} {gain!r} is not a number of e/ADU; accepted: a positive "
                         "finite gain in e/ADU")
    gain = float(gain)
    if not (math.isfinite(gain) and gain > 0):
        raise InputError(f"{what} {gain} is not positive and finite; accepted: a positive "
                         "finite gain in e/ADU")
    return gain


def _unit_name(stated):
    """A stated unit (str, astropy unit or None) as a lower-case name ('' when none)."""
    if stated is None:
        return ""
    if isinstance(stated, u.UnitBase):
        if stated == u.dimensionless_unscaled:
            return ""
        if stated == u.electron:
            return "electron"
        if stated in (u.adu, u.count):
            return "adu"
        return stated.to_string()
    return str(stated).strip().lower()


def image_unit(stated=None, *, gain=None, header_gain=None, from_file=True, source="image",
               gain_name="gain"):
    """The unit of an image and the gain that converts it to electrons (the unit rule).

    Parameters
    ----------
    stated : str, astropy unit or None
        The unit the image states: ``BUNIT`` (else ``LSST ISR UNITS``), or a
        CCDData/NDData unit; None or '' when it states none.
    gain : float or Quantity, optional
        A gain given by the caller (e/ADU).
    header_gain : object, optional
        The image's ``GAIN`` keyword, if any (checked here).
    from_file : bool, optional
        Whether the image comes with a header that could state its unit (a
        file, an exposure read from one). Without a unit or a gain such an
        image is ADU with an unknown gain; an in-memory image is electrons.
    source : str, optional
        The image's name in messages (a path).
    gain_name : str, optional
        How messages name ``gain`` (``'--gain'``, ``'config.gain'``).

    Returns
    -------
    ImageUnit

    Raises
    ------
    InputError
        An unknown unit, a gain given for an image that states electrons, or
        a gain that is not a positive number.
    """
    given = gain_value(gain, what=gain_name)
    name = _unit_name(stated)
    if name in ELECTRON_UNITS:
        if given is not None:
            raise InputError(f"{source}: a gain of {given:g} e/ADU was given ({gain_name}) but "
                             f"the image states it is in electrons (BUNIT or unit "
                             f"{stated!s}); drop the gain, or fix the unit if the image is in "
                             "ADU")
        return ImageUnit("electron", 1.0, "BUNIT", f"BUNIT {stated!s}: electrons")
    if name and name not in ADU_UNITS:
        raise InputError(f"{source}: BUNIT = {stated!s} is not a charge image; accepted: "
                         "electron (e, e-, electrons) or ADU (adu, dn, count)")
    keyword = None if header_gain is None else gain_value(header_gain, what=f"{source}: GAIN "
                                                                            "keyword")
    g = given if given is not None else keyword
    how = (f"{gain_name} {g:g} e/ADU" if given is not None else
           f"GAIN keyword {g:g} e/ADU" if g is not None else "")
    if name:  # stated ADU
        return ImageUnit("adu", g, "BUNIT",
                         f"BUNIT {stated!s}: ADU, " + (how if g is not None else "gain unknown"))
    if g is not None:
        return ImageUnit("adu", g, "gain", f"no BUNIT: ADU, as the {how} says")
    if from_file:
        return ImageUnit("adu", None, "none",
                         "no BUNIT and no gain: ADU with an unknown gain, as raw images are")
    return ImageUnit("electron", 1.0, "memory",
                     "an in-memory image without a unit or gain: electrons")


def _require_gain(unit, source, gain_name):
    """Refuse an image whose gain is unknown where electrons are needed."""
    if unit.gain is None:
        if unit.origin == "BUNIT":
            raise InputError(f"{source}: the image is in ADU (BUNIT) and no gain is known: give "
                             f"one ({gain_name}, or a GAIN keyword)")
        raise InputError(f"{source}: the image states no unit (no BUNIT or LSST ISR UNITS) and "
                         f"no gain (no GAIN keyword, no {gain_name}), so it is ADU with an "
                         f"unknown gain, as raw images are, and cannot be converted to "
                         f"electrons. Give the gain ({gain_name} G, in e/ADU) or, for an "
                         "image already in electrons, set BUNIT = 'electron' in its header "
                         f"(or give {gain_name} 1)")


def saturation_level(data, bad=None, *, saturation=None, header=None, gain=1.0,
                     source="image", saturation_name="saturation"):
    """The saturation level of an image in electrons (the saturation rule).

    Parameters
    ----------
    data : ndarray
        The image in electrons (non-finite pixels are skipped by the plateau
        search when ``bad`` marks them).
    bad : ndarray of bool, optional
        Pixels left out of the plateau search.
    saturation : float, optional
        The level given by the caller, in the image's own unit.
    header : mapping, optional
        Its ``SATURATE`` keyword is the level when none is given.
    gain : float, optional
        e per unit of the image (1 for electrons).
    source, saturation_name : str, optional
        Names used in messages.

    Returns
    -------
    level : float or None
        e; None when no level is given, stated or found.
    origin : str or None
        ``'given'``, ``'SATURATE'``, ``'plateau'`` or None.
    warning : str or None
        For a plateau: how many pixels share it and how to state the level.

    Raises
    ------
    InputError
        A given or stated level that is not a positive finite number (a
        boolean or text too).
    """
    origin, level = None, None
    if saturation is not None:
        origin, level, name = "given", saturation, saturation_name
    elif header is not None and "SATURATE" in header:
        origin, level, name = "SATURATE", header["SATURATE"], f"{source}: SATURATE keyword"
    if origin is not None:
        if isinstance(level, (bool, np.bool_)) or not isinstance(level, (int, float, np.number)) \
                or not (math.isfinite(float(level)) and float(level) > 0):
            raise InputError(f"{name} {level!r} is not a positive level; accepted: a positive "
                             "finite saturation level in the image's unit (e or ADU)")
        return float(level) * gain, origin, None
    found = plateau_level(data, bad)
    if found is None:
        return None, None, None
    return found, "plateau", plateau_warning(
        data, found, f"they are taken as saturated (give {saturation_name} or a SATURATE "
                     "keyword to state the level)")


def as_float64(array):
    """``array`` as float64, a copy only if the dtype differs.

    Nothing below writes into it (the caller's data are never modified;
    checked by ``tests/correction/test_task.py::test_input_untouched_and_not_aliased``).
    It is not made read-only: numba compiles read-only arrays as another
    type, which would double the kernels' compilations. Integer and float
    images are accepted; boolean, complex and non-numeric ones are refused.
    """
    array = np.asarray(array)
    if array.dtype.kind not in "iuf":
        what = {"b": "boolean", "c": "complex"}.get(array.dtype.kind,
                                                    f"non-numeric ({array.dtype})")
        raise InputError(f"exposure data must be real numbers (e or ADU), got a {what} array")
    return array.astype(np.float64, copy=False)


def _afw_metadata(exposure):
    md = exposure.getMetadata()
    return md.toDict() if hasattr(md, "toDict") else dict(md or {})


def refuse_corrected(exposure, meta=None, source="exposure"):
    """Refuse an image whose metadata says the BF correction was already applied
    (``LSST ISR BF APPLIED = T`` from ip_isr, ``BFDRIFT = T`` from this
    package): a second correction would double it, silently.

    Parameters
    ----------
    exposure : object
        The input (its own metadata is read: an exposure's primary header, an
        afw metadata, an NDData's meta).
    meta : mapping, optional
        Metadata of other inputs.
    source : str, optional
        The image's name in the message.
    """
    if isinstance(exposure, MaskedExposure):
        def get(key):
            return exposure.header_value(key)
        source = exposure.path or source
    elif is_afw_like(exposure):
        get = _afw_metadata(exposure).get
    elif isinstance(exposure, NDData) and exposure.meta:
        get = dict(exposure.meta).get
    else:
        def get(key):
            return meta.get(key) if meta is not None else None
    for key in CORRECTED_KEYS:
        value = get(key)
        if value is True or (isinstance(value, str) and value.strip().upper() in ("T", "TRUE")):
            how = get("LSST ISR BF CORR METHOD") or get("BFMETHOD")
            raise InputError(
                f"{source}: already corrected for the brighter-fatter effect ({key} = True"
                + (f", method {how}" if how else "") + "); a second correction would double "
                "it. Give the image from before the BF step (ip_isr: doBrighterFatter=False), "
                f"or remove {key} if the header is wrong")


@dataclasses.dataclass
class ElectronImage:
    """An image read by :func:`to_electrons`.

    Attributes
    ----------
    data : ndarray
        float64 electrons (the input's own array when it was float64 in
        electrons: never write into it). Non-finite pixels are kept as they
        are (see ``bad``).
    mask : ndarray of bool or None
        The input's own mask: an NDData/MaskedArray mask, or the blocking
        planes of a bit-plane mask (MaskedExposure, afw Exposure).
    bad : ndarray of bool
        ``mask``, the non-finite pixels and the caller's extra mask.
    uncertainty : object or None
        An NDData's uncertainty, carried to outputs.
    meta : astropy.io.fits.Header
        The metadata FITS can hold (``GAIN`` and ``SATURATE`` inherited from a
        primary header).
    unit : ImageUnit
    gain : float
        e/ADU applied (1 for electrons).
    kind : str
        ``'path'``, ``'exposure'`` (MaskedExposure), ``'afw'``, ``'ccddata'``,
        ``'nddata'``, ``'masked'`` or ``'ndarray'``.
    source : str
        The path, or ``'exposure'``.
    saturation : float or None
        Level in electrons (:func:`saturation_level`).
    saturation_origin : str or None
    saturated : ndarray of bool or None
        Finite pixels at or above the level (None without a level).
    sat_plane : ndarray of bool or None
        Pixels of the SAT plane of a bit-plane mask (saturated pixels that ISR
        may have interpolated over).
    exposure : object
        The input as read (a path becomes its MaskedExposure).
    warnings : list of str
        What looks wrong and was accepted: a plateau taken as saturation, mask
        bits no plane declares.
    """

    data: np.ndarray
    mask: np.ndarray
    bad: np.ndarray
    uncertainty: object
    meta: fits.Header
    unit: ImageUnit
    gain: float
    kind: str
    source: str
    saturation: float = None
    saturation_origin: str = None
    saturated: np.ndarray = None
    sat_plane: np.ndarray = None
    exposure: object = None
    warnings: list = dataclasses.field(default_factory=list)

    @property
    def astropy_unit(self):
        """The image's unit as an astropy unit (adu or electron)."""
        return u.adu if self.unit.unit == "adu" else u.electron

    def warn(self):
        """Issue each of ``warnings`` as an AstropyUserWarning (the catalogs' way;
        the Task logs them instead)."""
        for message in self.warnings:
            _warnings.warn(message, AstropyUserWarning, stacklevel=3)


def _unpack(exposure):
    """(data array, own mask or None, uncertainty, meta Header, stated unit, from_file,
    kind, source, bit mask and planes or None) of any accepted input."""
    kind, source, unc, bits = "ndarray", "exposure", None, None
    if isinstance(exposure, (str, os.PathLike)):
        source = os.fspath(exposure)
        exposure = read_exposure(exposure)  # a truncated file is named as such
        kind = "path"
    if isinstance(exposure, MaskedExposure):
        kind = "path" if kind == "path" else "exposure"
        source = exposure.path or source
        data = exposure.image
        bits = (exposure.mask, exposure.mask_planes)
        meta = fits.Header(exposure.header)
        for key in ("GAIN", "SATURATE", "BAND", "FILTER"):
            if key not in meta and exposure.header_value(key) is not None:
                meta[key] = exposure.header_value(key)  # INHERIT from the primary
        stated, from_file, mask = exposure.unit(), True, None
    elif is_afw_like(exposure):
        kind = "afw"
        data = exposure.image.array
        bits = (np.asarray(exposure.mask.array), exposure.mask.getMaskPlaneDict())
        md = _afw_metadata(exposure)
        meta = fits.Header({k: v for k, v in md.items() if isinstance(v, (int, float, str, bool))
                            and len(k) <= 8})
        stated = str(md.get("LSST ISR UNITS", md.get("BUNIT", ""))).strip().lower()
        from_file, mask = False, None
    elif isinstance(exposure, NDData):
        kind = "ccddata" if isinstance(exposure, CCDData) else "nddata"
        data = exposure.data
        mask = None if exposure.mask is None else np.array(exposure.mask, bool)
        unc = exposure.uncertainty
        meta = fits_header(exposure.meta)
        stated = exposure.unit if exposure.unit is not None else meta.get("BUNIT")
        from_file = False
    elif isinstance(exposure, np.ma.MaskedArray):
        kind = "masked"
        data = exposure.data
        mask = np.array(np.ma.getmaskarray(exposure), bool)
        meta, stated, from_file = fits.Header(), None, False
    else:
        data, mask, meta, stated, from_file = exposure, None, fits.Header(), None, False
    return exposure, data, mask, unc, meta, stated, from_file, kind, source, bits


def to_electrons(exposure, *, gain=None, saturation=None, mask=None, blocking=BLOCKING_PLANES,
                 refuse_bf_corrected=True, gain_name="gain", saturation_name="saturation"):
    """Any accepted image in electrons, with its mask, metadata and saturation.

    Parameters
    ----------
    exposure : str, path-like, MaskedExposure, afw Exposure, CCDData, NDData, MaskedArray or ndarray
        The image, by the unit rule of this module. Never modified.
    gain : float or Quantity, optional
        e/ADU given by the caller: the image is in ADU.
    saturation : float, optional
        Saturation level in the image's own unit (the saturation rule).
    mask : array_like of bool, optional
        Extra bad pixels (True = bad), the image's shape.
    blocking : sequence of str, optional
        Planes of a bit-plane mask that make a pixel bad.
    refuse_bf_corrected : bool, optional
        Refuse an image already corrected for the brighter-fatter effect
        (:func:`refuse_corrected`).
    gain_name, saturation_name : str, optional
        How messages name the caller's options (``'--gain'``, ``'config.gain'``).

    Returns
    -------
    ElectronImage

    Raises
    ------
    InputError
        An image that is not 2-d and real, empty, of another unit, already
        corrected, in ADU without a known gain, a mask of another shape, a
        bad gain or saturation level; each message names the image and what
        would be accepted.
    """
    (exposure, data, own_mask, unc, meta, stated, from_file, kind, source,
     bits) = _unpack(exposure)
    data = as_float64(data)
    if bits is not None:
        own_mask = plane_mask(bits[0], bits[1], blocking)
    if refuse_bf_corrected:
        refuse_corrected(exposure, meta, source)
    if data.ndim != 2:
        raise InputError(f"{source}: exposure must be a 2-d image, got shape {data.shape}")
    if 0 in data.shape:
        raise InputError(f"{source}: exposure is empty (shape {data.shape}); accepted: an "
                         "image of at least 1 x 1 pixels")
    if own_mask is not None and own_mask.shape != data.shape:
        raise InputError(f"{source}: mask shape {own_mask.shape} does not match image "
                         f"{data.shape}")
    unit = image_unit(stated, gain=gain, header_gain=meta.get("GAIN"), from_file=from_file,
                      source=source, gain_name=gain_name)
    _require_gain(unit, source, gain_name)
    g = unit.gain
    electrons = data if g == 1.0 else data * g
    bad = ~np.isfinite(electrons)
    if own_mask is not None:
        bad |= own_mask
    if mask is not None:
        extra = np.asarray(mask, dtype=bool)
        if extra.shape != data.shape:
            raise InputError(f"{source}: mask shape {extra.shape} does not match image "
                             f"{data.shape}")
        bad |= extra
    level, origin, warning = saturation_level(
        np.where(bad, -np.inf, electrons) if bad.any() else electrons, bad, saturation=saturation,
        header=meta, gain=g, source=source, saturation_name=saturation_name)
    warnings = []
    saturated = None
    if level is not None:
        with np.errstate(invalid="ignore"):
            saturated = electrons >= level
    if bits is not None:
        undeclared = undeclared_bits(*bits)
        if undeclared:
            n = int(np.count_nonzero(bits[0] & sum(1 << b for b in undeclared)))
            warnings.append(f"mask bits {undeclared} are set in {n} pixels but no MP_<NAME> "
                            f"card declares them: those pixels are not blocked (declared "
                            f"planes: {sorted(bits[1]) or 'none'}); declare the planes in the "
                            "MASK header to use them")
    if warning is not None:
        warnings.append(warning)
    return ElectronImage(data=electrons, mask=own_mask, bad=bad, uncertainty=unc, meta=meta,
                         unit=unit, gain=g, kind=kind, source=source, saturation=level,
                         saturation_origin=origin, saturated=saturated,
                         sat_plane=plane_pixels(exposure, ("SAT",)), exposure=exposure,
                         warnings=warnings)
