"""BrighterFatterDriftTask: correct exposures with the template as Green's function.

The Task only wires plain functions: :func:`~lsst_bfdrift.correction.solvers.correct_image`
for the flux redistribution and :func:`~lsst_bfdrift.geometry.linear.linear_moment_maps`
(or :func:`~lsst_bfdrift.geometry.superpose.moment_maps`) for the final pixel geometry
predicted from the recorded image.
"""

import copy
import math
import os

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.nddata import CCDData, NDData

import lsst.pex.config as pexConfig

from lsst_bfdrift.utils.config import Struct, Task
from lsst_bfdrift.utils.exposure import (BLOCKING_PLANES, MaskedExposure, _is_afw_like,
                                         add_mask_plane, plane_mask, read_exposure)
from lsst_bfdrift.correction.checks import (input_warnings, mask_warnings, plateau_level,
                                            plateau_warning)
from lsst_bfdrift.correction.solvers import (MAX_SWEEP, area_coefficients, correct_coulton18,
                                             correct_half_shift, correct_image,
                                             coulton18_kernel, refuse_out_of_range)
from lsst_bfdrift.geometry.first_order import FirstOrderPass
from lsst_bfdrift.geometry.linear import linear_moment_maps
from lsst_bfdrift.geometry.superpose import moment_maps
from lsst_bfdrift.templates.refine import draw_templates
from lsst_bfdrift.templates.swept import OperatorCache
from lsst_bfdrift.templates.template import DistortionTemplate, load_default_template
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["BrighterFatterDriftConfig", "BrighterFatterDriftTask", "unpack_exposure",
           "template_digest", "gain_value", "fits_header", "FLAG_BLOCKED",
           "FLAG_EDGE", "BF_PLANE_DOC", "stage_order"]

#: Flag bit: pixel masked, saturated or non-finite (no flux exchanged).
FLAG_BLOCKED = 1
#: Flag bit: pixel within the template's reach of the image border (aggressors missing).
FLAG_EDGE = 2
#: Description of the BF mask plane (afw's ``MPD_BF`` card).
BF_PLANE_DOC = ("BF correction incomplete: blocked (masked, saturated, non-finite) or within "
                "the template's reach of the border")

_METHODS = {
    "drift": "time-history series of the template's swept areas (order >= 3), inverted by "
             "a third-order series",
    "astier23": "Astier & Regnault 2023: per-electron boundary shifts (the template's swept "
                "areas), half the final shift, two-pixel flux density, one pass",
    "coulton18": "Coulton et al. 2018: kernel with Laplacian equal to the template's a_ij, "
                 "I = F + 1/2 div(F grad(K * F)), iterated",
}


class BrighterFatterDriftConfig(pexConfig.Config):
    """Configuration of :class:`BrighterFatterDriftTask` (an ``lsst.pex.config`` Config).

    Field names are snake_case, as everywhere in the package. A config file is
    a pex_config override file (``config.method = "astier23"``), read with
    :func:`~lsst_bfdrift.utils.config.load_config`.
    """

    template = pexConfig.Field(
        doc="template FITS file; None uses the bundled default", dtype=str, default=None,
        optional=True)
    method = pexConfig.ChoiceField(
        doc="correction method", dtype=str, default="drift", allowed=_METHODS, optional=False)
    order = pexConfig.Field(
        doc="terms of the time-history series for method 'drift' (2 = half shift)",
        dtype=int, default=3, check=lambda v: 2 <= v <= 8)
    density = pexConfig.ChoiceField(
        doc="flux density at pixel edges (drift)", dtype=str, default="fv4", optional=False,
        allowed={"mean2": "mean of the two pixels beside the edge",
                 "cubic4": "four-point interpolation along the normal",
                 "fv4": "four-point finite-volume reconstruction from pixel averages"})
    max_iter = pexConfig.Field(
        doc="largest number of solver iterations", dtype=int, default=10,
        check=lambda v: v >= 1)
    rtol = pexConfig.Field(
        doc="convergence: max |I - R(F)| / max |I| (when noise_tol is None)", dtype=float,
        default=1e-7, check=lambda v: 0 < v < 1)
    noise_tol = pexConfig.Field(
        doc="convergence: |I - R(F)| <= noise_tol * sqrt(I) in every pixel (fraction of the "
            "Poisson noise); None: use rtol", dtype=float, default=0.05, optional=True,
        check=lambda v: 0 < v < 1)
    start = pexConfig.ChoiceField(
        doc="first guess of the drift solver", dtype=str, default="series", optional=False,
        allowed={"series": "third-order inverse series (three operator calls), iterated only "
                           "if an a-priori bound requires",
                 "image": "the recorded image"})
    fft_precision = pexConfig.ChoiceField(
        doc="precision of the FFT convolutions", dtype=str, default="float32", optional=False,
        allowed={"float32": "single (half the time and memory); the linear centroid and "
                            "ellipticity maps are returned in float32 too",
                 "float64": "double"})
    strip = pexConfig.Field(
        doc="rows per block for the drift and astier23 solvers (bounded memory); None: whole "
            "image", dtype=int, default=512, optional=True, check=lambda v: v >= 16)
    sparse = pexConfig.Field(
        doc="drift with start='series': second- and third-order terms only in windows around "
            "the sources that need them (bounded error; dense fallback)", dtype=bool,
        default=True)
    gain = pexConfig.Field(
        doc="e/ADU for images in ADU (None: read GAIN from the header)", dtype=float,
        default=None, optional=True, check=lambda v: math.isfinite(v) and v > 0)
    saturation = pexConfig.Field(
        doc="level at and above which pixels are blocked, in the image's units (e, or ADU for "
            "an image in ADU); None: the SATURATE keyword of the header if present, else the "
            "image's largest value when three or more unblocked pixels share it exactly, 10 "
            "sigma above the sky (a flat top, checks.plateau_level; with a warning), else no "
            "limit", dtype=float,
        default=None, optional=True, check=lambda v: math.isfinite(v) and v > 0)
    compute_geometry = pexConfig.Field(
        doc="compute area, centroid and ellipticity maps", dtype=bool, default=True)
    geometry_method = pexConfig.ChoiceField(
        doc="how the geometry maps are computed", dtype=str, default="linear", optional=False,
        allowed={"linear": "first order in the charge (FFT convolutions with the template's "
                           "moment kernels), exact polygon moments where an a-priori bound "
                           "exceeds geometry_tolerance (geometry.linear)",
                 "exact": "exact polygon moments of every pixel (geometry.superpose)"})
    geometry_tolerance = pexConfig.Field(
        doc="geometry_method 'linear': largest error against the exact maps in any pixel, as a "
            "fraction of each map's signal (its largest abs(map - nominal) over the image)",
        dtype=float, default=1e-3, check=lambda v: 0 < v < 1)
    geometry_samples = pexConfig.Field(
        doc="samples per pixel edge for the geometry maps (template edges resampled keeping "
            "swept areas and moments to first order: ~1e-5 of the signal for area and "
            "centroid, ~2e-4 for e2, 4x less CPU than the 32-sample default; "
            "superpose.resample_template); templates with no more samples are used as they "
            "are; None: the template's own", dtype=int, default=8, optional=True,
        check=lambda v: v >= 1)
    workers = pexConfig.Field(doc="FFT threads", dtype=int, default=2, check=lambda v: v >= 1)
    uncertainty_draws = pexConfig.Field(
        doc="templates drawn from the calibration uncertainty stored in a calibrated template "
            "(bfdrift calibrate) to give flux_moved_err, the standard deviation of "
            "flux_moved; each costs one more correction; 0: off", dtype=int, default=0,
        check=lambda v: v == 0 or v >= 2)
    uncertainty_seed = pexConfig.Field(doc="seed of the template draws", dtype=int, default=0)
    blocking_mask_planes = pexConfig.ListField(
        doc="mask planes whose pixels neither give nor receive charge (where the exposure "
            "declares them; other planes, e.g. DETECTED, never block)", dtype=str,
        default=list(BLOCKING_PLANES))
    masked_aggressors = pexConfig.ChoiceField(
        doc="charge of masked pixels as aggressors (they never exchange flux)", dtype=str,
        default="keep", optional=False,
        allowed={"keep": "their recorded value (a saturated core's charge is real); a masked "
                         "pixel beyond the model's range is interpolated all the same",
                 "interpolate": "the mean of the unmasked pixels in the 5 x 5 box around "
                                "them, as ip_isr interpolates defects before BF; recorded "
                                "values restored after"})
    on_input_warning = pexConfig.ChoiceField(
        doc="what an input that looks wrong (input_warnings: a bias pedestal, a mask over "
            "the sources, undeclared mask bits) gives", dtype=str, default="warn",
        optional=False,
        allowed={"warn": "logged, counted in BFWARN and returned as Struct.warnings; the "
                         "image is corrected (noiseless simulations look like a pedestal)",
                 "raise": "an InputError naming the warnings; nothing is returned"})
    bf_mask_plane = pexConfig.Field(
        doc="mask plane added to exposures with bit-plane masks for the pixels the correction "
            "flags (flags != 0: blocked, or within the template's reach of the border)",
        dtype=str, default="BF")


def stage_order(config=None):
    """The stages :meth:`BrighterFatterDriftTask.run` reports, in their order.

    ``('correct',)`` without ``compute_geometry``; ``('maps', 'correct')``
    with the exact maps (computed before the correction: their working
    arrays are freed before the solver's outputs exist); ``('correct',
    'maps')`` with the linear ones (computed after it, from its first pass).

    Parameters
    ----------
    config : BrighterFatterDriftConfig or dict, optional
        Default: the defaults.
    """
    defaults = BrighterFatterDriftConfig()
    if config is None:
        config = defaults
    get = config.get if isinstance(config, dict) else \
        (lambda key, default: getattr(config, key))
    if not get("compute_geometry", defaults.compute_geometry):
        return ("correct",)
    if get("geometry_method", defaults.geometry_method) == "linear":
        return ("correct", "maps")
    return ("maps", "correct")


def _correct(data, template, blocked, cfg, dtype, cache, maps=None, progress=None):
    """The configured correction of ``data`` with ``template``: (flux,
    iterations, converged, order, density, solver info); ``maps``
    (:class:`~lsst_bfdrift.geometry.first_order.FirstOrderPass`) is filled by the
    astier23 pass and by the drift series' first-order pass when it is the
    sparse one; ``progress`` (a fraction) as for
    :func:`~lsst_bfdrift.correction.solvers.correct_image`."""
    order = 2 if cfg.method == "astier23" else cfg.order
    density = "mean2" if cfg.method == "astier23" else cfg.density
    solver = {}
    if cfg.method == "astier23":
        flux, iterations, converged = correct_half_shift(
            data, template, blocked=blocked, workers=cfg.workers, dtype=dtype,
            strip=cfg.strip, cache=cache, check_range=False, maps=maps)
    elif cfg.method == "coulton18":
        order = density = "n/a"
        kernel = coulton18_kernel(area_coefficients(template))
        flux, iterations, converged = correct_coulton18(
            data, kernel, blocked=blocked, max_iter=cfg.max_iter, rtol=cfg.rtol,
            workers=cfg.workers)
    else:
        flux, iterations, converged = correct_image(
            data, template, order=order, density=density, blocked=blocked,
            max_iter=cfg.max_iter, rtol=cfg.rtol, noise_tol=cfg.noise_tol, start=cfg.start,
            workers=cfg.workers, dtype=dtype, strip=cfg.strip, sparse=cfg.sparse,
            cache=cache, info=solver, check_range=False, maps=maps, progress=progress)
    return flux, iterations, converged, order, density, solver


def unpack_exposure(exposure, gain_cfg, *, blocking=BLOCKING_PLANES):
    """data (float64, e; no copy when possible), mask, uncertainty, meta, unit, gain,
    kind.

    ``mask`` is the boolean mask of blocked pixels: an NDData/MaskedArray mask,
    or the ``blocking`` planes of a bit-plane mask (MaskedExposure, afw
    Exposure).
    """
    kind = "ndarray"
    mask = unc = None
    meta = fits.Header()
    unit = u.electron
    stated = False  # whether the input states its unit (BUNIT, a CCDData unit)
    gain_cfg = gain_value(gain_cfg)
    if isinstance(exposure, (str, os.PathLike)):
        exposure = read_exposure(exposure)  # a truncated file is named as such
        kind = "path"
    if isinstance(exposure, MaskedExposure):
        kind = "path" if kind == "path" else "exposure"
        data = _as_float64(exposure.image)
        mask = plane_mask(exposure.mask, exposure.mask_planes, blocking)
        meta = fits.Header(exposure.header)
        for key in ("GAIN", "SATURATE"):
            if key not in meta and exposure.header_value(key) is not None:
                meta[key] = exposure.header_value(key)  # INHERIT from the primary
        unit = _bunit(exposure.unit(), exposure.path or "exposure")
        stated = exposure.unit() != ""
    elif _is_afw_like(exposure):
        kind = "afw"
        data = _as_float64(exposure.image.array)
        m = exposure.mask
        mask = plane_mask(np.asarray(m.array), m.getMaskPlaneDict(), blocking)
        md = exposure.getMetadata()
        md = md.toDict() if hasattr(md, "toDict") else dict(md or {})
        meta = fits.Header({k: v for k, v in md.items() if isinstance(v, (int, float, str, bool))
                            and len(k) <= 8})
        stated_unit = str(md.get("LSST ISR UNITS", md.get("BUNIT", ""))).strip().lower()
        unit = _bunit(stated_unit, "exposure")
        stated = stated_unit != ""
    elif isinstance(exposure, NDData):
        kind = "ccddata" if isinstance(exposure, CCDData) else "nddata"
        data = _as_float64(exposure.data)
        mask = None if exposure.mask is None else np.array(exposure.mask, bool)
        unc = exposure.uncertainty
        meta = fits_header(exposure.meta)
        unit = exposure.unit if exposure.unit is not None else u.electron
        stated = exposure.unit is not None
    elif isinstance(exposure, np.ma.MaskedArray):
        kind = "masked"
        data = _as_float64(exposure.data)
        mask = np.array(np.ma.getmaskarray(exposure), bool)
    else:
        data = _as_float64(exposure)
    _refuse_corrected(exposure, meta)
    if data.ndim != 2:
        raise InputError(f"exposure must be a 2-d image, got shape {data.shape}")
    if 0 in data.shape:
        raise InputError(f"exposure is empty (shape {data.shape}); accepted: an image of at "
                         "least 1 x 1 pixels")
    if mask is not None and mask.shape != data.shape:
        raise InputError(f"mask shape {mask.shape} does not match image {data.shape}")
    gain = 1.0
    is_adu = unit in (u.adu, u.count) or str(unit).lower() in ("adu", "dn")
    if gain_cfg is not None and not is_adu:
        # one meaning of a given gain everywhere: the image is in ADU
        if stated and unit in (u.electron,):
            raise InputError(f"a gain of {gain_cfg} e/ADU was given (--gain, config.gain) but "
                             "the image states it is in electrons (BUNIT or unit); drop the "
                             "gain, or fix the unit if the image is in ADU")
        if unit not in (u.electron, u.dimensionless_unscaled):
            raise InputError(f"exposure unit must be electron or adu, got {unit}")
        unit, is_adu = u.adu, True
    if is_adu:
        gain = gain_cfg if gain_cfg is not None else meta.get("GAIN")
        if gain is None:
            raise InputError("image is in ADU: give a gain (--gain, config.gain) or a GAIN "
                             "header keyword")
        if isinstance(gain, (bool, np.bool_)) or not isinstance(gain, (int, float, np.number)):
            raise InputError(f"gain {gain!r} (GAIN keyword or config.gain) is not a number of "
                             "e/ADU")
        gain = float(gain)
        if not gain > 0:
            raise InputError(f"gain must be positive, got {gain}")
    elif unit not in (u.electron, u.dimensionless_unscaled):
        raise InputError(f"exposure unit must be electron or adu, got {unit}")
    return (data if gain == 1.0 else data * gain), mask, unc, meta, unit, gain, kind


#: Keys that say an image was already corrected for the brighter-fatter effect
#: (ip_isr's, then the package's own).
_CORRECTED_KEYS = ("LSST ISR BF APPLIED", "BFDRIFT")


def _refuse_corrected(exposure, meta):
    """Refuse an image whose metadata says the BF correction was already applied
    (``LSST ISR BF APPLIED = T`` from ip_isr, ``BFDRIFT = T`` from this package):
    a second correction would double it, silently."""
    if isinstance(exposure, MaskedExposure):
        def get(key):
            return exposure.header_value(key)
        source = exposure.path or "exposure"
    elif _is_afw_like(exposure):
        md = exposure.getMetadata()
        md = md.toDict() if hasattr(md, "toDict") else dict(md or {})
        get, source = md.get, "exposure"
    elif isinstance(exposure, NDData) and exposure.meta:
        get, source = dict(exposure.meta).get, "exposure"
    else:
        def get(key):
            return meta.get(key) if meta is not None else None
        source = "exposure"
    for key in _CORRECTED_KEYS:
        value = get(key)
        if value is True or (isinstance(value, str) and value.strip().upper() in ("T", "TRUE")):
            how = get("LSST ISR BF CORR METHOD") or get("BFMETHOD")
            raise InputError(
                f"{source}: already corrected for the brighter-fatter effect ({key} = True"
                + (f", method {how}" if how else "") + "); a second correction would double "
                "it. Give the image from before the BF step (ip_isr: doBrighterFatter=False), "
                f"or remove {key} if the header is wrong")


#: ``LSST ISR BF CORR METHOD`` of each method (ip_isr's names where they apply).
_LSST_METHOD = {"drift": "LSST_BFDRIFT", "astier23": "ASTIER23", "coulton18": "COULTON18"}


def _version():
    from lsst_bfdrift import __version__
    return __version__


def template_digest(template):
    """First 16 hex digits of the sha1 of a template's displacements (its identity)."""
    import hashlib

    h = hashlib.sha1()
    for name in ("corner_d", "vedge_d", "hedge_d", "fractions"):
        arr = getattr(template, name, None)
        if arr is not None:
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    h.update(repr(float(template.charge)).encode())
    return h.hexdigest()[:16]


def _fill_masked(image, fill, blocked):
    """``image`` with the ``fill`` pixels replaced by the mean of the pixels that are
    not blocked in the 5 x 5 box around each (the image median where a box has none)."""
    from scipy.ndimage import uniform_filter

    good = ~blocked
    num = uniform_filter(np.where(good, image, 0.0), size=5, mode="constant")
    den = uniform_filter(good.astype(np.float64), size=5, mode="constant")
    fallback = float(np.median(image[good])) if good.any() else 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        local = np.where(den > 1e-9, num / np.where(den > 1e-9, den, 1.0), fallback)
    return np.where(fill, local, image)


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


def gain_value(gain):
    """A gain as float e/ADU: a number or an astropy Quantity in electron/adu (None
    stays None)."""
    if gain is None:
        return None
    if isinstance(gain, u.Quantity):
        try:
            return float(gain.to_value(u.electron / u.adu))
        except u.UnitConversionError:
            raise InputError(f"gain {gain} is not in electron/adu") from None
    if isinstance(gain, (bool, np.bool_)) or not isinstance(gain, (int, float, np.number)):
        raise InputError(f"gain {gain!r} is not a number of e/ADU")
    return float(gain)


def _bunit(bunit, source):
    """astropy unit of a BUNIT / LSST ISR UNITS string (missing: electrons)."""
    if bunit in _ADU_UNITS:
        return u.adu
    if bunit in _ELECTRON_UNITS:
        return u.electron
    raise InputError(f"{source}: BUNIT = {bunit!r} is not a charge image; accepted: electron "
                     "(e, e-, electrons) or ADU (adu, dn, count)")


#: BUNIT spellings of a charge image in electrons (a missing BUNIT means electrons).
_ELECTRON_UNITS = ("electron", "electrons", "e", "e-", "")
#: BUNIT spellings of an image in ADU.
_ADU_UNITS = ("adu", "dn", "count", "counts")


def _as_float64(array):
    """``array`` as float64, a copy only if the dtype differs. Nothing below
    writes into it (the caller's data are never modified; checked by
    ``tests/correction/test_task.py::test_input_untouched_and_not_aliased``). It is not
    made read-only: numba compiles read-only arrays as another type, which
    would double the kernels' compilations. Integer and float images are
    accepted; boolean, complex and non-numeric ones are refused."""
    array = np.asarray(array)
    if array.dtype.kind not in "iuf":
        what = {"b": "boolean", "c": "complex"}.get(array.dtype.kind,
                                                    f"non-numeric ({array.dtype})")
        raise InputError(f"exposure data must be real numbers (e or ADU), got a {what} array")
    return array.astype(np.float64, copy=False)


def _result_header(meta, cfg, template, *, warnings, order, density, iterations, converged,
                   solver, filled, gain, saturation):
    """The input's header with the BF* cards of one run and LSST ISR's BF keys."""
    header = fits.Header(meta)
    header["BFDRIFT"] = (True, "BF correction applied (lsst_bfdrift)")
    header["BFWARN"] = (warnings, "input warnings (see the task's log)")
    header["BFMETHOD"] = (cfg.method, "correction method")
    header["BFORDER"] = (order, "time-history series order")
    header["BFDENS"] = (density, "edge flux density estimate")
    header["BFITER"] = (iterations, "solver iterations")
    header["BFCONV"] = (bool(converged), "solver converged")
    if cfg.method == "drift":
        header["BFSOLVER"] = (solver.get("solver", "dense"), "drift series: sparse or dense")
    if cfg.compute_geometry:
        ns = template.edge_samples
        if cfg.geometry_samples is not None:
            ns = min(cfg.geometry_samples, ns)
        header["BFGSAMP"] = (ns, "edge samples of the geometry maps")
        header["BFGMETH"] = (cfg.geometry_method, "geometry maps: linear or exact")
    header["BFQTMPL"] = (template.charge, "template aggressor charge (e)")
    header["BFTMPL"] = (os.path.basename(str(cfg.template or "bundled default"))[-40:],
                        "BF template file")
    header["BFVERS"] = (_version(), "lsst_bfdrift version")
    header["BFNFILL"] = (filled, "masked pixels interpolated as aggressors")
    header["BFTSUM"] = (template_digest(template), "BF template digest (sha1, 16)")
    header["BFGAIN"] = (float(gain), "gain applied (e/ADU; 1: image in e)")
    if saturation is not None:
        header["BFSATUR"] = (saturation, "saturation level applied (e)")
    header["HIERARCH LSST ISR BF APPLIED"] = True
    header["HIERARCH LSST ISR BF CORR METHOD"] = _LSST_METHOD[cfg.method]
    return header


class BrighterFatterDriftTask(Task):
    """Correct the brighter-fatter effect with an electrostatic template.

    ``run(exposure)`` predicts the final pixel boundaries from the recorded
    image with the template as Green's function, returns the pixel geometry
    maps and the flux-conserving correction.

    Examples
    --------
    A bright star (4e5 e) on a sky of 1000 e, in electrons. The correction
    moves the charge the star pushed into its neighbours back to its core,
    and conserves the flux:

    >>> import numpy as np
    >>> from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    >>> yy, xx = np.mgrid[:48, :48] - 24.0
    >>> img = 1000.0 + 4e5 / (2 * np.pi * 1.5**2) * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2)
    >>> res = BrighterFatterDriftTask().run(img)
    >>> bool(np.isclose(res.exposure.sum(), img.sum(), rtol=1e-12))
    True
    >>> bool(res.exposure[24, 24] > img[24, 24])
    True
    >>> res.area.shape, res.header["BFMETHOD"]
    ((48, 48), 'drift')

    The astier23 correction with the same template, without the maps:

    >>> config = BrighterFatterDriftConfig(method="astier23", compute_geometry=False)
    >>> res = BrighterFatterDriftTask(config=config).run(img)
    >>> res.area is None, bool(np.isclose(res.exposure.sum(), img.sum(), rtol=1e-12))
    (True, True)
    """

    ConfigClass = BrighterFatterDriftConfig
    _DefaultName = "brighterFatterDrift"

    def __init__(self, config=None, *, template=None, **kwargs):
        if config is not None and not isinstance(config, self.ConfigClass):
            raise InputTypeError(f"config must be a {self.ConfigClass.__name__}, got "
                                 f"{type(config).__name__}")
        super().__init__(config=config, **kwargs)
        self.config.validate()
        self.config.freeze()
        if template is not None:
            self.template = template
        elif self.config.template is None:
            self.template = load_default_template()
        else:
            self.template = DistortionTemplate.load(self.config.template)
        self._cache = None

    def _operators(self, dtype):
        """Swept-area operators of the template, kept between calls to run()."""
        c = self._cache
        if c is None or not c.matches(self.template, self.config.workers, dtype):
            c = self._cache = OperatorCache(self.template, workers=self.config.workers,
                                            dtype=dtype)
        return c

    def run(self, exposure, *, progress=None):
        """Correct ``exposure``.

        Parameters
        ----------
        exposure : CCDData, NDData, numpy.ma.MaskedArray, ndarray or path
            Image in electrons (or ADU with ``config.gain`` / a GAIN keyword).
            Masked pixels (NDData and MaskedArray masks) neither give nor
            receive charge and are flagged. A FITS file's BUNIT must say
            electron or ADU (other units, e.g. e/s or MJy/sr, are refused).
            Never modified.
        progress : callable, optional
            Called as ``progress(stage, fraction)`` while the run goes on:
            stages ``'correct'`` and, with ``compute_geometry``, ``'maps'``
            (the geometry maps), in the order they run (:func:`stage_order`:
            the exact maps before the correction, the linear ones after it,
            from its first pass), each with the fraction (0 to 1) of that
            stage done, never decreasing, from 0 to 1, e.g. a
            :class:`~lsst_bfdrift.utils.progress.StageProgress`. It does not
            change the result.

        Returns
        -------
        Struct
            ``exposure`` (corrected, same type as given; mask and uncertainty
            carried; a MaskedArray's mask gains the blocked pixels), ``area``,
            ``centroid_x``, ``centroid_y`` (shift from the pixel centre, px),
            ``e1``, ``e2`` (None if ``compute_geometry`` is off), ``flux_moved`` (e;
            sums to zero), ``flux_moved_err`` (e; its standard deviation over
            templates drawn from the calibration uncertainty, None unless
            ``uncertainty_draws``), ``flags`` (uint8, bits FLAG_BLOCKED, FLAG_EDGE),
            ``iterations``, ``converged``, ``warnings`` (what looks wrong with the
            input: :func:`input_warnings`; also logged).
        """
        cfg = self.config

        def report(stage, fraction):
            if progress is not None:
                progress(stage, fraction)

        data, mask, unc, meta, unit, gain, kind = unpack_exposure(
            exposure, cfg.gain, blocking=tuple(cfg.blocking_mask_planes))
        finite = np.isfinite(data)
        all_finite = bool(finite.all())
        finite_data = data if all_finite else np.where(finite, data, 0.0)
        blocked = np.logical_not(finite, out=finite)
        if mask is not None:
            blocked |= mask
        sat = cfg.saturation if cfg.saturation is not None else meta.get("SATURATE")
        sat_e = None
        if sat is not None:
            if isinstance(sat, (bool, np.bool_)) or not isinstance(sat, (int, float, np.number)) \
                    or not float(sat) > 0:
                raise InputError(f"saturation {sat!r} (SATURATE keyword or config.saturation) "
                                 "is not a positive level")
            sat_e = float(sat) * gain  # image units -> e
            blocked |= finite_data >= sat_e
        else:
            # no stated level: an image clipped at one (a flat top) gives it
            sat_e = plateau_level(finite_data, blocked)
            if sat_e is not None:
                blocked |= finite_data >= sat_e
        dtype = np.float32 if cfg.fft_precision == "float32" else np.float64
        # pixels masked as blocking (a hot pixel, a saturated core) never stop a run
        checked = finite_data if mask is None or not mask.any() else \
            np.where(mask, 0.0, finite_data)
        kabs = self._operators(dtype).kernel_abs_sum
        refuse_out_of_range(checked, kabs,
                            f"; the image was converted with gain {gain} e/ADU" if gain != 1.0
                            else "; is the image in ADU without a gain?")
        # masked pixels as aggressors: their recorded charge ('keep'), or the mean of
        # their unmasked neighbours ('interpolate', as ip_isr does); one beyond the
        # model's range is never charge the model can use, so it is always filled
        fill = None
        if mask is not None and mask.any():
            fill = mask.copy() if cfg.masked_aggressors == "interpolate" else \
                mask & (np.abs(finite_data) > MAX_SWEEP / kabs)
            if fill.any():
                recorded = data  # not modified: new arrays below
                finite_data = _fill_masked(finite_data, fill, blocked)
                data = np.where(fill, finite_data, data)
            else:
                fill = None
        # exact maps first: their working arrays are freed before the solver's
        # outputs exist (peak memory, docs/benchmarks.rst); the linear maps'
        # first order comes from the correction's first pass when it applies
        # the swept-area operator to this very image, the rest after it
        geom = dict(area=None, centroid_x=None, centroid_y=None, e1=None, e2=None)
        ns = cfg.geometry_samples
        samples = None if ns is None else min(ns, self.template.edge_samples)
        names = ("area", "dx", "dy", "e1", "e2")  # only those returned
        # what looks wrong with the input (of the image the flux moved is
        # taken from), before the maps and the correction allocate: its
        # temporaries (two images) are gone by then (peak memory)
        warnings = input_warnings(finite_data if fill is None else
                                  np.where(fill, 0.0, finite_data), blocked)
        warnings += mask_warnings(exposure, kind)
        if sat is None and sat_e is not None:
            warnings.append(plateau_warning(
                finite_data, sat_e, "they are blocked as saturated (set config.saturation or a "
                "SATURATE keyword to state the level)"))
        linear = cfg.compute_geometry and cfg.geometry_method == "linear"
        first = None
        if linear and data is finite_data and (
                cfg.method == "astier23"
                or (cfg.method == "drift" and cfg.sparse and cfg.start == "series")):
            first = FirstOrderPass(self.template, data.shape, maps=names, samples=samples,
                                   dtype=dtype)
        if cfg.compute_geometry and not linear:
            # stage 'maps' before 'correct' (exact maps)
            report("maps", 0.0)
            rows = [0]

            def row_done(n):
                rows[0] += n
                report("maps", rows[0] / finite_data.shape[0])

            maps = moment_maps(self.template, finite_data, workers=cfg.workers, dtype=dtype,
                               samples=samples, maps=names, progress=row_done)
            geom = dict(area=maps.area, centroid_x=maps.dx, centroid_y=maps.dy, e1=maps.e1,
                        e2=maps.e2)
            report("maps", 1.0)
        report("correct", 0.0)
        flux, iterations, converged, order, density, solver = _correct(
            data, self.template, blocked, cfg, dtype, self._operators(dtype), maps=first,
            progress=lambda f: report("correct", f))
        report("correct", 1.0)
        if linear:
            # stage 'maps' after 'correct' (linear maps, from its first pass)
            report("maps", 0.0)
            maps = linear_moment_maps(
                self.template, finite_data, rtol=cfg.geometry_tolerance, samples=samples,
                workers=cfg.workers, dtype=dtype, maps=names,
                strip=data.shape[0] if cfg.strip is None else cfg.strip,
                first_order=first, ops=self._operators(dtype), check_range=False,
                map_dtype=dtype, progress=lambda f: report("maps", f))
            del first
            geom = dict(area=maps.area, centroid_x=maps.dx, centroid_y=maps.dy, e1=maps.e1,
                        e2=maps.e2)
            report("maps", 1.0)
        if fill is not None:  # the recorded values come back
            flux = np.where(fill, recorded, flux)
            finite_data = np.where(fill, 0.0, finite_data)
        moved = flux - finite_data
        moved[blocked] = 0.0
        moved_err = None
        if cfg.uncertainty_draws:
            moved_err = self._flux_moved_error(data, finite_data, blocked, moved, dtype)
        flags = blocked.astype(np.uint8)  # FLAG_BLOCKED = 1
        c = self.template.center
        for sl in (np.s_[:c], np.s_[-c:], np.s_[:, :c], np.s_[:, -c:]):
            flags[sl] |= FLAG_EDGE
        if not converged:
            self.log.warning("brighter-fatter correction did not converge in %d iterations",
                             iterations)
        if warnings and cfg.on_input_warning == "raise":
            raise InputError("input refused (on_input_warning='raise'): " + "; ".join(warnings))
        for w in warnings:
            self.log.warning("%s", w)
        header = _result_header(meta, cfg, self.template, warnings=len(warnings), order=order,
                                density=density, iterations=iterations,
                                converged=converged, solver=solver,
                                filled=0 if fill is None else int(fill.sum()), gain=gain,
                                saturation=sat_e)
        out_data = flux if gain == 1.0 else flux / gain  # flux: a new array of the solver
        if moved_err is not None:
            header["BFUNCN"] = (cfg.uncertainty_draws, "template draws of flux_moved_err")
        if kind in ("ccddata", "nddata"):
            new_mask = blocked if mask is None else (mask | blocked)
            cls = CCDData if kind == "ccddata" else NDData
            # the input's meta as it was (values FITS cannot hold included) + BF keys
            meta_out = copy.copy(exposure.meta) if exposure.meta else {}
            for card in header.cards:
                if card.keyword.startswith(("BF", "LSST ISR BF")):
                    meta_out[card.keyword] = card.value
            out = cls(out_data, unit=unit, mask=new_mask, uncertainty=unc, meta=meta_out,
                      wcs=exposure.wcs)
        elif kind == "exposure":
            out = self._exposure_out(exposure, out_data, flags, header, moved_err, gain)
        elif kind == "afw":
            out = self._afw_out(exposure, out_data, flags, header, moved_err, gain)
        elif kind == "path":
            out = CCDData(out_data, unit=unit, mask=blocked, meta=header)
        elif kind == "masked":
            out = np.ma.MaskedArray(out_data, mask=mask | blocked)
        else:
            out = out_data
        return Struct(exposure=out, warnings=warnings, flux_moved=moved, flux_moved_err=moved_err,
                      flags=flags, iterations=iterations, converged=bool(converged), header=header,
                      **geom)

    def _exposure_out(self, exposure, out_data, flags, header, moved_err, gain):
        """A copy of the MaskedExposure with the corrected image, the BF plane and the
        correction's variance added (when ``flux_moved_err`` was computed).

        The BF and ``LSST ISR BF`` keys go where afw keeps the metadata
        (:meth:`~lsst_bfdrift.utils.exposure.MaskedExposure.metadata`: the
        primary header of an LSST file with ``INHERIT``); an integer image
        becomes float32 (the corrected values are fractional)."""
        out = exposure.copy()
        dtype = exposure.image.dtype
        out.image = out_data.astype(np.float32 if dtype.kind in "iub" else dtype, copy=False)
        md = out.metadata()
        for card in header.cards:
            key = card.keyword
            if key.startswith(("BF", "LSST ISR BF")):
                name = f"HIERARCH {key}" if len(key) > 8 or " " in key else key
                md[name] = (card.value, card.comment)
        if out.mask is not None and out.layout != "ccddata":
            # a CCDData file's mask is boolean for its readers: the flags stay in
            # BFFLAGS rather than turn flagged (e.g. border) pixels into masked ones
            bit = add_mask_plane(out, self.config.bf_mask_plane, doc=BF_PLANE_DOC)
            out.mask = out.mask | np.where(flags != 0, np.int32(1 << bit), np.int32(0))
        if out.variance is not None and moved_err is not None:
            out.variance = out.variance + (moved_err / gain) ** 2
        return out

    def _afw_out(self, exposure, out_data, flags, header, moved_err, gain):
        """A clone of an afw-like Exposure: image replaced, BF plane added (with its
        description where afw takes one), variance + flux_moved_err^2, keys set."""
        out = exposure.clone() if hasattr(exposure, "clone") else copy.deepcopy(exposure)
        arr = out.image.array
        arr[...] = out_data.astype(arr.dtype, copy=False)
        name = self.config.bf_mask_plane
        try:
            bit = out.mask.addMaskPlane(name, BF_PLANE_DOC)  # afw with plane docs
        except TypeError:
            bit = out.mask.addMaskPlane(name)
        m = out.mask.array
        m |= np.where(flags != 0, 1 << int(bit), 0).astype(m.dtype)
        var = getattr(out, "variance", None)
        if moved_err is not None and var is not None and hasattr(var, "array"):
            var.array[...] += ((moved_err / gain) ** 2).astype(var.array.dtype)
        md = out.getMetadata()
        for card in header.cards:
            key = card.keyword
            if not key.startswith(("BF", "LSST ISR BF")):
                continue
            if hasattr(md, "set"):
                md.set(key, card.value)
            else:
                md[key] = card.value
        return out

    def _flux_moved_error(self, data, finite_data, blocked, moved, dtype):
        """Standard deviation of flux_moved over templates drawn from the
        calibration uncertainty (templates.refine.draw_templates)."""
        cfg = self.config
        draws = draw_templates(self.template, cfg.uncertainty_draws, seed=cfg.uncertainty_seed)
        acc = np.zeros_like(moved)
        for tpl in draws:
            cache = OperatorCache(tpl, workers=cfg.workers, dtype=dtype)
            flux = _correct(data, tpl, blocked, cfg, dtype, cache)[0]
            d = flux - finite_data
            d[blocked] = 0.0
            d -= moved
            acc += d * d
        return np.sqrt(acc / max(len(draws) - 1, 1))
