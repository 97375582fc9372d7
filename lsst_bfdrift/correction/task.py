"""BrighterFatterDriftTask: correct exposures with the template as Green's function.

The Task only wires plain functions: :func:`~lsst_bfdrift.correction.solvers.correct_image`
for the flux redistribution and :func:`~lsst_bfdrift.geometry.linear.linear_moment_maps`
(or :func:`~lsst_bfdrift.geometry.superpose.moment_maps`) for the final pixel geometry
predicted from the recorded image.
"""

import math
import os

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.nddata import CCDData, NDData

import lsst.pex.config as pexConfig

from lsst_bfdrift.utils.config import Struct, Task
from lsst_bfdrift.utils.io import read_image
from lsst_bfdrift.correction.solvers import (area_coefficients, correct_coulton18,
                                             correct_half_shift, correct_image,
                                             coulton18_kernel, refuse_out_of_range)
from lsst_bfdrift.geometry.linear import linear_moment_maps
from lsst_bfdrift.geometry.superpose import moment_maps
from lsst_bfdrift.templates.refine import draw_templates
from lsst_bfdrift.templates.swept import OperatorCache
from lsst_bfdrift.templates.template import DistortionTemplate, load_default_template
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["BrighterFatterDriftConfig", "BrighterFatterDriftTask", "unpack_exposure", "FLAG_BLOCKED",
           "FLAG_EDGE"]

#: Flag bit: pixel masked, saturated or non-finite (no flux exchanged).
FLAG_BLOCKED = 1
#: Flag bit: pixel within the template's reach of the image border (aggressors missing).
FLAG_EDGE = 2

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
        allowed={"float32": "single (half the time and memory)", "float64": "double"})
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
        doc="level (e) at and above which pixels are blocked; None: no limit", dtype=float,
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


def _correct(data, template, blocked, cfg, dtype, cache):
    """The configured correction of ``data`` with ``template``: (flux,
    iterations, converged, order, density, solver info)."""
    order = 2 if cfg.method == "astier23" else cfg.order
    density = "mean2" if cfg.method == "astier23" else cfg.density
    solver = {}
    if cfg.method == "astier23":
        flux, iterations, converged = correct_half_shift(
            data, template, blocked=blocked, workers=cfg.workers, dtype=dtype,
            strip=cfg.strip, cache=cache, check_range=False)
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
            cache=cache, info=solver, check_range=False)
    return flux, iterations, converged, order, density, solver


def unpack_exposure(exposure, gain_cfg):
    """data (float64, e; no copy when possible), mask, uncertainty, meta, unit, gain,
    kind."""
    kind = "ndarray"
    mask = unc = None
    meta = fits.Header()
    unit = u.electron
    if isinstance(exposure, (str, os.PathLike)):
        data, _, meta = read_image(exposure)  # a truncated file is named as such
        bunit = str(meta.get("BUNIT", "electron")).strip().lower()
        if bunit in _ADU_UNITS:
            unit = u.adu
        elif bunit in _ELECTRON_UNITS:
            unit = u.electron
        else:
            raise InputError(f"{os.fspath(exposure)}: BUNIT = {meta['BUNIT']!r} is not a charge "
                             "image; accepted: electron (e, e-, electrons) or ADU (adu, dn, "
                             "count)")
        kind = "path"
    elif isinstance(exposure, NDData):
        kind = "ccddata" if isinstance(exposure, CCDData) else "nddata"
        data = _as_float64(exposure.data)
        mask = None if exposure.mask is None else np.array(exposure.mask, bool)
        unc = exposure.uncertainty
        meta = fits.Header(exposure.meta) if exposure.meta else fits.Header()
        unit = exposure.unit if exposure.unit is not None else u.electron
    elif isinstance(exposure, np.ma.MaskedArray):
        kind = "masked"
        data = _as_float64(exposure.data)
        mask = np.array(np.ma.getmaskarray(exposure), bool)
    else:
        data = _as_float64(exposure)
    if data.ndim != 2:
        raise InputError(f"exposure must be a 2-d image, got shape {data.shape}")
    if 0 in data.shape:
        raise InputError(f"exposure is empty (shape {data.shape}); accepted: an image of at "
                         "least 1 x 1 pixels")
    if mask is not None and mask.shape != data.shape:
        raise InputError(f"mask shape {mask.shape} does not match image {data.shape}")
    gain = 1.0
    if unit in (u.adu, u.count) or str(unit).lower() in ("adu", "dn"):
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


class BrighterFatterDriftTask(Task):
    """Correct the brighter-fatter effect with an electrostatic template.

    ``run(exposure)`` predicts the final pixel boundaries from the recorded
    image with the template as Green's function, returns the pixel geometry
    maps and the flux-conserving correction.
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

    def run(self, exposure):
        """Correct ``exposure``.

        Parameters
        ----------
        exposure : CCDData, NDData, numpy.ma.MaskedArray, ndarray or path
            Image in electrons (or ADU with ``config.gain`` / a GAIN keyword).
            Masked pixels (NDData and MaskedArray masks) neither give nor
            receive charge and are flagged. A FITS file's BUNIT must say
            electron or ADU (other units, e.g. e/s or MJy/sr, are refused).
            Never modified.

        Returns
        -------
        Struct
            ``exposure`` (corrected, same type as given; mask and uncertainty
            carried; a MaskedArray's mask gains the blocked pixels), ``area``, ``centroid_x``, ``centroid_y`` (shift from the
            pixel centre, px), ``e1``, ``e2`` (None if ``compute_geometry`` is
            off), ``flux_moved`` (e; sums to zero), ``flux_moved_err`` (e; its
            standard deviation over templates drawn from the calibration
            uncertainty, None unless ``uncertainty_draws``), ``flags`` (uint8, bits
            FLAG_BLOCKED, FLAG_EDGE), ``iterations``, ``converged``.
        """
        cfg = self.config
        data, mask, unc, meta, unit, gain, kind = unpack_exposure(exposure, cfg.gain)
        finite = np.isfinite(data)
        all_finite = bool(finite.all())
        finite_data = data if all_finite else np.where(finite, data, 0.0)
        blocked = np.logical_not(finite, out=finite)
        if mask is not None:
            blocked |= mask
        if cfg.saturation is not None:
            blocked |= finite_data >= cfg.saturation
        dtype = np.float32 if cfg.fft_precision == "float32" else np.float64
        refuse_out_of_range(finite_data, self._operators(dtype).kernel_abs_sum,
                     f"; the image was converted with gain {gain} e/ADU" if gain != 1.0
                     else "; is the image in ADU without a gain?")
        # the maps first: their working arrays are freed before the solver's
        # outputs exist (peak memory, docs/benchmarks.rst)
        geom = dict(area=None, centroid_x=None, centroid_y=None, e1=None, e2=None)
        if cfg.compute_geometry:
            ns = cfg.geometry_samples
            samples = None if ns is None else min(ns, self.template.edge_samples)
            names = ("area", "dx", "dy", "e1", "e2")  # only those returned
            if cfg.geometry_method == "linear":
                maps = linear_moment_maps(self.template, finite_data, rtol=cfg.geometry_tolerance,
                                          samples=samples, workers=cfg.workers, dtype=dtype,
                                          maps=names)
            else:
                maps = moment_maps(self.template, finite_data, workers=cfg.workers, dtype=dtype,
                                   samples=samples, maps=names)
            geom = dict(area=maps.area, centroid_x=maps.dx, centroid_y=maps.dy, e1=maps.e1,
                        e2=maps.e2)
        flux, iterations, converged, order, density, solver = _correct(
            data, self.template, blocked, cfg, dtype, self._operators(dtype))
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
        header = fits.Header(meta)
        header["BFDRIFT"] = (True, "BF correction applied (lsst_bfdrift)")
        header["BFMETHOD"] = (cfg.method, "correction method")
        header["BFORDER"] = (order, "time-history series order")
        header["BFDENS"] = (density, "edge flux density estimate")
        header["BFITER"] = (iterations, "solver iterations")
        header["BFCONV"] = (bool(converged), "solver converged")
        if cfg.method == "drift":
            header["BFSOLVER"] = (solver.get("solver", "dense"), "drift series: sparse or dense")
        if cfg.compute_geometry:
            ns = self.template.edge_samples
            if cfg.geometry_samples is not None:
                ns = min(cfg.geometry_samples, ns)
            header["BFGSAMP"] = (ns, "edge samples of the geometry maps")
            header["BFGMETH"] = (cfg.geometry_method, "geometry maps: linear or exact")
        header["BFQTMPL"] = (self.template.charge, "template aggressor charge (e)")
        header["BFTMPL"] = (os.path.basename(str(cfg.template or "bundled default"))[-40:],
                            "BF template file")
        out_data = flux if gain == 1.0 else flux / gain  # flux: a new array of the solver
        if kind in ("ccddata", "nddata"):
            new_mask = blocked if mask is None else (mask | blocked)
            cls = CCDData if kind == "ccddata" else NDData
            out = cls(out_data, unit=unit, mask=new_mask, uncertainty=unc, meta=header)
        elif kind == "path":
            out = CCDData(out_data, unit=unit, mask=blocked, meta=header)
        elif kind == "masked":
            out = np.ma.MaskedArray(out_data, mask=mask | blocked)
        else:
            out = out_data
        if moved_err is not None:
            header["BFUNCN"] = (cfg.uncertainty_draws, "template draws of flux_moved_err")
        return Struct(exposure=out, flux_moved=moved, flux_moved_err=moved_err, flags=flags,
                      iterations=iterations, converged=bool(converged), header=header, **geom)

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
