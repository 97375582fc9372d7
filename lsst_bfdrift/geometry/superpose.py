"""Superposition of a template over a charge image (the Green's-function step).

Boundaries for any charge pattern are the nominal grid plus, for every
aggressor, Q_agg / Q_template times the template shifted to the aggressor.
This is linear in charge, so every boundary sample's displacement field is a
2-d convolution of the charge image with a fixed kernel; the convolutions are
done by FFT, and the pixel polygons and their exact shoelace moments are
evaluated strip by strip so that a full 4k x 4k CCD fits in memory.

Image frame: ``charge[j, i]`` is pixel (i, j), centred on (i, j) in pixel units.
"""

import numpy as np

from lsst_bfdrift.geometry._convolve import Convolver, block_stack
from lsst_bfdrift.geometry._moment_kernels import moment_kernel
from lsst_bfdrift.physics.boundaries import BoundaryGrid
from lsst_bfdrift.utils.errors import InputError, InputTypeError
from lsst_bfdrift.templates.swept import kernel_abs_sum, refuse_out_of_range

__all__ = ["MomentMaps", "check_charge_image", "superpose_boundaries", "moment_maps",
           "resample_template"]


def check_charge_image(charge, *, mask=None, name="charge", template=None):
    """Validate a charge image (e per pixel) and return a float64 copy.

    With ``template``, values beyond the model's range are refused too
    (:func:`~lsst_bfdrift.templates.swept.refuse_out_of_range`, the range
    check the Task and the solvers apply).

    Parameters
    ----------
    charge : array_like, 2-d
        Collected charge per pixel (e). Negative values are allowed (the model
        is linear; they act as charge deficits).
    mask : array_like of bool, optional
        True where a pixel must not act as an aggressor; its charge is set to
        zero in the copy. NaN or inf are allowed only in masked pixels.
    name : str, optional
        Name used in error messages.

    Returns
    -------
    ndarray
        A new float64 array (the input is never modified).
    """
    arr = np.array(charge, dtype=np.float64, copy=True)
    if arr.ndim != 2:
        raise InputError(f"{name} image must be 2-d, got shape {arr.shape}")
    if arr.size == 0:
        raise InputError(f"{name} image is empty")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != arr.shape:
            raise InputError(f"mask shape {mask.shape} does not match {name} shape {arr.shape}")
        arr[mask] = 0.0
    bad = ~np.isfinite(arr)
    if np.any(bad):
        j, i = np.argwhere(bad)[0]
        raise InputError(f"{name} image has {int(bad.sum())} non-finite pixel(s) "
                         f"(first at x={i}, y={j}); mask them")
    if template is not None:
        refuse_out_of_range(arr, kernel_abs_sum(template))
    return arr


def _profile_matrix(old, new, n_moments):
    """Linear map from an edge profile on knots ``old`` to one on ``new``.

    Both profiles are piecewise linear on [0, 1] with the same values at the
    ends (the corners). The interior values on ``new`` minimise the L2
    distance to the old profile subject to equal moments
    integral(s**m * profile, 0..1) for m < ``n_moments``.

    Parameters
    ----------
    old : ndarray, shape (ns,)
        Interior knots of the given profile (fractions in (0, 1)).
    new : ndarray, shape (k,)
        Interior knots of the resampled profile.
    n_moments : int
        Moments kept exactly (at most ``k``).

    Returns
    -------
    ndarray, shape (k, ns + 2)
        Interior values on ``new`` from (corner 0, old samples, corner 1).
    """
    s = np.concatenate([[0.0], old, [1.0]])
    t = np.concatenate([[0.0], new, [1.0]])
    u = np.union1d(s, t)
    # Simpson's rule on every interval of the merged knots: exact for the
    # products of two piecewise-linear profiles and for s**2 times one.
    a, b = u[:-1], u[1:]
    x = np.concatenate([a, 0.5 * (a + b), b])
    w = np.concatenate([(b - a) / 6.0, 4.0 * (b - a) / 6.0, (b - a) / 6.0])

    def hats(knots):
        return np.stack([np.interp(x, knots, np.eye(knots.size)[j])
                         for j in range(knots.size)], axis=1)

    ef, eg = hats(s), hats(t)
    gram = eg.T @ (w[:, None] * eg)
    cross = eg.T @ (w[:, None] * ef)
    mom = np.stack([x**m * w for m in range(n_moments)])
    mg, mf = mom @ eg, mom @ ef
    k, n = new.size, s.size
    ends = np.zeros((k + 2, n))
    ends[0, 0] = ends[-1, -1] = 1.0
    inner = slice(1, k + 1)
    lhs = np.zeros((k + n_moments, k + n_moments))
    lhs[:k, :k] = gram[inner, inner]
    lhs[:k, k:] = mg[:, inner].T
    lhs[k:, :k] = mg[:, inner]
    rhs = np.concatenate([(cross - gram @ ends)[inner], mf - mg @ ends])
    return np.linalg.solve(lhs, rhs)[:k]


def _lobatto_knots(fractions, k):
    """k Chebyshev-Lobatto points from the first to the last of ``fractions``."""
    lo, hi = float(fractions[0]), float(fractions[-1])
    if k == 1:
        return np.array([0.5 * (lo + hi)])
    return lo + (hi - lo) * 0.5 * (1.0 - np.cos(np.pi * np.arange(k) / (k - 1)))


def resample_template(template, samples):
    """The template with its edge profiles resampled to ``samples`` points per edge.

    Each edge's displacement profile (piecewise linear through its two
    corners and samples) is replaced by the piecewise-linear profile through
    the same corners and ``samples`` new points that is closest to it in the
    L2 sense while having the same integrals of ``s**m`` times the profile
    along the edge (s the fraction of the edge), m = 0, 1, 2 (m < ``samples``
    if ``samples`` < 3). The new points are Chebyshev-Lobatto nodes between
    the template's first and last sample fractions, so the segments next to
    the corners keep the template's own length and the points cluster
    towards the corners.

    The swept area of every edge (m = 0) is unchanged, and so is every pixel
    moment (area, centroid, second moments, ellipticity) to first order in
    the displacements: the polygons' shoelace moments differ from those of
    the full template only by terms quadratic in the displacements. The map
    is linear, so resampling the template equals resampling the superposed
    boundaries of any image. Corners are kept as they are; tangential
    displacements, if any, are resampled with the same map (they enter the
    moments only at second order). Accuracy against the full 32-sample
    default template: see ``docs/benchmarks.rst`` (geometry maps).

    Parameters
    ----------
    template : DistortionTemplate
        The full template.
    samples : int
        Samples per edge of the result, 1 <= samples <= the template's own.

    Returns
    -------
    DistortionTemplate
        ``template`` itself when ``samples`` equals its number of samples,
        otherwise a new template (same charge, corners and provenance, with
        ``meta['resampled_from']`` set to the original number of samples).

    Raises
    ------
    TypeError
        ``samples`` is not an integer.
    ValueError
        ``samples`` is outside 1 .. the template's samples per edge.
    """
    ns = template.edge_samples
    if isinstance(samples, (bool, np.bool_)) or not isinstance(samples, (int, np.integer)):
        raise InputTypeError(f"samples must be an integer, got {samples!r}")
    samples = int(samples)
    if not 1 <= samples <= ns:
        raise InputError(f"samples must be between 1 and the template's {ns} samples per "
                         f"edge, got {samples}")
    if samples == ns:
        return template
    new = _lobatto_knots(template.fractions, samples)
    r = _profile_matrix(template.fractions, new, min(samples, 3))
    cd = template.corner_d

    def apply(c0, prof, c1):
        full = np.concatenate([c0[..., None], prof, c1[..., None]], axis=-1)
        return full @ r.T

    v = apply(cd[:-1, :, 0], template.vedge_d, cd[1:, :, 0])
    h = apply(cd[:, :-1, 1], template.hedge_d, cd[:, 1:, 1])
    vt = ht = None
    if template.vedge_t is not None:
        vt = apply(cd[:-1, :, 1], template.vedge_t, cd[1:, :, 1])
        ht = apply(cd[:, :-1, 0], template.hedge_t, cd[:, 1:, 0])
    meta = dict(template.meta)
    meta["resampled_from"] = ns
    return type(template)(cd, v, h, new, template.charge, vedge_t=vt, hedge_t=ht, meta=meta)


def _block_displacements(conv, charge, r0, r1, workers=1):
    """Absolute boundary positions of pixel rows r0..r1-1 (float64).

    Returns corners (r1 - r0 + 1, nx + 1, 2), vedge (r1 - r0, nx + 1, ns),
    hedge (r1 - r0 + 1, nx, ns), vedge_t, hedge_t (None without tangential
    displacements).
    """
    t = conv.t
    c, ns = t.center, t.edge_samples
    nx = charge.shape[1]
    st, ro = block_stack(conv, charge, r0, r1, workers)
    rc, rv = slice(ro, ro + r1 - r0 + 1), slice(ro, ro + r1 - r0)
    cc, ch = slice(c, c + nx + 1), slice(c, c + nx)

    def take(first, rows, cols):
        return np.moveaxis(st[first:first + ns, rows, cols], 0, -1).astype(np.float64)

    xs = np.arange(nx + 1) - 0.5
    ys = np.arange(r0, r1 + 1) - 0.5
    cd = np.moveaxis(st[:2, rc, cc], 0, -1).astype(np.float64)
    cd[..., 0] += xs
    cd[..., 1] += ys[:, None]
    v = take(2, rv, cc) + xs[None, :, None]
    h = take(2 + ns, rc, ch) + ys[:, None, None]
    vt = ht = None
    if t.vedge_t is not None:
        vt, ht = take(2 + 2 * ns, rv, cc), take(2 + 3 * ns, rc, ch)
    return cd, v, h, vt, ht


def superpose_boundaries(template, charge, *, mask=None, workers=1):
    """Pixel boundaries of a whole charge image (absolute, pixel units).

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    charge : array_like, 2-d
        Collected charge (e), ``charge[j, i]`` for pixel (i, j).
    mask : array_like of bool, optional
        Pixels that do not act as aggressors.
    workers : int, optional
        FFT threads.

    Returns
    -------
    BoundaryGrid
        With ``vedge_t`` and ``hedge_t`` attributes (None if the template has
        no tangential displacements).
    """
    q = check_charge_image(charge, mask=mask, template=template)
    conv = Convolver(template)
    cd, v, h, vt, ht = _block_displacements(conv, q, 0, q.shape[0], workers=workers)
    grid = BoundaryGrid(0, 0, cd, v, h, template.fractions)
    grid.vedge_t, grid.hedge_t = vt, ht
    return grid


class MomentMaps:
    """Per-pixel geometry of the final pixel boundaries.

    Attributes
    ----------
    area : ndarray
        Pixel area (px^2; nominal 1).
    dx, dy : ndarray
        Centroid shift from the nominal pixel centre (px).
    ixx, iyy, ixy : ndarray
        Central second moments (px^2; nominal 1/12, 1/12, 0).
    e1, e2 : ndarray
        Ellipticity of the pixel's second moments.

    A map that was not requested (``moment_maps(..., maps=...)``) is None.
    """

    _names = ("area", "dx", "dy", "ixx", "iyy", "ixy", "e1", "e2")

    def __init__(self, shape, names=None):
        names = self._names if names is None else tuple(names)
        unknown = sorted(set(names) - set(self._names))
        if unknown:
            raise InputError(f"unknown maps {unknown}; choose from {list(self._names)}")
        for k in self._names:
            setattr(self, k, np.empty(shape) if k in names else None)

    def as_dict(self):
        """The maps by name (those computed)."""
        return {k: getattr(self, k) for k in self._names if getattr(self, k) is not None}


def moment_maps(template, charge, *, mask=None, samples=None, strip=256, workers=1,
                dtype=np.float64, progress=None, maps=None):
    """Area, centroid-shift and ellipticity maps of a charge image's pixels.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    charge : array_like, 2-d
        Collected charge (e), ``charge[j, i]``.
    mask : array_like of bool, optional
        Pixels that do not act as aggressors (their geometry is still computed).
    samples : int, optional
        Samples per edge of the polygons: the template is first resampled by
        :func:`resample_template` (moment-preserving, so the maps differ from
        the full computation only at second order in the displacements; the
        time falls with the number of boundary channels, 2 + 2 ``samples``).
        None (default): the template's own samples, exact.
    strip : int, optional
        Rows per block: the block's 2 + 2 ns boundary channels (ns samples
        per edge, twice that with tangential displacements) are transformed
        together, about 2 * (strip + 2 N) * width * (2 + 2 ns) * itemsize
        bytes at once, plus the kernels' transforms (half that). The moments
        are evaluated by a compiled kernel (:mod:`lsst_bfdrift.physics._drift_kernels`) that
        builds each pixel's polygon on the fly from the channels.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the FFT convolutions (the polygons and their moments are
        always evaluated in float64).
    progress : callable, optional
        Called with the number of rows finished.
    maps : sequence of str, optional
        Names of the maps to keep (of ``area, dx, dy, ixx, iyy, ixy, e1,
        e2``); the others are None. Each kept map is one float64 image of
        memory. None: all eight.

    Returns
    -------
    MomentMaps

    Examples
    --------
    One bright pixel on a sky of 1000 e: it shrinks, its neighbours grow,
    and their centroids move towards it (x is the serial axis):

    >>> import numpy as np
    >>> from lsst_bfdrift import load_default_template, moment_maps
    >>> q = np.full((32, 32), 1000.0)
    >>> q[16, 16] = 1e5
    >>> maps = moment_maps(load_default_template(), q)
    >>> print(f"{maps.area[16, 16]:.3f} {maps.area[16, 17]:.4f} {maps.dx[16, 17]:+.4f}")
    0.899 1.0057 -0.0107
    """
    if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
        raise InputError(f"dtype must be float64 or float32, got {dtype!r}")
    if isinstance(strip, (bool, np.bool_)) or int(strip) != strip or strip < 1:
        raise InputError(f"strip must be a positive integer, got {strip!r}")
    if samples is not None:
        template = resample_template(template, samples)
    q = check_charge_image(charge, mask=mask, template=template)
    ny, nx = q.shape
    strip = int(strip)
    conv = Convolver(template, dtype=dtype)
    out = MomentMaps(q.shape, maps)
    fr = np.ascontiguousarray(template.fractions)
    ns, has_t = template.edge_samples, template.vedge_t is not None
    res = np.empty((8, min(strip, ny), nx))
    for r0 in range(0, ny, strip):
        r1 = min(r0 + strip, ny)
        st, ro = block_stack(conv, q, r0, r1, workers)
        part = res if r1 - r0 == res.shape[1] else np.empty((8, r1 - r0, nx))
        moment_kernel(part[0].size)(st, ns, has_t, ro, template.center, fr, part)
        del st
        for k, name in enumerate(MomentMaps._names):
            if getattr(out, name) is not None:
                getattr(out, name)[r0:r1] = part[k]
        if progress is not None:
            progress(r1 - r0)
    return out
