"""A-priori bounds of the linearised geometry maps' error (:mod:`lsst_bfdrift.geometry.linear`).

The second-order remainder of each map as a function of the largest
boundary displacement of a pixel (:func:`second_order_bounds`), and an upper
bound of that displacement per bin of pixels from the charge image
(:func:`displacement_bound`: one single-precision FFT convolution of binned
absolute deviations); :func:`~lsst_bfdrift.geometry.linear.error_bounds`
combines them.
"""

import math

import numpy as np
from scipy import fft as sp_fft

from lsst_bfdrift.geometry._linear_kernels import abs_dev_bins, pixel_abs_dev_sums

__all__ = ["second_order_bounds", "displacement_bound", "pixel_displacement_bound",
           "reference_level", "bin_abs_dev"]


def second_order_bounds(eps, chi=4.0):
    """Bounds of abs(exact - linear) per map for boundary displacements up to ``eps``.

    Parameters
    ----------
    eps : float or ndarray
        Largest abs displacement component (px) of any boundary point of
        the pixel (its corners, edge samples and tangential displacements).
    chi : float, optional
        :attr:`~.LinearKernels.chi`.

    Returns
    -------
    dict
        ``area`` (px^2), ``dx``, ``dy`` (px), ``e1``, ``e2``; inf where the
        bound does not apply (``eps`` so large that the area or the trace of
        the second moments could change sign).

    Notes
    -----
    Polygon P_t has vertices V + t d (t from 0 to 1). The transport theorem
    over each segment of the boundary gives the exact change of
    ``integral f dA`` as a sum over segments of ``integral f(V(s) + t d(s))
    (L d(s).n + t (d_b x d_a)) ds dt`` (L the segment's length), whose first
    term at ``t = 0`` is the linear change. The remainder is at most
    ``(2 sqrt(2) G + chi F) eps**2`` with G the largest gradient and F the
    largest abs(f) within ``rho = 1/2 + eps`` of the centre (for the total
    perimeter 4 and abs(d) <= sqrt(2) eps; only the segments next to a
    corner have a cross product, at most eps**2, unless there are
    tangential displacements). The first-order changes are at most 4 max
    abs(f) on the boundary times eps: 4 eps (area), 2 eps (x), eps
    (x**2 - y**2, xy), 2 eps (x**2 + y**2). The centroid and e1, e2 are
    ratios; with a = dA, T = trace of the second moments, their errors
    follow from these by the triangle inequality (see the code). For small
    eps and chi = 4: area 4 eps**2, dx and dy 12.8 eps**2, e1 126 eps**2,
    e2 228 eps**2 (measured on star fields and flats: at most 1.9, 0.8, 1.9
    and 11 times the squared largest displacement).
    """
    eps = np.asarray(eps, dtype=np.float64)
    s2 = math.sqrt(2.0)
    rho = 0.5 + eps
    e2_ = eps * eps
    r_a = chi * e2_
    r_x = (2.0 * s2 + chi * rho) * e2_
    r_d = (8.0 * rho + chi * rho**2) * e2_          # x**2 - y**2
    r_t = (8.0 * rho + 2.0 * chi * rho**2) * e2_    # x**2 + y**2
    r_xy = (4.0 * rho + chi * rho**2) * e2_         # xy
    alpha = 4.0 * eps + r_a                         # abs(dA)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = alpha < 1.0
        delta = np.where(ok, (2.0 * eps + r_x) / (1.0 - alpha), np.inf)   # abs(dx), abs(dy)
        beta = 2.0 * eps + r_t + 2.0 * (1.0 + alpha) * delta**2          # abs(T - 1/6)
        ok &= beta < 1.0 / 6.0
        den = np.where(ok, 1.0 / 6.0 - beta, np.nan)
        dxb = np.where(ok, (r_x + 2.0 * eps * alpha) / (1.0 - alpha), np.inf)
        e1b = np.where(ok, (r_d + (1.0 + alpha) * delta**2 + 6.0 * eps * beta) / den, np.inf)
        e2b = np.where(ok, (2.0 * (r_xy + (1.0 + alpha) * delta**2) + 12.0 * eps * beta) / den,
                       np.inf)
    ra = np.where(ok, r_a, np.inf)
    return dict(area=ra, dx=dxb, dy=dxb.copy(), e1=e1b, e2=e2b)


def reference_level(q):
    """A typical charge level of an image: the median of at most ~65000 pixels on a grid.

    Parameters
    ----------
    q : ndarray, shape (ny, nx)
        Charge (e).

    Returns
    -------
    float
        The default reference level ``qbar`` (e) of :func:`displacement_bound`
        and :func:`~lsst_bfdrift.geometry.linear.error_bounds`.
    """
    step = max(1, int(math.sqrt(q.size / 65536.0)))
    return float(np.median(q[::step, ::step]))


def bin_abs_dev(q, qbar, b, outside):
    """Sums of ``abs(q - qbar)`` over ``b`` x ``b`` bins (e).

    Parameters
    ----------
    q : ndarray, shape (ny, nx), float64
        Charge (e), finite.
    qbar : float
        Reference level (e).
    b : int
        Bin side (px).
    outside : float
        Counted for each pixel of a partial bin beyond the image (e).

    Returns
    -------
    ndarray, shape (ceil(ny / b), ceil(nx / b))
    """
    out = np.empty((-(-q.shape[0] // int(b)), -(-q.shape[1] // int(b))))
    abs_dev_bins(np.ascontiguousarray(q, dtype=np.float64), float(qbar), int(b),
                 float(outside), out)
    return out


def displacement_bound(lk, q, *, bin=2, workers=1, qbar=None, outside=None, bin_sums=None):
    """Upper bound of every boundary displacement of each pixel (px), per bin.

    Parameters
    ----------
    lk : lsst_bfdrift.geometry.first_order.LinearKernels
    q : ndarray, shape (ny, nx), float64
        Charge (e), finite.
    bin : int, optional
        Bin side (px): the bound is one value per ``bin`` x ``bin`` pixels.
    workers : int, optional
        FFT threads.
    qbar : float, optional
        Reference level (e); default: a median of the image.
    outside : float, optional
        Value of ``g`` outside the image (e); default ``abs(qbar)``, which
        bounds the whole displacement. 0 bounds the displacement of
        ``q - qbar`` (inside the image, zero outside) alone.
    bin_sums : ndarray, shape (ceil(ny / bin), ceil(nx / bin)), optional
        The sums of ``abs(q - qbar)`` over the bins (``outside`` for the
        pixels of a partial bin beyond the image) when already computed
        (:func:`bin_abs_dev`); not modified.

    Returns
    -------
    ndarray, shape (ceil(ny / bin), ceil(nx / bin))

    Notes
    -----
    A boundary point's displacement is ``sum_a T(p - a) q(a)`` over the
    image's pixels a, ``= qbar sum_a T + sum_a T (q - qbar)``; the first sum
    differs from the sum over all offsets (at most :attr:`~.LinearKernels.net`
    per e) by the offsets outside the image. Hence every displacement of
    pixel p is at most ``sum_a disp(p - a) g(a) + abs(qbar) net`` with
    ``g = abs(q - qbar)`` inside the image and ``abs(qbar)`` outside. Per bin
    B: ``sum over bins B' of Kb(B - B') G(B')``, with ``G`` the sums of
    ``g`` over the bins and ``Kb`` the largest ``disp`` between any pixels
    of two bins that far apart (a single-precision FFT convolution, with a
    margin of 1e-5 of the largest value for its rounding).
    """
    b = int(bin)
    ny, nx = q.shape
    qbar = reference_level(q) if qbar is None else float(qbar)
    rb = lk.bin_kernel(b).shape[0] // 2
    nby, nbx = -(-ny // b), -(-nx // b)
    out_level = abs(qbar) if outside is None else float(outside)
    g = np.full((nby + 2 * rb, nbx + 2 * rb), out_level * b * b)
    g[rb:rb + nby, rb:rb + nbx] = bin_abs_dev(q, qbar, b, out_level) if bin_sums is None \
        else bin_sums
    shape = (sp_fft.next_fast_len(g.shape[0] + 2 * rb), sp_fft.next_fast_len(g.shape[1] + 2 * rb))
    d = sp_fft.irfft2(sp_fft.rfft2(g.astype(np.float32), shape, workers=workers)
                      * lk.bin_spectrum(b, shape, workers), shape, workers=workers)
    # the pad is beyond every kernel's reach of the rows kept: no wrap-around
    d = d[rb:rb + nby, rb:rb + nbx].astype(np.float64)
    # single-precision rounding (about 1e-7 of the largest value; margin 100x)
    d += 1e-5 * d.max()
    d *= 1.0 + 1e-5
    if outside is None:
        d += abs(qbar) * lk.net
    return d


def pixel_displacement_bound(lk, q, rows, cols, *, qbar, outside=0.0):
    """:func:`displacement_bound` of single pixels, without bins (px).

    Parameters
    ----------
    lk : lsst_bfdrift.geometry.first_order.LinearKernels
    q : ndarray, shape (ny, nx), float64
        Charge (e), finite.
    rows, cols : ndarray of int
        The pixels (same length).
    qbar : float
        Reference level (e).
    outside : float, optional
        Value of ``g`` outside the image (e), as for
        :func:`displacement_bound`: 0 bounds the displacement of ``q -
        qbar`` alone; ``abs(qbar)`` (with ``abs(qbar) net`` added) the whole
        displacement.

    Returns
    -------
    ndarray, float64, one value per pixel

    Notes
    -----
    ``sum_a disp(p - a) g(a)`` summed directly over the template's reach in
    double precision (relative margin 1e-12 for its rounding): the bound of
    :func:`displacement_bound` with ``bin`` = 1, at most the binned one. It
    refines the bins that the binned bound flags (about 1 % of a star field),
    where the bins' largest kernel (``Kb``) is loosest: next to bright
    sources, whose displacement kernel falls steeply with the offset.
    """
    out = np.empty(len(rows))
    pixel_abs_dev_sums(np.ascontiguousarray(q, dtype=np.float64), float(qbar), lk.disp,
                       float(outside), np.asarray(rows, np.int64), np.asarray(cols, np.int64),
                       out)
    out *= 1.0 + 1e-12
    if outside != 0.0:
        out += abs(qbar) * lk.net
    return out
