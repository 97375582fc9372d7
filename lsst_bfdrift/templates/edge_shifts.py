"""Templates whose edges move rigidly: from per-edge shifts and from kernels.

LSST's corrections describe the brighter-fatter distortion by one number
per pixel edge: the ASTIER23 correction by the edge shifts ``aN``, ``aS``,
``aE``, ``aW`` of its ``electroBfDistortionMatrix`` (Astier & Regnault
2023), the COULTON18 correction by a kernel K whose gradient is the edge
shift (Coulton et al. 2018: the discrete Laplacian of K is the a-matrix).
:func:`template_from_edge_shifts` and :func:`template_from_kernel` turn
either into a :class:`~lsst_bfdrift.templates.template.DistortionTemplate`,
so that the Task corrects with them and the package's tools (swept areas,
area coefficients, geometry maps) apply. :func:`template_edge_shifts` goes
back (the kernel of a template is
:func:`~lsst_bfdrift.correction.solvers.coulton18_kernel` of its area
coefficients).

Each edge of the template moves by its shift along its normal: the samples
are set so that the area the edge sweeps (the trapezoid rule of
:func:`~lsst_bfdrift.templates.swept.swept_area_kernels`) is the shift
exactly, the corners by the mean of the shifts of the edges that meet
there. Shifts are per electron, outward positive, arrays ``[i, j]`` with i
the serial and j the parallel lag, 0 <= i, j <= L (the quadrant; the
others follow by symmetry).
"""

import numpy as np

from lsst_bfdrift.templates.swept import swept_area_kernels
from lsst_bfdrift.templates.template import DistortionTemplate
from lsst_bfdrift.utils.errors import InputError

__all__ = ["template_from_edge_shifts", "template_from_kernel", "template_edge_shifts"]


def _full(quadrant, mirror_i, mirror_j, size):
    """An [i, j] quadrant (0..L) spread to offsets -c..c by the given mirror signs,
    as a [J, I] array of the template's size (zero beyond L)."""
    c = size // 2
    q = np.asarray(quadrant, dtype=float)
    out = np.zeros((size, size))
    n = min(q.shape[0], c + 1)
    for di in range(-n + 1, n):
        for dj in range(-n + 1, n):
            s = (mirror_i if di < 0 else 1.0) * (mirror_j if dj < 0 else 1.0)
            out[dj + c, di + c] = s * q[abs(di), abs(dj)]
    return out


def _rigid_template(sv, sh, *, edge_samples, charge, meta):
    """Template whose vertical edges (sv, [J, I] for the boundary x = I - c - 1/2)
    and horizontal edges (sh, [J, I] for y = J - c - 1/2) sweep exactly sv, sh
    (px per electron) times ``charge``."""
    ns = int(edge_samples)
    if ns < 1:
        raise InputError(f"edge_samples must be a positive integer, got {edge_samples!r}")
    n = sh.shape[1]
    fractions = (np.arange(ns) + 0.5) / ns
    sv, sh = sv * charge, sh * charge
    corner = np.zeros((n + 1, n + 1, 2))
    # x of a corner: the mean of the vertical edges above and below it (one at the border)
    pad = np.zeros((n + 2, n + 1))
    pad[1:-1] = sv
    corner[..., 0] = 0.5 * (pad[:-1] + pad[1:])
    pad = np.zeros((n + 1, n + 2))
    pad[:, 1:-1] = sh
    corner[..., 1] = 0.5 * (pad[:, :-1] + pad[:, 1:])
    # samples: one value v per edge with trapezoid(c0, v, c1) = shift
    s = np.concatenate([[0.0], fractions, [1.0]])
    w0, w1 = 0.5 * (s[1] - s[0]), 0.5 * (s[-1] - s[-2])
    wv = 1.0 - w0 - w1  # the samples' total weight in the trapezoid rule

    def samples(shift, c0, c1):
        return np.repeat(((shift - w0 * c0 - w1 * c1) / wv)[..., None], ns, axis=-1)

    vedge = samples(sv, corner[:-1, :, 0], corner[1:, :, 0])
    hedge = samples(sh, corner[:, :-1, 1], corner[:, 1:, 1])
    return DistortionTemplate(corner, vedge, hedge, fractions, charge, meta=meta)


def template_from_edge_shifts(a_n, a_s, a_e, a_w, *, size=None, edge_samples=8, charge=1e4,
                              meta=None):
    """A template from per-edge shifts (LSST's ``aN``, ``aS``, ``aE``, ``aW``).

    Parameters
    ----------
    a_n, a_s, a_e, a_w : array_like, shape (L + 1, L + 1)
        Outward shifts (pixels per electron) of the top, bottom, right and left
        edges of pixel [i, j] (i serial, j parallel) per electron in pixel
        (0, 0). A boundary shared by two pixels is given twice (the right edge
        of [i, j] and the left edge of [i + 1, j]); the template takes their
        mean.
    size : int, optional
        Side of the template (odd); default 2 L + 3 (every given lag and a
        ring of unmoved edges).
    edge_samples : int, optional
        Samples per edge.
    charge : float, optional
        Aggressor charge of the template (e).
    meta : dict, optional
        Provenance.

    Returns
    -------
    DistortionTemplate
    """
    arrs = [np.asarray(x, dtype=float) for x in (a_n, a_s, a_e, a_w)]
    shape = arrs[0].shape
    if len(shape) != 2 or shape[0] != shape[1] or any(x.shape != shape for x in arrs):
        raise InputError("aN, aS, aE, aW must be square arrays of one shape, got "
                         + ", ".join(str(x.shape) for x in arrs))
    if not all(np.all(np.isfinite(x)) for x in arrs):
        raise InputError("aN, aS, aE, aW must be finite")
    n_lag = shape[0]
    size = 2 * n_lag + 1 if size is None else int(size)
    if size % 2 != 1 or size < 3:
        raise InputError(f"template size must be odd and >= 3, got {size}")
    c = size // 2
    # outward shifts of every pixel [J, I]: right edges move +x (mirror: left edges in x < 0)
    east = _full(arrs[2], 1.0, 1.0, size)
    west = _full(arrs[3], 1.0, 1.0, size)
    north = _full(arrs[0], 1.0, 1.0, size)
    south = _full(arrs[1], 1.0, 1.0, size)
    # in mirrored quadrants the right and left (top and bottom) edges swap roles
    ii = np.arange(size) - c
    neg_i = (ii < 0)[None, :]
    neg_j = (ii < 0)[:, None]
    right = np.where(neg_i, west, east)   # outward shift of each pixel's right edge
    left = np.where(neg_i, east, west)
    top = np.where(neg_j, south, north)
    bottom = np.where(neg_j, north, south)
    # which pixels were given (lags 0..L): a boundary between a given pixel and one
    # beyond the given lags takes the given pixel's shift alone
    given = np.zeros((size, size))
    lag = np.abs(ii)
    given[(lag[:, None] < n_lag) & (lag[None, :] < n_lag)] = 1.0

    def boundary(plus, minus, w_plus, w_minus, axis):
        """Mean of the two estimates of each boundary (plus side's outward shift
        and minus the other side's), weighted by which pixels were given."""
        shape = list(plus.shape)
        shape[axis] += 1
        num, den = np.zeros(shape), np.zeros(shape)
        hi = [slice(None)] * 2
        lo = [slice(None)] * 2
        hi[axis], lo[axis] = slice(1, None), slice(None, -1)
        num[tuple(hi)] += w_plus * plus
        den[tuple(hi)] += w_plus
        num[tuple(lo)] -= w_minus * minus
        den[tuple(lo)] += w_minus
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)

    # boundary x = I - c - 1/2 (I = 0..size): right edge of pixel I-1, left edge of pixel I
    sv = boundary(right, left, given, given, axis=1)
    sh = boundary(top, bottom, given, given, axis=0)
    meta = dict(meta or {})
    meta.setdefault("source", "per-edge shifts (aN, aS, aE, aW)")
    return _rigid_template(sv, sh, edge_samples=edge_samples, charge=charge, meta=meta)


def template_from_kernel(kernel, *, edge_samples=8, charge=1e4, meta=None):
    """A template from a brighter-fatter kernel (Coulton et al. 2018).

    The boundary between two pixels moves by the difference of the kernel
    across it (per electron): the area change of a pixel is then the
    discrete Laplacian of the kernel, its a_ij.

    Parameters
    ----------
    kernel : array_like, shape (N, N)
        K (per electron), [y, x], N odd, centred on the aggressor; the
        convention of :func:`~lsst_bfdrift.correction.solvers.coulton18_kernel`
        and of LSST's ``bfk`` (the Laplacian of K is the a-matrix, negative
        at the centre).
    edge_samples, charge, meta
        As for :func:`template_from_edge_shifts`.

    Returns
    -------
    DistortionTemplate
        Of size N.
    """
    k = np.asarray(kernel, dtype=float)
    if k.ndim != 2 or k.shape[0] != k.shape[1] or k.shape[0] % 2 != 1 or k.shape[0] < 3:
        raise InputError(f"kernel must be a square array of odd size >= 3, got {k.shape}")
    if not np.all(np.isfinite(k)):
        raise InputError("kernel must be finite")
    pad = np.pad(k, 1, mode="edge")  # no gradient across the outer border
    sv = pad[1:-1, 1:] - pad[1:-1, :-1]   # x boundaries: K(right) - K(left)
    sh = pad[1:, 1:-1] - pad[:-1, 1:-1]   # y boundaries: K(top) - K(bottom)
    meta = dict(meta or {})
    meta.setdefault("source", "kernel (Coulton et al. 2018)")
    return _rigid_template(sv, sh, edge_samples=edge_samples, charge=charge, meta=meta)


def template_edge_shifts(template, max_lag=None):
    """The template's per-edge shifts, as LSST's distortion matrix holds them.

    Parameters
    ----------
    template : DistortionTemplate
    max_lag : int, optional
        Largest lag L; default the template's centre index minus one.

    Returns
    -------
    aN, aS, aE, aW : ndarray, shape (L + 1, L + 1)
        Outward shifts (pixels per electron, the swept areas of
        :func:`~lsst_bfdrift.templates.swept.swept_area_kernels`) of pixel
        [i, j]'s top, bottom, right and left edges.
    """
    c = template.center
    L = c - 1 if max_lag is None else int(max_lag)
    if not 0 <= L <= c - 1:
        raise InputError(f"max_lag must be 0..{c - 1} for this template, got {max_lag!r}")
    kv, kh = swept_area_kernels(template)
    kv, kh = kv / template.charge, kh / template.charge
    i = np.arange(L + 1)
    # pixel [J, I] = (c + j, c + i): left edge kv[J, I], right edge kv[J, I + 1]
    J, I = np.meshgrid(c + i, c + i, indexing="ij")  # [j, i]
    a_e = kv[J, I + 1].T
    a_w = -kv[J, I].T
    a_n = kh[J + 1, I].T
    a_s = -kh[J, I].T
    return a_n, a_s, a_e, a_w

