"""Geometry maps to first order in the charge, exact where that is not enough.

Every pixel moment is a smooth function of the boundary displacements,
which are linear in the charge (:mod:`lsst_bfdrift.geometry.superpose`). To
first order each map of :func:`~lsst_bfdrift.geometry.superpose.moment_maps`
is therefore a convolution of the charge image with a fixed kernel: the
first-order change of the moment of the pixel at each offset from one
electron of aggressor. By the transport theorem the first-order change of
``integral f dA`` over a pixel is the boundary integral of ``f`` times the
outward normal displacement; the edge profiles are piecewise linear, so
the integrals of ``s**m`` times each profile (m <= 2, s along the edge) give
the kernels exactly (:class:`LinearKernels`). With ``L_f`` that change for
``f`` about the nominal centre:

* area ``1 + L_1``; centroid shift ``dx = L_x``, ``dy = L_y``;
* ``e1 = 6 (L_xx - L_yy)`` and ``e2 = 12 L_xy``: the ellipticities
  linearised about the square pixel (moments 1/12, 1/12, 0), not ratios of
  linearised moments (forming the ratios from first-order moment maps is
  less accurate: its quadratic errors do not cancel those of the moments:
  5 to 15 times larger for e1 and e2 on a 1.5e6 e star).

Where the charge is high the neglected second-order terms matter, and the
exact polygon moments are computed there instead, on windows chosen by an
a-priori bound (:func:`second_order_bounds`, :func:`displacement_bound`):
the maps returned by :func:`linear_moment_maps` differ from the exact
``moment_maps`` (same ``samples``) by at most ``rtol`` times each map's
signal in every pixel (signal: the largest abs(map - nominal) over the
image).
"""

import math
import weakref

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage

from lsst_bfdrift.templates.swept import kernel_abs_sum, refuse_out_of_range
from lsst_bfdrift.geometry.superpose import (MomentMaps, check_charge_image, moment_maps,
                                             resample_template, superpose_boundaries)
from lsst_bfdrift.utils.errors import InputError

__all__ = ["LINEAR_MAPS", "MEASURED_CONSTANTS", "LinearKernels", "linear_kernels",
           "second_order_bounds", "displacement_bound", "error_bounds", "linear_moment_maps"]

#: Maps that :func:`linear_moment_maps` computes, in the order of
#: :attr:`LinearKernels.kernels`.
LINEAR_MAPS = ("area", "dx", "dy", "e1", "e2")
_NOMINAL = np.array([1.0, 0.0, 0.0, 0.0, 0.0])

#: abs(exact - linear) <= C eps**2 per map (eps: the pixel's largest boundary
#: displacement component, px; eps <= 0.05): twice the largest ratio measured
#: on star fields (up to a 1.5e6 e star) and 1e5 e flats with the bundled
#: template (1.9, 0.75, 0.76, 1.9, 10.5; ``tests/geometry/test_linear.py``
#: checks them), at most the analytic bounds of :func:`second_order_bounds`
#: (4, 12.8, 12.8, 126, 228 for small eps). These make the default
#: ``bound='measured'`` of :func:`linear_moment_maps`.
MEASURED_CONSTANTS = dict(area=4.0, dx=1.6, dy=1.6, e1=4.0, e2=21.0)


def _hat_moments(fractions):
    """``w[m, k]`` = integral over [0, 1] of ``s**m`` times the k-th hat function
    of the knots (0, fractions, 1), m = 0, 1, 2 (Simpson: exact for cubics)."""
    t = np.concatenate([[0.0], fractions, [1.0]])
    w = np.zeros((3, t.size))
    for k in range(t.size - 1):
        a, b = t[k], t[k + 1]
        h = b - a
        for x, wt in ((a, h / 6.0), (0.5 * (a + b), 4.0 * h / 6.0), (b, h / 6.0)):
            for m in range(3):
                w[m, k] += wt * x**m * (b - x) / h
                w[m, k + 1] += wt * x**m * (x - a) / h
    return w


class LinearKernels:
    """First-order moment kernels of a template, and its displacement bound.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function (N x N, centre c).
    exact_template : DistortionTemplate, optional
        The template of the exact fallback (e.g. resampled to fewer edge
        samples); its displacements define :attr:`disp` and :attr:`chi`.
        Default: ``template``.

    Attributes
    ----------
    kernels : ndarray, shape (5, N + 2, N + 2)
        Change of area (px^2), dx, dy (px), e1, e2 of the pixel at offset
        (dj, di) = (j - c - 1, i - c - 1) from one electron of aggressor
        (per e), in the order of :data:`LINEAR_MAPS`.
    disp : ndarray, shape (N + 2, N + 2)
        Largest abs displacement component (px per e) of any boundary point
        (corners, edge samples, tangential displacements) of the pixel at
        each offset.
    net : float
        Largest abs of the sum over all offsets of one boundary point's
        displacement (px per e): the displacement in a uniform field per e.
    chi : float
        4 without tangential displacements (only the 8 segments next to
        the corners have cross products), else 4 (samples + 1) (every
        segment).
    reach : int
        c + 1: aggressors farther than this (in x or y) do not move a
        pixel's boundaries.
    """

    def __init__(self, template, exact_template=None):
        t = template
        e = t if exact_template is None else exact_template
        self.reach = r = t.center + 1
        n = t.size
        m = n + 2
        w = _hat_moments(t.fractions)
        cd = np.zeros((n + 3, n + 3, 2))
        cd[1:n + 2, 1:n + 2] = t.corner_d
        vd = np.zeros((n + 2, n + 3, t.edge_samples))
        vd[1:n + 1, 1:n + 2] = t.vedge_d
        hd = np.zeros((n + 3, n + 2, t.edge_samples))
        hd[1:n + 2, 1:n + 1] = t.hedge_d
        a0, a1 = slice(0, m), slice(1, m + 1)

        def mom(c0, samples, c1):
            vals = np.concatenate([c0[..., None], samples, c1[..., None]], axis=-1)
            mu = vals @ w.T
            # integrals of 1, (s - 1/2) and (s - 1/2)**2 times the profile
            return mu[..., 0], mu[..., 1] - 0.5 * mu[..., 0], \
                mu[..., 2] - mu[..., 1] + 0.25 * mu[..., 0]

        # pixel (dj, di): left edge = column boundary di, right = di + 1;
        # bottom edge = row boundary dj, top = dj + 1 (outward normals -x, +x, -y, +y)
        uL = mom(cd[a0, a0, 0], vd[a0, a0], cd[a1, a0, 0])
        uR = mom(cd[a0, a1, 0], vd[a0, a1], cd[a1, a1, 0])
        vB = mom(cd[a0, a0, 1], hd[a0, a0], cd[a0, a1, 1])
        vT = mom(cd[a1, a0, 1], hd[a1, a0], cd[a1, a1, 1])
        l1 = uR[0] - uL[0] + vT[0] - vB[0]
        lx = 0.5 * (uR[0] + uL[0]) + vT[1] - vB[1]
        ly = 0.5 * (vT[0] + vB[0]) + uR[1] - uL[1]
        lxx_yy = 0.25 * (uR[0] - uL[0]) + vT[2] - vB[2] - 0.25 * (vT[0] - vB[0]) - uR[2] + uL[2]
        lxy = 0.5 * (uR[1] + uL[1] + vT[1] + vB[1])
        self.kernels = np.stack([l1, lx, ly, 6.0 * lxx_yy, 12.0 * lxy]) / t.charge
        # displacement bound of the exact template's boundary points
        ns = e.edge_samples
        ac = np.zeros((n + 3, n + 3))
        ac[1:n + 2, 1:n + 2] = np.abs(e.corner_d).max(-1)
        av = np.zeros((n + 2, n + 3))
        av[1:n + 1, 1:n + 2] = np.abs(e.vedge_d).max(-1)
        ah = np.zeros((n + 3, n + 2))
        ah[1:n + 2, 1:n + 1] = np.abs(e.hedge_d).max(-1)
        sums = [np.abs(e.corner_d.sum(axis=(0, 1))).max(), np.abs(e.vedge_d.sum(axis=(0, 1))).max(),
                np.abs(e.hedge_d.sum(axis=(0, 1))).max()]
        if e.vedge_t is not None:
            av[1:n + 1, 1:n + 2] = np.maximum(av[1:n + 1, 1:n + 2], np.abs(e.vedge_t).max(-1))
            ah[1:n + 2, 1:n + 1] = np.maximum(ah[1:n + 2, 1:n + 1], np.abs(e.hedge_t).max(-1))
            sums += [np.abs(e.vedge_t.sum(axis=(0, 1))).max(),
                     np.abs(e.hedge_t.sum(axis=(0, 1))).max()]
        self.disp = np.maximum.reduce([ac[a0, a0], ac[a1, a0], ac[a0, a1], ac[a1, a1],
                                       av[a0, a0], av[a0, a1], ah[a0, a0], ah[a1, a0]]) / e.charge
        self.net = float(max(sums)) / abs(e.charge)
        self.chi = 4.0 if e.vedge_t is None else 4.0 * (ns + 1)
        self._spectra = {}
        self._bins = {}

    def bin_kernel(self, b):
        """:attr:`disp` per ``b`` x ``b`` bins (:func:`displacement_bound`)."""
        if b not in self._bins:
            self._bins.clear()
            self._bins[b] = [_bin_kernel(self.disp, b), None, None]
        return self._bins[b][0]

    def bin_spectrum(self, b, shape, workers=1):
        """Single-precision transform of :meth:`bin_kernel` padded to ``shape``
        (wrapped about bin (0, 0)); kept for the last shape."""
        kb = self.bin_kernel(b)
        entry = self._bins[b]
        if entry[1] != tuple(shape):
            rb = kb.shape[0] // 2
            kpad = np.zeros(shape, np.float32)
            idx = np.arange(-rb, rb + 1)
            kpad[np.ix_(idx % shape[0], idx % shape[1])] = kb
            entry[1], entry[2] = tuple(shape), sp_fft.rfft2(kpad, workers=workers)
        return entry[2]

    def spectra(self, shape, dtype, workers=1):
        """Transforms of the kernels zero-padded to ``shape``, centred on
        pixel (0, 0) (wrapped), shape (5, shape[0], shape[1] // 2 + 1); kept
        for the last shape and dtype asked for."""
        key = (tuple(shape), np.dtype(dtype))
        if key not in self._spectra:
            self._spectra.clear()
            idx = np.arange(2 * self.reach + 1) - self.reach
            pad = np.zeros((5,) + tuple(shape), dtype)
            pad[:, (idx % shape[0])[:, None], (idx % shape[1])[None, :]] = self.kernels
            self._spectra[key] = sp_fft.rfft2(pad, axes=(-2, -1), workers=workers)
        return self._spectra[key]


_CACHE = weakref.WeakKeyDictionary()


def linear_kernels(template, *, samples=None):
    """:class:`LinearKernels` of ``template`` (its exact fallback resampled to
    ``samples`` per edge, None: the template's own), cached per template.

    The kernels are the same for any ``samples`` to rounding: resampling
    keeps the integrals of ``s**m`` times every edge profile, m <= 2
    (:func:`~lsst_bfdrift.geometry.superpose.resample_template`), which are
    all that the first-order moments depend on.
    """
    per = _CACHE.setdefault(template, {})
    ns = template.edge_samples if samples is None else min(int(samples), template.edge_samples)
    if ns not in per:
        per[ns] = LinearKernels(template, resample_template(template, ns))
        per[ns].samples = ns
    return per[ns]


def second_order_bounds(eps, chi=4.0):
    """Bounds of abs(exact - linear) per map for boundary displacements up to ``eps``.

    Parameters
    ----------
    eps : float or ndarray
        Largest abs displacement component (px) of any boundary point of
        the pixel (its corners, edge samples and tangential displacements).
    chi : float, optional
        :attr:`LinearKernels.chi`.

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


def _reference_level(q):
    """A typical charge level: the median of at most ~65000 pixels on a grid."""
    step = max(1, int(math.sqrt(q.size / 65536.0)))
    return float(np.median(q[::step, ::step]))


def _bin_kernel(disp, b):
    """``Kb[D]`` = max of ``disp`` over the pixel offsets between bins D apart."""
    r = disp.shape[0] // 2
    rb = -(-(r + b - 1) // b)
    pad = np.zeros((2 * (rb * b + b) + 1,) * 2)
    o = rb * b + b
    pad[o - r:o + r + 1, o - r:o + r + 1] = disp
    full = ndimage.maximum_filter(pad, size=2 * b - 1, mode="constant")
    idx = o + b * np.arange(-rb, rb + 1)
    return full[np.ix_(idx, idx)]


def displacement_bound(lk, q, *, bin=2, workers=1, qbar=None, outside=None):
    """Upper bound of every boundary displacement of each pixel (px), per bin.

    Parameters
    ----------
    lk : LinearKernels
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

    Returns
    -------
    ndarray, shape (ceil(ny / bin), ceil(nx / bin))

    Notes
    -----
    A boundary point's displacement is ``sum_a T(p - a) q(a)`` over the
    image's pixels a, ``= qbar sum_a T + sum_a T (q - qbar)``; the first sum
    differs from the sum over all offsets (at most :attr:`LinearKernels.net`
    per e) by the offsets outside the image. Hence every displacement of
    pixel p is at most ``sum_a disp(p - a) g(a) + abs(qbar) net`` with
    ``g = abs(q - qbar)`` inside the image and ``abs(qbar)`` outside. Per bin
    B: ``sum over bins B' of Kb(B - B') G(B')``, with ``G`` the sums of
    ``g`` over the bins and ``Kb`` the largest ``disp`` between any pixels
    of two bins that far apart (a single-precision FFT convolution, with a
    margin of 1e-5 of the largest value for its rounding).
    """
    from lsst_bfdrift.geometry._linear_kernels import abs_dev_bins

    b = int(bin)
    ny, nx = q.shape
    qbar = _reference_level(q) if qbar is None else float(qbar)
    rb = lk.bin_kernel(b).shape[0] // 2
    nby, nbx = -(-ny // b), -(-nx // b)
    out_level = abs(qbar) if outside is None else float(outside)
    g = np.full((nby + 2 * rb, nbx + 2 * rb), out_level * b * b)
    inner = np.empty((nby, nbx))
    abs_dev_bins(np.ascontiguousarray(q, dtype=np.float64), qbar, b, out_level, inner)
    g[rb:rb + nby, rb:rb + nbx] = inner
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


def _uniform_response(template, lk, qbar, samples):
    """Exact minus linear maps (5, n, n) and the largest boundary displacement
    (n, n) of the pixels of a uniform image of level ``qbar`` (e), n = 2 reach + 1.

    Pixel (j, i) of an image of at least n x n pixels responds to a uniform
    level as pixel (rowmap(j), colmap(i)) of this one (:func:`_index_map`):
    only its distances to the image borders, up to the reach, matter.
    """
    n = 2 * lk.reach + 1
    qs = np.full((n, n), float(qbar))
    ex = moment_maps(template, qs, samples=samples, maps=LINEAR_MAPS)
    lin, _ = _linear_maps(lk, qs, LINEAR_MAPS, (n, n), np.float64, 1)
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
    return corr, eps


def _index_map(size, n):
    """Pixel index in the n-pixel uniform image (:func:`_uniform_response`) of
    every pixel along an axis of ``size`` >= n pixels."""
    r = n // 2
    m = np.full(size, r)
    m[:r] = np.arange(r)
    m[size - r:] = np.arange(r + 1, n)
    return m


def _binned_eps(eps, rowmap, colmap, b, nby, nbx):
    """Largest ``eps[rowmap[j], colmap[i]]`` over every b x b bin."""
    def classes(m, nb):
        keys, idx = {}, np.empty(nb, np.int64)
        for k in range(nb):
            key = tuple(np.unique(m[k * b:(k + 1) * b]))
            idx[k] = keys.setdefault(key, len(keys))
        return list(keys), idx

    ky, iy = classes(rowmap, nby)
    kx, ix = classes(colmap, nbx)
    table = np.array([[eps[np.ix_(a, c)].max() for c in kx] for a in ky])
    return table[iy[:, None], ix[None, :]]


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
    are at most D (:func:`displacement_bound` with nothing outside). The
    linear maps of :func:`linear_moment_maps` include the exact second-order
    terms of d_u; what is left of the remainder R (quadratic to the order
    that matters) is ``R(d_u + d_f) - R(d_u) = 2 B(d_u, d_f) + R(d_f)``, and
    with abs(R(d)) <= C eps**2 the polarisation identity gives abs(2 B(x, y))
    <= 4 C eps_x eps_y: the bound is ``C (4 eps_u D + D**2)`` with C the
    :data:`MEASURED_CONSTANTS`. With ``bound='analytic'``: twice
    :func:`second_order_bounds` of ``eps_u + D`` (the remainders at d and at
    d_u, each bounded).
    Images smaller than the uniform one (2 reach + 1 pixels) use ``eps_u``
    = 0 and D with ``abs(qbar)`` outside the image (the whole displacement).
    """
    lk = linear_kernels(template, samples=samples)
    b = int(bin)
    qbar = _reference_level(q) if qbar is None else float(qbar)
    ny, nx = q.shape
    n = 2 * lk.reach + 1
    nby, nbx = -(-ny // b), -(-nx // b)
    if ny >= n and nx >= n:
        d = displacement_bound(lk, q, bin=b, workers=workers, qbar=qbar, outside=0.0)
        d += abs(qbar) * lk.net
        _, eps_small = _uniform_response(template, lk, qbar, samples)
        eps_u = _binned_eps(eps_small, _index_map(ny, n), _index_map(nx, n), b, nby, nbx)
    else:
        d = displacement_bound(lk, q, bin=b, workers=workers, qbar=qbar)
        eps_u = np.zeros_like(d)
    if bound == "measured":
        x = d * (4.0 * eps_u + d)
        return {k: np.where(eps_u + d <= 0.05, MEASURED_CONSTANTS[k] * x, np.inf)
                for k in LINEAR_MAPS}
    an = second_order_bounds(eps_u + d, lk.chi)
    return {k: 2.0 * an[k] for k in LINEAR_MAPS}


def _boxes(flag, b, shape, *, band, block=32):
    """Pixel boxes (y0, y1, x0, x1) covering the flagged bins.

    Flagged bins within ``band`` bins of the image border (where the
    uniform level's displacements are) make one strip per side, as long as
    the flagged part of that side and as deep as its deepest flagged bin;
    the others, the bounding box of every connected group of flagged bins
    within each ``block`` x ``block`` block of bins.
    """
    ny, nx = shape
    nby, nbx = flag.shape
    flag = flag.copy()
    out = []
    band = min(band, nby // 2, nbx // 2)
    if band > 0:
        sides = ((flag[:band], False, False), (flag[nby - band:][::-1], False, True),
                 (flag[:, :band].T, True, False), (flag[:, nbx - band:][:, ::-1].T, True, True))
        for f, transposed, far in sides:
            if not f.any():
                continue
            depth = int(np.flatnonzero(f.any(axis=1))[-1]) + 1
            cols = np.flatnonzero(f.any(axis=0))
            a, z = int(cols[0]) * b, (int(cols[-1]) + 1) * b
            n_along, n_across = (ny, nx) if transposed else (nx, ny)
            bins_across = nbx if transposed else nby
            lo, hi = ((bins_across - depth) * b, n_across) if far else (0, min(depth * b, n_across))
            z = min(z, n_along)
            out.append((a, z, lo, hi) if transposed else (lo, hi, a, z))
        flag[:band] = flag[nby - band:] = False
        flag[:, :band] = flag[:, nbx - band:] = False
    labels, _ = ndimage.label(flag, structure=np.ones((3, 3), int))
    for sl in ndimage.find_objects(labels):
        for by in range(sl[0].start, sl[0].stop, block):
            for bx in range(sl[1].start, sl[1].stop, block):
                f = flag[by:min(by + block, sl[0].stop), bx:min(bx + block, sl[1].stop)]
                if not f.any():
                    continue
                rows = np.flatnonzero(f.any(axis=1))
                cols = np.flatnonzero(f.any(axis=0))
                out.append(((by + rows[0]) * b, min((by + rows[-1] + 1) * b, ny),
                            (bx + cols[0]) * b, min((bx + cols[-1] + 1) * b, nx)))
    return out


def _exact_windows(template, q, boxes, r, outs, names, *, samples, workers, dtype, strip,
                   progress=None):
    """Exact moments of the pixels in ``boxes``. Every box with ``r`` pixels of
    its charge around it is a slot on a canvas, apart from the other slots by
    its margins (no pixel of a box sees another slot's charge), and
    :func:`moment_maps` runs once per canvas: one for the slots taller than
    wide (the strips along the left and right image borders), side by side,
    one for the others, on shelves. ``progress`` is called with the fraction
    of the canvases' pixels done. Returns the canvases' area (px)."""
    slots = [(y1 - y0 + 2 * r, x1 - x0 + 2 * r, (y0, y1, x0, x1)) for y0, y1, x0, x1 in boxes]
    tall = [sl for sl in slots if sl[0] > 4 * sl[1]]
    rest = sorted((sl for sl in slots if sl[0] <= 4 * sl[1]), reverse=True)
    layouts = []
    for group, shelves in ((tall, False), (rest, True)):
        if not group:
            continue
        total = sum(h * w for h, w, _ in group)
        width = max(max(w for _, w, _ in group), int(math.sqrt(total) * 1.1)) if shelves \
            else sum(w for _, w, _ in group)
        place, x, y, shelf = [], 0, 0, 0
        for h, w, box in group:
            if x + w > width:
                y, x, shelf = y + shelf, 0, 0
            place.append((y, x, box))
            x += w
            shelf = max(shelf, h)
        layouts.append((place, (y + shelf, width)))
    area = sum(shape[0] * shape[1] for _, shape in layouts)
    done = [0]  # canvas pixels finished
    for place, shape in layouts:
        canvas = np.zeros(shape)
        ny, nx = q.shape
        for cy, cx, (y0, y1, x0, x1) in place:
            a0, a1, b0, b1 = max(y0 - r, 0), min(y1 + r, ny), max(x0 - r, 0), min(x1 + r, nx)
            oy, ox = cy + a0 - (y0 - r), cx + b0 - (x0 - r)
            canvas[oy:oy + a1 - a0, ox:ox + b1 - b0] = q[a0:a1, b0:b1]

        def rows(n, width=shape[1]):
            done[0] += n * width
            progress(done[0] / area)

        mm = moment_maps(template, canvas, samples=samples, workers=workers, dtype=dtype,
                         strip=strip, maps=names, progress=None if progress is None else rows)
        for cy, cx, (y0, y1, x0, x1) in place:
            for k, name in enumerate(names):
                outs[k][y0:y1, x0:x1] = getattr(mm, name)[cy + r:cy + r + y1 - y0,
                                                           cx + r:cx + r + x1 - x0]
    return area


def linear_moment_maps(template, charge, *, mask=None, rtol=1e-3, samples=None, fallback=True,
                       bound="measured", tile=(256, 1024), bin=2, max_fraction=0.5, workers=1,
                       dtype=np.float32, strip=256, maps=None, info=None, progress=None):
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
        'analytic' (:func:`second_order_bounds`: a proof, but 2 to 60 times
        the measured worst case, so that a faint field's sky noise alone
        may exceed it and every pixel becomes exact).
    tile : (int, int), optional
        Rows and columns per FFT block of the linear maps (each with a
        halo of the template's reach).
    bin : int, optional
        Side (px) of the bins of the a-priori bound (:func:`displacement_bound`).
    max_fraction : float, optional
        When the exact windows (with their margins) would cover more than
        this fraction of the image, ``moment_maps`` runs on the whole image.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float32, numpy.float64}, optional
        Precision of the FFTs (linear maps and exact fallback).
    strip : int, optional
        Rows per block of the exact fallback.
    maps : sequence of str, optional
        Maps to keep, of :data:`LINEAR_MAPS` (default: all five).
    info : dict, optional
        Filled with ``method`` ('linear', 'linear+exact' or 'exact'),
        ``signal`` (S per map), ``tolerance`` (per map), ``windows``,
        ``exact_fraction`` (flagged bins' share of the image) and
        ``canvas_fraction`` (pixels run through ``moment_maps``, margins
        included, over the image size).
    progress : callable, optional
        Called with the fraction (0 to 1, never decreasing) of the work done:
        the linear maps by rows of tiles, the bound, then the exact moments by
        rows of their canvases; 1 at the end. It does not change the maps.

    Returns
    -------
    MomentMaps
        ``area``, ``dx``, ``dy``, ``e1``, ``e2`` (float64; the second
        moments ``ixx``, ``iyy``, ``ixy`` are None).

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
    """
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
    th, tw = (int(v) for v in tile)
    if th < 1 or tw < 1 or int(bin) < 1:
        raise InputError(f"tile and bin must be positive, got {tile!r}, {bin!r}")
    info = {} if info is None else info
    q = np.asarray(charge)
    if mask is not None or q.dtype != np.float64 or q.ndim != 2 or q.size == 0 \
            or not np.isfinite(q).all():
        q = check_charge_image(charge, mask=mask, template=template)
    else:
        refuse_out_of_range(q, kernel_abs_sum(template))  # the package's one range check
    ny, nx = q.shape
    lk = linear_kernels(template, samples=samples)
    r = lk.reach
    out = MomentMaps((0, 0), ())
    # shares of the time on a 4k x 4k field with 400 stars (the exact moments dominate)
    linear_share, bound_share = (0.15, 0.23) if fallback else (1.0, 1.0)

    def report(fraction):
        if progress is not None:
            progress(fraction)

    outs, smax = _linear_maps(lk, q, names, (th, tw), dtype, workers,
                              progress=lambda f: report(linear_share * f))
    for name, arr in zip(names, outs):
        setattr(out, name, arr)
    signal = dict(zip(LINEAR_MAPS, smax.tolist()))
    tol = {k: 0.9 * rtol * v for k, v in signal.items()}
    info.update(method="linear", signal=signal, tolerance=tol, windows=0,
                exact_fraction=0.0, canvas_fraction=0.0)
    qbar = _reference_level(q)
    n = 2 * r + 1
    if ny >= n and nx >= n:
        # exact second-order terms of the uniform level near the image border
        corr, _ = _uniform_response(template, lk, qbar, samples)
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
    if not fallback:
        report(1.0)
        return out
    bounds = error_bounds(template, q, samples=samples, bin=bin, bound=bound,
                          workers=workers, qbar=qbar)
    report(bound_share)
    flag = np.zeros(bounds["area"].shape, bool)
    for k in LINEAR_MAPS:
        flag |= bounds[k] > tol[k]
    if not flag.any():
        report(1.0)
        return out

    def exact(fraction):
        report(bound_share + (1.0 - bound_share) * min(fraction, 1.0))
    b = int(bin)
    info["exact_fraction"] = float(flag.sum()) * b * b / q.size
    boxes = _boxes(flag, b, q.shape, band=-(-r // b))
    canvas = sum((y1 - y0 + 2 * r) * (x1 - x0 + 2 * r) for y0, y1, x0, x1 in boxes)
    if canvas > max_fraction * q.size:
        rows = [0]

        def row_progress(n):
            rows[0] += n
            exact(rows[0] / ny)

        mm = moment_maps(template, q, samples=samples, workers=workers, dtype=dtype,
                         strip=strip, maps=names, progress=row_progress)
        for k, name in enumerate(names):
            outs[k][:] = getattr(mm, name)
        info.update(method="exact", windows=1, canvas_fraction=1.0)
        report(1.0)
        return out
    area = _exact_windows(template, q, boxes, r, outs, names, samples=samples,
                          workers=workers, dtype=dtype, strip=strip, progress=exact)
    info.update(method="linear+exact", windows=len(boxes), canvas_fraction=area / q.size)
    report(1.0)
    return out


def _linear_maps(lk, q, names, tile, dtype, workers, progress=None):
    """The first-order maps (float64, in ``names`` order) by tiled FFTs, and
    max abs(map - nominal) of all five; ``progress`` is called with the
    fraction of the rows done after each row of tiles."""
    from lsst_bfdrift.geometry._linear_kernels import store_tile

    ny, nx = q.shape
    r = lk.reach
    th, tw = min(tile[0], ny), min(tile[1], nx)
    fshape = (sp_fft.next_fast_len(th + 2 * r), sp_fft.next_fast_len(tw + 2 * r))
    spec = lk.spectra(fshape, dtype, workers)
    store = np.empty((len(names), ny, nx))
    slot = np.array([names.index(k) if k in names else -1 for k in LINEAR_MAPS], np.int64)
    smax = np.zeros(len(LINEAR_MAPS))
    pad = np.zeros(fshape, dtype)
    for y0 in range(0, ny, th):
        h = min(th, ny - y0)
        for x0 in range(0, nx, tw):
            w = min(tw, nx - x0)
            a0, a1, b0, b1 = max(y0 - r, 0), min(y0 + h + r, ny), max(x0 - r, 0), min(x0 + w + r, nx)
            pad[:] = 0.0
            pad[a0 - (y0 - r):a1 - (y0 - r), b0 - (x0 - r):b1 - (x0 - r)] = q[a0:a1, b0:b1]
            f = sp_fft.rfft2(pad, workers=workers)
            res = sp_fft.irfft2(spec * f, fshape, axes=(-2, -1), workers=workers,
                                overwrite_x=True)
            store_tile(res, r, y0, x0, h, w, _NOMINAL, slot, store, smax)
        if progress is not None:
            progress((y0 + h) / ny)
    return [store[k] for k in range(len(names))], smax
