"""Geometry maps to first order in the charge, exact where that is not enough.

The first-order maps are convolutions of the charge image with fixed
kernels (:mod:`~lsst_bfdrift.geometry.first_order`). Where the charge is
high the neglected second-order terms matter, and the exact polygon moments
are computed there instead, on windows chosen by an a-priori bound
(:mod:`~lsst_bfdrift.geometry.bounds`): the maps returned by
:func:`linear_moment_maps` differ from the exact ``moment_maps`` (same
``samples``) by at most ``rtol`` times each map's signal in every pixel
(signal: the largest abs(map - nominal) over the image).

:func:`linear_moment_maps` wires these steps: the options and the charge
checked (:func:`_checked_names`, :func:`_checked_charge`); the first-order
maps (:func:`_first_order_pass`, :func:`_complete_first_order`); the exact
second-order terms of the image's uniform level near its border
(:func:`_add_border_terms`); the a-priori bound and the bins where it
exceeds the tolerance (:func:`_exact_flags`); the exact moments there
(:func:`_add_exact_moments`: in windows, or on the whole image when the
windows would cover most of it); the maps assembled
(:func:`_assembled`). Without a first-order pass given, the windowed route
(:func:`_windowed_route`, :func:`_windowed_maps_out`; the pieces in
:mod:`~lsst_bfdrift.geometry._windowed`) computes the first order only
where the charge varies, when :func:`first_order_route` expects it to pay.
"""

import threading

import numpy as np

from lsst_bfdrift.templates.swept import OperatorCache, kernel_abs_sum, refuse_out_of_range
from lsst_bfdrift.geometry._exact import exact_boxes, exact_windows
from lsst_bfdrift.geometry._windowed import (_index_map, expected_route, first_order_bound,
                                             signal_floor, windowed_maps)
from lsst_bfdrift.geometry.bounds import (bin_abs_dev, displacement_bound,
                                          pixel_displacement_bound, reference_level,
                                          second_order_bounds)
from lsst_bfdrift.geometry.first_order import (LINEAR_MAPS, FirstOrderPass,
                                               convolved_first_order_maps, linear_kernels)
from lsst_bfdrift.geometry.superpose import (MomentMaps, check_charge_image, moment_maps,
                                             resample_template, superpose_boundaries)
from lsst_bfdrift.utils.errors import InputError

__all__ = ["MEASURED_CONSTANTS", "error_bounds", "linear_moment_maps", "first_order_route"]

#: abs(exact - linear) <= C eps**2 per map (eps: the pixel's largest boundary
#: displacement component, px; eps <= 0.05): twice the largest ratio measured
#: on star fields (up to a 1.5e6 e star) and 1e5 e flats with the bundled
#: template (1.9, 0.75, 0.76, 1.9, 10.5; ``tests/geometry/test_linear.py``
#: checks them), at most the analytic bounds of :func:`~.second_order_bounds`
#: (4, 12.8, 12.8, 126, 228 for small eps). These make the default
#: ``bound='measured'`` of :func:`linear_moment_maps`.
MEASURED_CONSTANTS = dict(area=4.0, dx=1.6, dy=1.6, e1=4.0, e2=21.0)


_CLASSES = {}
_CLASSES_LOCK = threading.Lock()


def _bin_classes(m, b, nb):
    """The distinct sets of indices of ``m`` held by its ``nb`` bins of ``b``
    (a list of tuples) and each bin's set; kept for the last few maps (the
    same for every image of a shape)."""
    key = (m.tobytes(), int(b), int(nb))
    with _CLASSES_LOCK:  # shared by the threads of a dask worker
        if key not in _CLASSES:
            if len(_CLASSES) >= 8:
                _CLASSES.pop(next(iter(_CLASSES)))
            keys, idx = {}, np.empty(nb, np.int64)
            for k in range(nb):
                idx[k] = keys.setdefault(tuple(np.unique(m[k * b:(k + 1) * b])), len(keys))
            _CLASSES[key] = (list(keys), idx)
        return _CLASSES[key]


def _binned_eps(eps, rowmap, colmap, b, nby, nbx):
    """Largest ``eps[rowmap[j], colmap[i]]`` over every b x b bin (the bins
    classed by the indices they hold: a few near the borders, one inside)."""
    ky, iy = _bin_classes(rowmap, b, nby)
    kx, ix = _bin_classes(colmap, b, nbx)
    table = np.array([[eps[np.ix_(a, c)].max() for c in kx] for a in ky])
    # C order (``table[iy][:, ix]`` is Fortran-ordered: the callers' in-place
    # arithmetic with C-ordered arrays then ran 15 times slower)
    return np.take(table[iy], ix, axis=1)


def _uniform_response(template, lk, qbar, samples):
    """Exact minus linear maps (5, n, n), the largest boundary displacement
    (n, n) and the linear maps (5, n, n; nominal included) of the pixels of a
    uniform image of level ``qbar`` (e), n = 2 reach + 1.

    Pixel (j, i) of an image of at least n x n pixels responds to a uniform
    level as pixel (rowmap(j), colmap(i)) of this one (:func:`_index_map`):
    only its distances to the image borders, up to the reach, matter.
    """
    n = 2 * lk.reach + 1
    qs = np.full((n, n), float(qbar))
    ex = moment_maps(template, qs, samples=samples, maps=LINEAR_MAPS)
    lin, _ = convolved_first_order_maps(lk, qs, LINEAR_MAPS, tile=(n, n),
                                        dtype=np.float64)
    corr = np.stack([getattr(ex, k) - v for k, v in zip(LINEAR_MAPS, lin)])
    t = resample_template(template, lk.samples)
    g = superpose_boundaries(t, qs)
    nom = g.nominal()
    c = np.abs(g.corners - nom.corners).max(-1)
    v = np.abs(g.vedge - nom.vedge).max(-1)
    h = np.abs(g.hedge - nom.hedge).max(-1)
    if g.vedge_t is not None:
        v = np.maximum(v, np.abs(g.vedge_t).max(-1))
        h = np.maximum(h, np.abs(g.hedge_t).max(-1))
    eps = np.maximum.reduce([c[:-1, :-1], c[1:, :-1], c[:-1, 1:], c[1:, 1:],
                             v[:, :-1], v[:, 1:], h[:-1], h[1:]])
    return corr, eps, np.stack(lin)


def _bound_terms(template, lk, q, *, bin, samples, workers, qbar, uniform=None,
                 bin_sums=None):
    """``D`` and ``eps_u`` per bin (px) of :func:`error_bounds` (``uniform``:
    :func:`_uniform_response`'s result if already computed; ``bin_sums``:
    :func:`~.bin_abs_dev` with nothing outside, for an image of at least the
    uniform one's size)."""
    b = int(bin)
    qbar = reference_level(q) if qbar is None else float(qbar)
    ny, nx = q.shape
    n = 2 * lk.reach + 1
    nby, nbx = -(-ny // b), -(-nx // b)
    if ny >= n and nx >= n:
        d = displacement_bound(lk, q, bin=b, workers=workers, qbar=qbar, outside=0.0,
                               bin_sums=bin_sums)
        d += abs(qbar) * lk.net
        eps_small = (_uniform_response(template, lk, qbar, samples) if uniform is None
                     else uniform)[1]
        eps_u = _binned_eps(eps_small, _index_map(ny, n), _index_map(nx, n), b, nby, nbx)
    else:
        d = displacement_bound(lk, q, bin=b, workers=workers, qbar=qbar)
        eps_u = np.zeros_like(d)
    return d, eps_u


def error_bounds(template, q, *, samples=None, bin=2, bound="measured", workers=1,
                 qbar=None):
    """A-priori bound of abs(maps - exact maps) per bin, for :func:`linear_moment_maps`.

    Parameters
    ----------
    template : DistortionTemplate
    q : ndarray, shape (ny, nx), float64
        Charge (e), finite.
    samples : int, optional
        Samples per edge of the exact maps.
    bin : int, optional
        Bin side (px).
    bound : {'measured', 'analytic'}, optional
        See :func:`linear_moment_maps`.
    workers : int, optional
        FFT threads.
    qbar : float, optional
        Reference level (e); default: a median of the image.

    Returns
    -------
    dict
        Per map of :data:`LINEAR_MAPS`, an array of shape
        (ceil(ny / bin), ceil(nx / bin)) (map units).

    Notes
    -----
    The displacement d of a pixel's boundary is that of the uniform level
    ``qbar`` over the image, d_u (largest component eps_u, exact: computed
    on a small uniform image, :func:`_uniform_response`; non-zero within the
    reach of the image border), plus that of ``q - qbar``, whose components
    are at most D (:func:`~.displacement_bound` with nothing outside). The
    linear maps of :func:`linear_moment_maps` include the exact second-order
    terms of d_u; what is left of the remainder R (quadratic to the order
    that matters) is ``R(d_u + d_f) - R(d_u) = 2 B(d_u, d_f) + R(d_f)``, and
    with abs(R(d)) <= C eps**2 the polarisation identity gives abs(2 B(x, y))
    <= 4 C eps_x eps_y: the bound is ``C (4 eps_u D + D**2)`` with C the
    :data:`MEASURED_CONSTANTS`. With ``bound='analytic'``: twice
    :func:`~.second_order_bounds` of ``eps_u + D`` (the remainders at d and at
    d_u, each bounded).
    Images smaller than the uniform one (2 reach + 1 pixels) use ``eps_u``
    = 0 and D with ``abs(qbar)`` outside the image (the whole displacement).
    """
    lk = linear_kernels(template, samples=samples)
    d, eps_u = _bound_terms(template, lk, q, bin=bin, samples=samples, workers=workers,
                            qbar=qbar)
    if bound == "measured":
        x = d * (4.0 * eps_u + d)
        return {k: np.where(eps_u + d <= 0.05, MEASURED_CONSTANTS[k] * x, np.inf)
                for k in LINEAR_MAPS}
    an = second_order_bounds(eps_u + d, lk.chi)
    return {k: 2.0 * an[k] for k in LINEAR_MAPS}


def first_order_route(template, charge, *, rtol=1e-3, samples=None, bin=2, window_fraction=0.3):
    """The first-order route :func:`linear_moment_maps` expects to take with
    ``route='auto'`` (its guess from a sample of the image, before the bound).

    Parameters
    ----------
    template : DistortionTemplate
    charge : ndarray, shape (ny, nx), float64
        Charge (e), finite.
    rtol : float, optional
        As for :func:`linear_moment_maps`.
    samples : int, optional
        As for :func:`linear_moment_maps`.
    bin : int, optional
        As for :func:`linear_moment_maps`.
    window_fraction : float, optional
        As for :func:`linear_moment_maps`.

    Returns
    -------
    str
        'windows' when the sky's noise leaves room for windows and the
        sources' windows would cover at most ``window_fraction`` of the
        image by the estimate of :func:`~._windowed.expected_route` (the
        bound may still find that they cover more), else 'full' (also for
        an image smaller than 2 reach + 1 pixels a side).

    Notes
    -----
    A caller that computes the first-order maps itself (the Task, from the
    correction's first pass) skips that work when this says 'windows'. It
    costs a pass for the image's extreme pixel and the first-order maps of
    a box around it (about 30 ms on a 4096 x 4096 image), and one more
    pass (about 40 ms) when the sky leaves room for windows.
    """
    q = np.asarray(charge, dtype=np.float64)
    lk = linear_kernels(template, samples=samples)
    n = 2 * lk.reach + 1
    if q.ndim != 2 or q.shape[0] < n or q.shape[1] < n:
        return "full"
    qbar = reference_level(q)
    floor, _ = signal_floor(lk, q, qbar)
    return expected_route(lk, q, qbar, floor, float(rtol), bin=bin,
                          window_fraction=window_fraction)


def _refined_flag(lk, q, flag, b, qbar, eps_small, threshold):
    """The flagged ``b`` x ``b`` bins whose pixels, with the bound of each pixel
    (:func:`~.pixel_displacement_bound`, no bins), still exceed ``threshold``
    (``D (4 eps_u + D)``) or the displacement 0.05 px."""
    ny, nx = q.shape
    n = eps_small.shape[0]
    by, bx = np.nonzero(flag)
    oy, ox = np.divmod(np.arange(b * b), b)
    rows = (by[:, None] * b + oy[None, :]).ravel()
    cols = (bx[:, None] * b + ox[None, :]).ravel()
    keep = (rows < ny) & (cols < nx)
    rows, cols = rows[keep], cols[keep]
    d = pixel_displacement_bound(lk, q, rows, cols, qbar=qbar, outside=0.0)
    d += abs(qbar) * lk.net
    eu = eps_small[_index_map(ny, n)[rows], _index_map(nx, n)[cols]]
    hit = (eu + d > 0.05) | (d * (4.0 * eu + d) > threshold)
    out = np.zeros_like(flag)
    out[rows[hit] // b, cols[hit] // b] = True
    return out


def linear_moment_maps(template, charge, *, mask=None, rtol=1e-3, samples=None, fallback=True,
                       bound="measured", bin=2, max_fraction=0.5, workers=1,
                       dtype=np.float32, strip=512, maps=None, info=None, first_order=None,
                       ops=None, refine=True, check_range=True, map_dtype=np.float64,
                       progress=None, route="auto", window_fraction=0.3):
    """Area, centroid-shift and ellipticity maps: linear, exact where needed.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    charge : array_like, 2-d
        Collected charge (e), ``charge[j, i]``.
    mask : array_like of bool, optional
        Pixels that do not act as aggressors (their geometry is still computed).
    rtol : float, optional
        Largest error allowed in any pixel against the exact maps
        (``moment_maps`` with the same ``samples``), as a fraction of each
        map's signal S (the largest abs(map - nominal) over the image:
        abs(area - 1), abs(dx), ..., of the linear maps; the error is also
        at most ``rtol / (1 - rtol)`` of the exact maps' signal).
        Nine tenths of it is given to the linearisation, a tenth to the
        rounding of single-precision transforms.
    samples : int, optional
        Samples per edge of the exact fallback
        (:func:`~lsst_bfdrift.geometry.superpose.resample_template`); None:
        the template's own.
    fallback : bool, optional
        Compute the exact moments where the bound exceeds the tolerance
        (False: the linear maps everywhere, for tests and timing).
    bound : {'measured', 'analytic'}, optional
        Second-order bound per pixel, ``C eps**2`` with ``eps`` the
        displacement bound: 'measured' (:data:`MEASURED_CONSTANTS`) or
        'analytic' (:func:`~.second_order_bounds`: a proof, but 2 to 60 times
        the measured worst case, so that a faint field's sky noise alone
        may exceed it and every pixel becomes exact).
    bin : int, optional
        Side (px) of the bins of the a-priori bound (:func:`~.displacement_bound`).
    max_fraction : float, optional
        When the exact windows (with their margins) would cover more than
        this fraction of the image, ``moment_maps`` runs on the whole image.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float32, numpy.float64}, optional
        Precision of the FFTs (linear maps and exact fallback).
    strip : int, optional
        Rows per block of the first-order pass (each with a halo of the
        template's reach) and of the exact fallback.
    maps : sequence of str, optional
        Maps to keep, of :data:`LINEAR_MAPS` (default: all five).
    info : dict, optional
        Filled with ``method`` ('linear', 'linear+exact' or 'exact'),
        ``route`` ('full' or 'windows'), ``first_order_fraction`` (pixels of
        the first-order convolutions, margins included, over the image
        size: 1 on the full route), ``first_order_windows`` (their number,
        windowed route only), ``signal`` (S per map), ``tolerance``
        (per map), ``windows``,
        ``exact_fraction`` (flagged bins' share of the image) and
        ``canvas_fraction`` (pixels run through ``moment_maps``, margins
        included, over the image size).
    first_order : FirstOrderPass, optional
        The first-order maps of ``charge`` (same ``maps`` and ``samples``)
        from a correction's first pass
        (:func:`~lsst_bfdrift.correction.series.first_order_terms`), its
        rows not yet done computed here; its arrays become the maps
        returned. None: all computed here.
    ops : OperatorCache, optional
        Swept-area operators of ``template`` in ``dtype`` (kept kernel
        transforms) for the first-order pass; None: made for this call.
    refine : bool, optional
        With ``bound='measured'``, bound the displacements of the pixels of
        the flagged bins again pixel by pixel
        (:func:`~.pixel_displacement_bound`) and keep only the bins where
        that bound still exceeds the tolerance (images of at least 2 reach
        + 1 pixels a side).
    check_range : bool, optional
        Refuse a float64, finite, unmasked ``charge`` beyond the model's
        range (:func:`~lsst_bfdrift.templates.swept.refuse_out_of_range`);
        the Task has checked it before it calls. Other inputs are always
        checked.
    progress : callable, optional
        Called with the fraction (0 to 1, never decreasing) of the work done:
        the first-order maps by blocks of rows (unless ``first_order`` is
        complete), the bound, then the exact moments by rows of the image or
        of their boxes; 1 at the end. It does not change the maps.
    route : {'auto', 'full', 'windows'}, optional
        How the first-order maps are computed without ``first_order``:
        'full', over the whole image; 'windows', the uniform level's response
        (exact) everywhere and the first order only in windows where an
        a-priori bound of the rest exceeds what the tolerance leaves
        (:mod:`~lsst_bfdrift.geometry._windowed`; same accuracy contract);
        'auto', the windows when a sample of the image says the sky's noise
        leaves room for them and they cover at most ``window_fraction`` of
        the image, else the full route. The windows need ``fallback``,
        ``bound='measured'`` and an image of at least 2 reach + 1 pixels a
        side (else the full route is taken); 'windows' with ``first_order``
        or ``bound='analytic'`` is refused.
    window_fraction : float, optional
        Largest share of the image the windows' canvas (margins included)
        may cover on the 'auto' route.

    Returns
    -------
    MomentMaps
        ``area`` (float64), ``dx``, ``dy``, ``e1``, ``e2`` (``map_dtype``;
        the second moments ``ixx``, ``iyy``, ``ixy`` are None).

    Notes
    -----
    Single-precision transforms round the linear maps to about 2e-7 of
    their signal (measured; the test suite checks < 1e-5). Within the
    template's reach of the image border the maps include the exact
    second-order terms of the image's uniform level (a median; computed on a
    small uniform image). The bound (:func:`error_bounds`, per ``bin`` x
    ``bin`` pixels) decides where the exact moments are needed: where it
    exceeds ``0.9 rtol S`` for any map. The signal S is that of the
    first-order maps before the border terms (within 1.2 % of the exact
    maps' on a 1e5 e flat, whose signal is at its border; the factor 0.9
    covers it).

    On the windowed route the maps outside the windows are the first-order
    maps of the uniform level plus its border terms: the exact maps of a
    uniform image. They differ from the first-order maps of the image by at
    most ``beta_k`` (the first-order response of ``q - qbar``, bounded per
    bin), and from the exact maps by at most ``beta_k + C_k x`` (the
    second-order bound of :func:`error_bounds`); the windows cover every
    bin where that sum may exceed 0.999 ``rtol S_k`` (no single-precision
    rounding there: the uniform maps are computed in double precision). The
    bound and the exact flags use a lower bound of S (the first-order maps
    around the pixel farthest from the reference level, always in a window);
    S is then the largest abs(map - nominal) of the first-order maps so
    assembled.

    Examples
    --------
    A bright star on a sky of 1000 e: every map within ``rtol`` (1e-3) of
    its signal from the exact polygon moments, which are taken only around
    the star:

    >>> import numpy as np
    >>> from lsst_bfdrift import load_default_template, moment_maps
    >>> from lsst_bfdrift.geometry import linear_moment_maps
    >>> yy, xx = np.mgrid[:64, :64] - 32.0
    >>> q = 1000.0 + 1e6 / (2 * np.pi * 1.5**2) * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2)
    >>> t = load_default_template()
    >>> info = {}
    >>> lin = linear_moment_maps(t, q, info=info)
    >>> exact = moment_maps(t, q)
    >>> info["method"]
    'linear+exact'
    >>> [bool(np.abs(getattr(lin, k) - getattr(exact, k)).max()
    ...       <= 1e-3 * np.abs(getattr(exact, k) - (k == "area")).max())
    ...  for k in ("area", "dx", "dy", "e1", "e2")]
    [True, True, True, True, True]
    """
    names = _checked_names(maps, dtype=dtype, bound=bound, rtol=rtol, strip=strip, bin=bin)
    _check_route(route, window_fraction, bound=bound, first_order=first_order)
    info = {} if info is None else info
    q = _checked_charge(template, charge, mask=mask, check_range=check_range)
    lk = linear_kernels(template, samples=samples)
    report = _reporter(progress)
    qbar = reference_level(q)
    if route != "full" and first_order is None and fallback:
        report(0.0)
        win = _windowed_route(template, lk, q, qbar, names, rtol=rtol, bin=bin,
                              force=route == "windows", refine=refine, samples=samples,
                              workers=workers, dtype=dtype, strip=strip, map_dtype=map_dtype,
                              window_fraction=window_fraction)
        if win is not None:
            return _windowed_maps_out(template, lk, q, qbar, names, win, info, rtol=rtol,
                                      bin=bin, max_fraction=max_fraction, samples=samples,
                                      workers=workers, dtype=dtype, strip=strip, report=report)
    first_order = _first_order_pass(template, q, first_order, names=names, samples=samples,
                                    map_dtype=map_dtype)
    # rough shares of the time: the first-order pass (when it runs here), the
    # bound, then the exact moments
    first_share = 0.0 if first_order.complete else 0.4 if fallback else 1.0
    bound_share = first_share + 0.3 * (1.0 - first_share)
    report(0.0)
    # 1. the first-order maps
    _complete_first_order(template, q, first_order, ops, workers=workers, dtype=dtype,
                          strip=strip, report=report, share=first_share)
    out = _assembled(names, first_order.outs)
    signal = dict(zip(LINEAR_MAPS, first_order.smax.tolist()))
    tol = {k: 0.9 * rtol * v for k, v in signal.items()}
    info.update(method="linear", route="full", first_order_fraction=1.0, signal=signal,
                tolerance=tol, windows=0, exact_fraction=0.0, canvas_fraction=0.0)
    # 2. the exact second-order terms of the uniform level near the border
    uniform = _add_border_terms(template, lk, q, qbar, first_order.outs, names, samples=samples)
    if not fallback:
        report(1.0)
        return out
    # 3. the a-priori bound: where the exact moments are needed
    flag = _exact_flags(template, lk, q, qbar, tol, uniform, bound=bound, bin=bin,
                        samples=samples, workers=workers, refine=refine)
    report(bound_share)
    if not flag.any():
        report(1.0)
        return out

    def exact(fraction):
        report(bound_share + (1.0 - bound_share) * min(fraction, 1.0))

    # 4. the exact moments there, in windows (or on the whole image)
    _add_exact_moments(template, q, flag, first_order.outs, names, info, reach=lk.reach,
                       bin=bin, max_fraction=max_fraction, samples=samples, workers=workers,
                       dtype=dtype, strip=strip, progress=None if progress is None else exact)
    report(1.0)
    return out


def _checked_names(maps, *, dtype, bound, rtol, strip, bin):
    """The maps to keep (``maps``, default all of :data:`LINEAR_MAPS`), once
    the options of :func:`linear_moment_maps` are checked."""
    names = LINEAR_MAPS if maps is None else tuple(maps)
    unknown = sorted(set(names) - set(LINEAR_MAPS))
    if unknown:
        raise InputError(f"unknown linear maps {unknown}; choose from {list(LINEAR_MAPS)}")
    if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise InputError(f"dtype must be float64 or float32, got {dtype!r}")
    if bound not in ("measured", "analytic"):
        raise InputError(f"bound must be 'measured' or 'analytic', got {bound!r}")
    if not 0.0 < float(rtol) < 1.0:
        raise InputError(f"rtol must be between 0 and 1, got {rtol!r}")
    if int(strip) < 1 or int(bin) < 1:
        raise InputError(f"strip and bin must be positive, got {strip!r}, {bin!r}")
    return names


def _check_route(route, window_fraction, *, bound, first_order):
    """Refuse an unknown ``route``, a ``window_fraction`` outside (0, 1], and
    'windows' with ``first_order`` or ``bound='analytic'``."""
    if route not in ("auto", "full", "windows"):
        raise InputError(f"route must be 'auto', 'full' or 'windows', got {route!r}")
    if not 0.0 < float(window_fraction) <= 1.0:
        raise InputError(f"window_fraction must be in (0, 1], got {window_fraction!r}")
    if route == "windows" and (first_order is not None or bound != "measured"):
        raise InputError("route='windows' needs bound='measured' and no first_order (the "
                         "windows replace the first-order pass)")


def _windowed_route(template, lk, q, qbar, names, *, rtol, bin, force, refine, samples,
                    workers, dtype, strip, map_dtype, window_fraction):
    """The windowed route's first-order maps, or None when the full route is
    to be taken (an image smaller than the uniform one, a zero signal, the
    sample's guess (:func:`~._windowed.expected_route`) or windows covering
    more than ``window_fraction`` of the image, unless ``force``).

    Returns
    -------
    dict or None
        ``outs`` (the maps, ``names`` order), ``smax`` (signal per map),
        ``flag`` (bins of the exact moments, with the signal's lower bound),
        ``uniform`` (:func:`_uniform_response`), ``windows`` (boxes) and
        ``size`` (pixels of their canvas).
    """
    ny, nx = q.shape
    r = lk.reach
    n = 2 * r + 1
    if ny < n or nx < n:
        return None
    floor, fbox = signal_floor(lk, q, qbar)
    if not np.all(floor > 0.0) or (not force and expected_route(
            lk, q, qbar, floor, rtol, bin=bin, window_fraction=window_fraction) == "full"):
        return None
    uniform = _uniform_response(template, lk, qbar, samples)
    tol = {k: 0.9 * rtol * v for k, v in zip(LINEAR_MAPS, floor.tolist())}
    g = bin_abs_dev(q, qbar, bin, 0.0)  # shared by both bounds
    flag, x = _exact_flags(template, lk, q, qbar, tol, uniform, bound="measured", bin=bin,
                           samples=samples, workers=workers, refine=refine, keep_x=True,
                           bin_sums=g)
    w = 1.0 / (rtol * floor)
    # beta_k / (rtol S_k) <= m; C_k x / (rtol S_k) <= y, at most 0.9 where
    # the exact moments are not taken (their threshold)
    m = first_order_bound(lk, q, qbar, w, bin=bin, workers=workers, bin_sums=g)
    c = max(MEASURED_CONSTANTS[k] * w[i] for i, k in enumerate(LINEAR_MAPS))
    x *= c
    np.minimum(x, 0.9, out=x)
    m += x
    need = (m > 0.999) & ~flag
    del m, x
    b = int(bin)
    boxes = exact_boxes(need, b, q.shape, band=-(-r // b)) + [fbox]
    canvas = sum((y1 - y0 + 2 * r) * (x1 - x0 + 2 * r) for y0, y1, x0, x1 in boxes)
    if not force and canvas > window_fraction * q.size:
        return None
    outs, smax, size = windowed_maps(lk, q, boxes, uniform[2], names, map_dtype=map_dtype,
                                     dtype=dtype, workers=workers, strip=strip)
    return dict(outs=outs, smax=np.maximum(smax, floor), flag=flag, uniform=uniform,
                windows=boxes, size=size)


def _windowed_maps_out(template, lk, q, qbar, names, win, info, *, rtol, bin, max_fraction,
                       samples, workers, dtype, strip, report):
    """The maps of the windowed route (:func:`_windowed_route`'s ``win``):
    border terms added, exact moments where flagged; ``info`` filled."""
    out = _assembled(names, win["outs"])
    signal = dict(zip(LINEAR_MAPS, win["smax"].tolist()))
    info.update(method="linear", route="windows", first_order_fraction=win["size"] / q.size,
                first_order_windows=len(win["windows"]), signal=signal,
                tolerance={k: 0.9 * rtol * v for k, v in signal.items()}, windows=0,
                exact_fraction=0.0, canvas_fraction=0.0)
    _add_border_terms(template, lk, q, qbar, win["outs"], names, samples=samples,
                      uniform=win["uniform"])
    report(0.5)
    if win["flag"].any():
        def exact(fraction):
            report(0.5 + 0.5 * min(fraction, 1.0))

        _add_exact_moments(template, q, win["flag"], win["outs"], names, info, reach=lk.reach,
                           bin=bin, max_fraction=max_fraction, samples=samples,
                           workers=workers, dtype=dtype, strip=strip, progress=exact)
    report(1.0)
    return out


def _checked_charge(template, charge, *, mask, check_range):
    """The charge image (float64): ``charge`` itself when it is a finite,
    unmasked float64 image (refused beyond the model's range if
    ``check_range``), else a checked copy (:func:`~.check_charge_image`)."""
    q = np.asarray(charge)
    if mask is not None or q.dtype != np.float64 or q.ndim != 2 or q.size == 0 \
            or not np.isfinite(q).all():
        return check_charge_image(charge, mask=mask, template=template)
    if check_range:
        refuse_out_of_range(q, kernel_abs_sum(template))  # the package's one range check
    return q


def _reporter(progress):
    """A function reporting a fraction of the work done to ``progress`` (None:
    to nobody)."""
    def report(fraction):
        if progress is not None:
            progress(fraction)

    return report


def _first_order_pass(template, q, first_order, *, names, samples, map_dtype):
    """``first_order`` (checked against the image's shape and the maps), or a
    new :class:`~.FirstOrderPass` with no row done."""
    if first_order is None:
        return FirstOrderPass(template, q.shape, maps=names, samples=samples, dtype=map_dtype)
    if first_order.shape != q.shape or first_order.names != names:
        raise InputError("first_order must be a FirstOrderPass of this image's shape and maps")
    return first_order


def _complete_first_order(template, q, first_order, ops, *, workers, dtype, strip, report,
                          share):
    """Run the rows of ``first_order`` not yet done, ``strip`` rows per block,
    with the operators ``ops`` (checked; None: made here); the rows' progress
    is reported as ``share`` of the whole."""
    if first_order.complete:
        return
    if ops is None:
        ops = OperatorCache(template, workers=workers, dtype=dtype)
    elif not ops.matches(template, ops.workers, dtype):
        raise InputError("ops must be an OperatorCache made for this template and dtype")
    done = first_order.rows / q.shape[0]
    first_order.run(q, ops, rows=int(strip),
                    progress=lambda f: report(share * (f - done) / (1.0 - done)))


def _assembled(names, outs):
    """The :class:`~.MomentMaps` whose maps ``names`` are the arrays ``outs``
    (the others None); the steps after it fill the arrays in place."""
    out = MomentMaps((0, 0), ())
    for name, arr in zip(names, outs):
        setattr(out, name, arr)
    return out


def _add_border_terms(template, lk, q, qbar, outs, names, *, samples, uniform=None):
    """Add to the maps ``outs`` (``names`` order), within the template's reach
    of the image border, the exact second-order terms of the uniform level
    ``qbar`` (:func:`_uniform_response`).

    Returns :func:`_uniform_response`'s result (``uniform`` when given:
    already computed), or None for an image smaller than the uniform one (2
    reach + 1 pixels a side), left unchanged.
    """
    ny, nx = q.shape
    r = lk.reach
    n = 2 * r + 1
    if ny < n or nx < n:
        return None
    if uniform is None:
        uniform = _uniform_response(template, lk, qbar, samples)
    corr = uniform[0]
    rm, cm = _index_map(ny, n), _index_map(nx, n)
    for k, name in enumerate(LINEAR_MAPS):
        if name not in names:
            continue
        o = outs[names.index(name)]
        c = corr[k]
        for rows in (slice(0, r), slice(ny - r, ny)):
            o[rows] += c[rm[rows]][:, cm]
        for cols in (slice(0, r), slice(nx - r, nx)):
            o[r:ny - r, cols] += c[r, cm[cols]]
    return uniform


def _exact_flags(template, lk, q, qbar, tol, uniform, *, bound, bin, samples, workers, refine,
                 keep_x=False, bin_sums=None):
    """The ``bin`` x ``bin`` bins where the a-priori bound (:func:`error_bounds`)
    exceeds the tolerance ``tol`` of some map: where the exact moments are
    needed (bool, shape (ceil(ny / bin), ceil(nx / bin))).

    With ``bound='measured'`` the bound is computed once for all maps (one
    threshold) and, with ``refine``, the flagged bins are bounded again pixel
    by pixel (:func:`_refined_flag`); ``uniform`` is the border terms'
    :func:`_uniform_response` (None: an image smaller than the uniform one).
    With ``keep_x`` (``bound='measured'``) also returns ``x = D (4 eps_u + D)``
    per bin (px^2): each map's second-order bound is ``C_k x``. ``bin_sums``:
    as for :func:`_bound_terms`.
    """
    if bound != "measured":
        bounds = error_bounds(template, q, samples=samples, bin=bin, bound=bound,
                              workers=workers, qbar=qbar)
        flag = np.zeros(bounds["area"].shape, bool)
        for k in LINEAR_MAPS:
            flag |= bounds[k] > tol[k]
        return flag
    # error_bounds' C_k x > tol_k for some map k, x = D (4 eps_u + D): one
    # threshold on x; and everywhere eps_u + D > 0.05
    d, eps_u = _bound_terms(template, lk, q, bin=bin, samples=samples, workers=workers,
                            qbar=qbar, uniform=uniform, bin_sums=bin_sums)
    threshold = min(tol[k] / MEASURED_CONSTANTS[k] for k in LINEAR_MAPS)
    flag = eps_u + d > 0.05
    eps_u *= 4.0
    eps_u += d
    eps_u *= d
    flag |= eps_u > threshold
    del d
    if refine and uniform is not None and flag.any():
        flag = _refined_flag(lk, q, flag, int(bin), qbar, uniform[1], threshold)
    return (flag, eps_u) if keep_x else flag


def _add_exact_moments(template, q, flag, outs, names, info, *, reach, bin, max_fraction,
                       samples, workers, dtype, strip, progress):
    """Replace the maps ``outs`` (``names`` order) by the exact moments in the
    flagged bins (:func:`~._exact.exact_boxes`, :func:`~._exact.exact_windows`),
    or everywhere when the windows with their margins would cover more than
    ``max_fraction`` of the image (:func:`_exact_everywhere`); ``info`` gets
    the method, windows and fractions. ``progress`` (optional) is called with
    the fraction of the exact work done."""
    b = int(bin)
    r = reach
    info["exact_fraction"] = float(flag.sum()) * b * b / q.size
    boxes = exact_boxes(flag, b, q.shape, band=-(-r // b))
    canvas = sum((y1 - y0 + 2 * r) * (x1 - x0 + 2 * r) for y0, y1, x0, x1 in boxes)
    if canvas > max_fraction * q.size:
        _exact_everywhere(template, q, outs, names, samples=samples, workers=workers,
                          dtype=dtype, strip=strip, progress=progress)
        info.update(method="exact", windows=1, canvas_fraction=1.0)
        return
    area = exact_windows(template, q, boxes, r, outs, names, samples=samples, workers=workers,
                         dtype=dtype, strip=strip, progress=progress)
    info.update(method="linear+exact", windows=len(boxes), canvas_fraction=area / q.size)


def _exact_everywhere(template, q, outs, names, *, samples, workers, dtype, strip, progress):
    """Replace the maps ``outs`` (``names`` order) by the exact moments of the
    whole image (:func:`~.moment_maps`); ``progress`` (optional) is called
    with the fraction of the rows done."""
    ny = q.shape[0]
    row_progress = None
    if progress is not None:
        rows = [0]

        def row_progress(n):
            rows[0] += n
            progress(rows[0] / ny)

    mm = moment_maps(template, q, samples=samples, workers=workers, dtype=dtype, strip=strip,
                     maps=names, progress=row_progress)
    for k, name in enumerate(names):
        outs[k][:] = getattr(mm, name)
