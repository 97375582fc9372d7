"""The steps of one correction run, as plain functions.

:meth:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask.run` wires
them in this order: the image in electrons
(:func:`~lsst_bfdrift.images.electrons.to_electrons`), :func:`blocked_pixels`,
:func:`masked_aggressors`, the geometry maps (:func:`exact_maps` before the
correction or :func:`linear_maps` after it, from its first pass:
:func:`first_order_pass`), :func:`apply_method`, :func:`flux_moved`,
:func:`flux_moved_error`, :func:`edge_flags`, :func:`result_header` and the
output in the input's form (:func:`package_output`).
"""

import copy
import hashlib
import os

import numpy as np
from astropy.io import fits
from astropy.nddata import CCDData, NDData
from scipy.ndimage import uniform_filter

from lsst_bfdrift.correction.solvers import (MAX_SWEEP, area_coefficients, correct_coulton18,
                                             correct_half_shift, correct_image, coulton18_kernel)
from lsst_bfdrift.geometry.first_order import FirstOrderPass
from lsst_bfdrift.geometry.linear import first_order_route, linear_moment_maps
from lsst_bfdrift.geometry.superpose import moment_maps
from lsst_bfdrift.images.exposure import add_mask_plane
from lsst_bfdrift.templates.refine import draw_templates
from lsst_bfdrift.templates.swept import OperatorCache
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.version import __version__

__all__ = ["FLAG_BLOCKED", "FLAG_EDGE", "BF_PLANE_DOC", "MAP_NAMES", "LSST_METHOD",
           "blocked_pixels", "fill_masked", "masked_aggressors", "apply_method",
           "first_order_pass", "exact_maps", "linear_maps", "flux_moved", "flux_moved_error",
           "edge_flags", "template_digest", "result_header", "package_output"]

#: Flag bit: pixel masked, saturated or non-finite (no flux exchanged).
FLAG_BLOCKED = 1
#: Flag bit: pixel within the template's reach of the image border (aggressors missing).
FLAG_EDGE = 2
#: Description of the BF mask plane (afw's ``MPD_BF`` card).
BF_PLANE_DOC = ("BF correction incomplete: blocked (masked, saturated, non-finite) or within "
                "the template's reach of the border")
#: The geometry maps a run returns (of those the map functions can give).
MAP_NAMES = ("area", "dx", "dy", "e1", "e2")
#: ``LSST ISR BF CORR METHOD`` of each method (ip_isr's names where they apply).
LSST_METHOD = {"drift": "LSST_BFDRIFT", "astier23": "ASTIER23", "coulton18": "COULTON18"}


def blocked_pixels(image):
    """Pixels that neither give nor receive charge: the bad ones (masked,
    non-finite) and the saturated ones.

    Parameters
    ----------
    image : ElectronImage

    Returns
    -------
    ndarray of bool
        A new array.

    Raises
    ------
    InputError
        Every pixel is blocked: nothing to correct.
    """
    blocked = image.bad.copy()
    if image.saturated is not None:
        blocked |= image.saturated
    if blocked.all():
        nonfinite = int(np.count_nonzero(~np.isfinite(image.data)))
        masked = 0 if image.mask is None else int(np.count_nonzero(image.mask))
        raise InputError(f"{image.source}: every one of the {blocked.size} pixels is blocked "
                         f"({nonfinite} non-finite, {masked} masked, the rest saturated or "
                         "masked by the caller): there is no charge to correct")
    return blocked


def fill_masked(image, fill, blocked):
    """``image`` with the ``fill`` pixels replaced by the mean of the pixels that are
    not blocked in the 5 x 5 box around each (the image median where a box has none)."""
    good = ~blocked
    num = uniform_filter(np.where(good, image, 0.0), size=5, mode="constant")
    den = uniform_filter(good.astype(np.float64), size=5, mode="constant")
    fallback = float(np.median(image[good])) if good.any() else 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        local = np.where(den > 1e-9, num / np.where(den > 1e-9, den, 1.0), fallback)
    return np.where(fill, local, image)


def masked_aggressors(data, finite_data, mask, blocked, *, how, kernel_abs_sum):
    """The charge of masked pixels as aggressors (they never exchange flux).

    Their recorded charge (``how='keep'``), or the mean of their unmasked
    neighbours (``'interpolate'``, as ip_isr does); a pixel beyond the
    model's range is never charge the model can use, so it is always filled.

    Parameters
    ----------
    data, finite_data : ndarray
        The image (e), and the same with non-finite pixels set to 0.
    mask : ndarray of bool or None
        The input's own mask.
    blocked : ndarray of bool
    how : {'keep', 'interpolate'}
    kernel_abs_sum : float
        Of the template's swept-area kernels: a pixel above ``MAX_SWEEP /
        kernel_abs_sum`` e is beyond the model's range.

    Returns
    -------
    data, finite_data : ndarray
        New arrays where pixels were filled, else the inputs.
    fill : ndarray of bool or None
        The filled pixels (None: none).
    """
    if mask is None or not mask.any():
        return data, finite_data, None
    fill = mask.copy() if how == "interpolate" else \
        mask & (np.abs(finite_data) > MAX_SWEEP / kernel_abs_sum)
    if not fill.any():
        return data, finite_data, None
    finite_data = fill_masked(finite_data, fill, blocked)
    return np.where(fill, finite_data, data), finite_data, fill


def apply_method(data, template, blocked, cfg, dtype, cache, *, maps=None, progress=None):
    """The configured correction of ``data`` with ``template``.

    Parameters
    ----------
    data : ndarray
        e.
    template : DistortionTemplate
    blocked : ndarray of bool
    cfg : BrighterFatterDriftConfig
    dtype : numpy dtype
        FFT precision.
    cache : OperatorCache
        The template's operators.
    maps : FirstOrderPass, optional
        Filled by the astier23 pass and by the drift series' first-order pass
        when it is the sparse one.
    progress : callable, optional
        Called with the fraction done, as for
        :func:`~lsst_bfdrift.correction.solvers.correct_image` (drift) and
        :func:`~lsst_bfdrift.correction.solvers.correct_coulton18` (its
        iterations); astier23's single pass reports none.

    Returns
    -------
    flux : ndarray
    iterations : int
    converged : bool
    order, density : int or str
        As applied ('n/a' for coulton18).
    solver : dict
        The drift solver's info (``solver``: 'sparse' or 'dense').
    """
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
            workers=cfg.workers, progress=progress)
    else:
        flux, iterations, converged = correct_image(
            data, template, order=order, density=density, blocked=blocked,
            max_iter=cfg.max_iter, rtol=cfg.rtol, noise_tol=cfg.noise_tol, start=cfg.start,
            workers=cfg.workers, dtype=dtype, strip=cfg.strip, sparse=cfg.sparse,
            cache=cache, info=solver, check_range=False, maps=maps, progress=progress)
    return flux, iterations, converged, order, density, solver


def first_order_pass(template, image, cfg, *, samples, dtype, filled):
    """The first-order geometry maps the correction's first pass fills, or None.

    The linear maps take their first order from the correction's first pass
    when that pass applies the swept-area operator to the very image the
    maps are of: astier23, and drift with the sparse series; not when masked
    pixels were filled (``filled``), nor when the maps' windowed route is
    expected (:func:`~lsst_bfdrift.geometry.linear.first_order_route`: the
    first order then only in windows where the charge varies).
    """
    linear = cfg.compute_geometry and cfg.geometry_method == "linear"
    if not linear or filled or not (
            cfg.method == "astier23"
            or (cfg.method == "drift" and cfg.sparse and cfg.start == "series")):
        return None
    if first_order_route(template, image, rtol=cfg.geometry_tolerance,
                         samples=samples) == "windows":
        return None
    return FirstOrderPass(template, image.shape, maps=MAP_NAMES, samples=samples, dtype=dtype)


def _as_geometry(maps):
    return dict(area=maps.area, centroid_x=maps.dx, centroid_y=maps.dy, e1=maps.e1, e2=maps.e2)


def exact_maps(template, image, cfg, *, samples, dtype, report):
    """Exact polygon moment maps of ``image`` (:func:`~lsst_bfdrift.geometry.superpose.moment_maps`)
    as the Task returns them; ``report(stage, fraction)`` as the Task's progress."""
    report("maps", 0.0)
    rows = [0]

    def row_done(n):
        rows[0] += n
        report("maps", rows[0] / image.shape[0])

    maps = moment_maps(template, image, workers=cfg.workers, dtype=dtype, samples=samples,
                       maps=MAP_NAMES, progress=row_done)
    report("maps", 1.0)
    return _as_geometry(maps)


def linear_maps(template, image, cfg, *, samples, dtype, first, ops, report):
    """First-order maps with exact moments where needed
    (:func:`~lsst_bfdrift.geometry.linear.linear_moment_maps`), from the
    correction's first pass ``first`` when there is one."""
    report("maps", 0.0)
    maps = linear_moment_maps(
        template, image, rtol=cfg.geometry_tolerance, samples=samples, workers=cfg.workers,
        dtype=dtype, maps=MAP_NAMES, strip=image.shape[0] if cfg.strip is None else cfg.strip,
        first_order=first, ops=ops, check_range=False, map_dtype=dtype,
        progress=lambda f: report("maps", f))
    report("maps", 1.0)
    return _as_geometry(maps)


def flux_moved(flux, finite_data, blocked, fill, recorded):
    """The corrected flux with the filled pixels' recorded values back, and the
    flux moved (e; zero in blocked pixels).

    Returns
    -------
    flux, moved, finite_data : ndarray
        ``finite_data`` with the filled pixels at 0 (the image the flux moved is
        taken from).
    """
    if fill is not None:
        flux = np.where(fill, recorded, flux)
        finite_data = np.where(fill, 0.0, finite_data)
    moved = flux - finite_data
    moved[blocked] = 0.0
    return flux, moved, finite_data


def flux_moved_error(template, data, finite_data, blocked, moved, cfg, dtype):
    """Root-mean-square difference of the flux moved with templates drawn from the
    calibration uncertainty (:func:`~lsst_bfdrift.templates.refine.draw_templates`)
    from the flux moved with the template itself (``moved``).

    The draws scatter about the template, so the mean square is taken over the
    number of draws (no degree of freedom is spent on a sample mean).

    Returns
    -------
    ndarray
        e.
    """
    draws = draw_templates(template, cfg.uncertainty_draws, seed=cfg.uncertainty_seed)
    acc = np.zeros_like(moved)
    for tpl in draws:
        cache = OperatorCache(tpl, workers=cfg.workers, dtype=dtype)
        flux = apply_method(data, tpl, blocked, cfg, dtype, cache)[0]
        d = flux - finite_data
        d[blocked] = 0.0
        d -= moved
        acc += d * d
    return np.sqrt(acc / len(draws))


def edge_flags(blocked, reach):
    """Flags of a run: FLAG_BLOCKED where ``blocked``, FLAG_EDGE within ``reach``
    pixels of the border (the template's half size: aggressors missing).

    Returns
    -------
    ndarray of uint8
    """
    flags = blocked.astype(np.uint8)  # FLAG_BLOCKED = 1
    c = int(reach)
    for sl in (np.s_[:c], np.s_[-c:], np.s_[:, :c], np.s_[:, -c:]):
        flags[sl] |= FLAG_EDGE
    return flags


def template_digest(template):
    """First 16 hex digits of the sha1 of a template's displacements (its identity)."""
    h = hashlib.sha1()
    for name in ("corner_d", "vedge_d", "hedge_d", "fractions"):
        arr = getattr(template, name, None)
        if arr is not None:
            h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    h.update(repr(float(template.charge)).encode())
    return h.hexdigest()[:16]


def result_header(meta, cfg, template, *, warnings, order, density, iterations, converged,
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
    header["BFVERS"] = (__version__, "lsst_bfdrift version")
    header["BFNFILL"] = (filled, "masked pixels interpolated as aggressors")
    header["BFTSUM"] = (template_digest(template), "BF template digest (sha1, 16)")
    header["BFGAIN"] = (float(gain), "gain applied (e/ADU; 1: image in e)")
    if saturation is not None:
        header["BFSATUR"] = (saturation, "saturation level applied (e)")
    header["HIERARCH LSST ISR BF APPLIED"] = True
    header["HIERARCH LSST ISR BF CORR METHOD"] = LSST_METHOD[cfg.method]
    return header


def _bf_cards(header):
    return [c for c in header.cards if c.keyword.startswith(("BF", "LSST ISR BF"))]


def _nddata_out(image, out_data, blocked, flags, header, moved_err, plane):
    """A new CCDData or NDData: the input's meta as it was (values FITS cannot hold
    included) plus the BF keys; mask = the input's | blocked."""
    exposure = image.exposure
    new_mask = blocked if image.mask is None else (image.mask | blocked)
    cls = CCDData if image.kind == "ccddata" else NDData
    meta_out = copy.copy(exposure.meta) if exposure.meta else {}
    for card in _bf_cards(header):
        meta_out[card.keyword] = card.value
    unit = exposure.unit if image.unit.origin == "BUNIT" or (
        image.unit.origin == "memory" and exposure.unit is not None) else image.astropy_unit
    return cls(out_data, unit=unit, mask=new_mask, uncertainty=image.uncertainty, meta=meta_out, wcs=exposure.wcs)


def _exposure_out(image, out_data, blocked, flags, header, moved_err, plane):
    """A copy of the MaskedExposure with the corrected image, the BF plane and the
    correction's variance added (when ``flux_moved_err`` was computed).

    The BF and ``LSST ISR BF`` keys go where afw keeps the metadata
    (:meth:`~lsst_bfdrift.images.exposure.MaskedExposure.metadata`: the
    primary header of an LSST file with ``INHERIT``); an integer image
    becomes float32 (the corrected values are fractional)."""
    out = image.exposure.copy()
    dtype = image.exposure.image.dtype
    out.image = out_data.astype(np.float32 if dtype.kind in "iub" else dtype, copy=False)
    md = out.metadata()
    for card in _bf_cards(header):
        key = card.keyword
        name = f"HIERARCH {key}" if len(key) > 8 or " " in key else key
        md[name] = (card.value, card.comment)
    if out.mask is not None and out.layout != "ccddata":
        # a CCDData file's mask is boolean for its readers: the flags stay in
        # BFFLAGS rather than turn flagged (e.g. border) pixels into masked ones
        bit = add_mask_plane(out, plane, doc=BF_PLANE_DOC)
        out.mask = out.mask | np.where(flags != 0, np.int32(1 << bit), np.int32(0))
    if out.variance is not None and moved_err is not None:
        out.variance = out.variance + (moved_err / image.gain) ** 2
    return out


def _afw_out(image, out_data, blocked, flags, header, moved_err, plane):
    """A clone of an afw-like Exposure: image replaced, BF plane added (with its
    description where afw takes one), variance + flux_moved_err^2, keys set."""
    exposure = image.exposure
    out = exposure.clone() if hasattr(exposure, "clone") else copy.deepcopy(exposure)
    arr = out.image.array
    arr[...] = out_data.astype(arr.dtype, copy=False)
    try:
        bit = out.mask.addMaskPlane(plane, BF_PLANE_DOC)  # afw with plane docs
    except TypeError:
        bit = out.mask.addMaskPlane(plane)
    m = out.mask.array
    m |= np.where(flags != 0, 1 << int(bit), 0).astype(m.dtype)
    var = getattr(out, "variance", None)
    if moved_err is not None and var is not None and hasattr(var, "array"):
        var.array[...] += ((moved_err / image.gain) ** 2).astype(var.array.dtype)
    md = out.getMetadata()
    for card in _bf_cards(header):
        if hasattr(md, "set"):
            md.set(card.keyword, card.value)
        else:
            md[card.keyword] = card.value
    return out


def _path_out(image, out_data, blocked, flags, header, moved_err, plane):
    return CCDData(out_data, unit=image.astropy_unit, mask=blocked, meta=header)


def _masked_out(image, out_data, blocked, flags, header, moved_err, plane):
    return np.ma.MaskedArray(out_data, mask=image.mask | blocked)


def _array_out(image, out_data, blocked, flags, header, moved_err, plane):
    return out_data


#: How each kind of input comes back (``ElectronImage.kind``).
_OUTPUT_FORMS = {"ccddata": _nddata_out, "nddata": _nddata_out, "exposure": _exposure_out,
                 "afw": _afw_out, "path": _path_out, "masked": _masked_out,
                 "ndarray": _array_out}


def package_output(image, flux, blocked, flags, header, moved_err, *, plane):
    """The corrected image in the form the input had.

    Parameters
    ----------
    image : ElectronImage
        The input as read.
    flux : ndarray
        The corrected image (e); a new array of the solver.
    blocked, flags : ndarray
    header : astropy.io.fits.Header
        :func:`result_header`.
    moved_err : ndarray or None
        :func:`flux_moved_error` (e), added to a variance plane.
    plane : str
        Name of the mask plane the flags are set in.

    Returns
    -------
    object
        CCDData or NDData (a new one: the input's mask, uncertainty and meta
        carried), a MaskedExposure copy (a path gives a CCDData), an afw-like
        clone, a MaskedArray (its mask gains the blocked pixels) or an
        ndarray, in the input's unit.
    """
    out_data = flux if image.gain == 1.0 else flux / image.gain
    return _OUTPUT_FORMS[image.kind](image, out_data, blocked, flags, header, moved_err, plane)
