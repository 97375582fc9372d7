"""The first-order geometry maps: kernels of a template and one pass over an image.

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

:class:`FirstOrderPass` fills the maps block by block from the swept-area
operator's own transforms (what a correction computes anyway);
:mod:`~lsst_bfdrift.geometry.linear` adds the exact moments where the first
order is not enough.
"""

import weakref

import numpy as np
from scipy import fft as sp_fft
from scipy import ndimage

from lsst_bfdrift.geometry._linear_kernels import combine_rows, store_tile
from lsst_bfdrift.geometry.superpose import resample_template
from lsst_bfdrift.templates.swept import swept_area_kernels
from lsst_bfdrift.utils.errors import InputError

__all__ = ["LINEAR_MAPS", "LinearKernels", "linear_kernels", "FirstOrderPass",
           "convolved_first_order_maps"]

#: Maps that :func:`linear_moment_maps` computes, in the order of
#: :attr:`LinearKernels.kernels`.
LINEAR_MAPS = ("area", "dx", "dy", "e1", "e2")
_NOMINAL = np.array([1.0, 0.0, 0.0, 0.0, 0.0])


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
        self.reach = t.center + 1
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
        # the same maps from edge fields (FirstOrderPass): the swept areas
        # (moment 0) of the vertical and horizontal edges, laid out as the
        # swept-area kernels, their first moments, and the second-moment
        # part of e1 per pixel
        mv = mom(t.corner_d[:-1, :, 0], t.vedge_d, t.corner_d[1:, :, 0])
        mh = mom(t.corner_d[:, :-1, 1], t.hedge_d, t.corner_d[:, 1:, 1])
        self.edge_kernels = (mv[1] / t.charge, mh[1] / t.charge,
                             (vT[2] - vB[2] - uR[2] + uL[2]) / t.charge)
        self._edge_spectra = {}
        # the swept-area kernels leave out the edges beyond the template whose
        # one end is a displaced corner of its outer boundary; where those
        # are not zero the maps are convolved directly (five kernels)
        kv, kh = (k / t.charge for k in swept_area_kernels(t))
        self.decomposed = bool(np.abs(self._recombined(kv, kh) - self.kernels).max()
                               <= 1e-12 * np.abs(self.kernels).max())
        # displacement bound of the exact template's boundary points
        ns = e.edge_samples
        ac = np.zeros((n + 3, n + 3))
        ac[1:n + 2, 1:n + 2] = np.abs(e.corner_d).max(-1)
        av = np.zeros((n + 2, n + 3))
        av[1:n + 1, 1:n + 2] = np.abs(e.vedge_d).max(-1)
        ah = np.zeros((n + 3, n + 2))
        ah[1:n + 2, 1:n + 1] = np.abs(e.hedge_d).max(-1)
        sums = [np.abs(e.corner_d.sum(axis=(0, 1))).max(),
                np.abs(e.vedge_d.sum(axis=(0, 1))).max(),
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
        """:attr:`disp` per ``b`` x ``b`` bins (:func:`~.displacement_bound`)."""
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

    def _recombined(self, sv, sh):
        """The five map kernels from the swept-area kernels ``sv`` (N, N + 1),
        ``sh`` (N + 1, N) and :attr:`edge_kernels`, as
        :class:`FirstOrderPass` combines the fields (shape (5, N + 2, N + 2))."""
        m1v, m1h, p3 = self.edge_kernels
        m = p3.shape[0]

        def pad(k, dy, dx):  # kernel on the pixel offsets' grid, edge index + d
            out = np.zeros((m + 1, m + 1))
            out[1 + dy:1 + dy + k.shape[0], 1 + dx:1 + dx + k.shape[1]] = k
            return out[:m, :m]

        svl, svr = pad(sv, 0, 0), pad(sv, 0, -1)
        shb, sht = pad(sh, 0, 0), pad(sh, -1, 0)
        vl, vr = pad(m1v, 0, 0), pad(m1v, 0, -1)
        hb, ht = pad(m1h, 0, 0), pad(m1h, -1, 0)
        dv, dh = svr - svl, sht - shb
        return np.stack([dv + dh, 0.5 * (svl + svr) + ht - hb, 0.5 * (shb + sht) + vr - vl,
                         6.0 * (0.25 * (dv - dh) + p3), 6.0 * (vl + vr + hb + ht)])

    def edge_spectra(self, shape, dtype, workers=1):
        """Transforms of the kernels of :class:`FirstOrderPass` padded to
        ``shape`` in the frame of :class:`~lsst_bfdrift.templates.swept.SweptAreas`:
        :attr:`edge_kernels` when :attr:`decomposed` (the vertical- and
        horizontal-edge kernels at the origin as the swept-area kernels, the
        pixel kernel at offset (-1, -1), wrapped), else the five
        :attr:`kernels` (at offset (-1, -1)); shape (3 or 5, shape[0],
        shape[1] // 2 + 1), kept for the last eight shapes."""
        key = (tuple(shape), np.dtype(dtype))
        if key not in self._edge_spectra:
            if len(self._edge_spectra) >= 8:
                self._edge_spectra.pop(next(iter(self._edge_spectra)))
            idx = np.arange(2 * self.reach + 1) - 1
            at = ((idx % shape[0])[:, None], (idx % shape[1])[None, :])
            if self.decomposed:
                kv, kh, kp = self.edge_kernels
                pad = np.zeros((3,) + tuple(shape), dtype)
                pad[0, :kv.shape[0], :kv.shape[1]] = kv
                pad[1, :kh.shape[0], :kh.shape[1]] = kh
                pad[2][at] = kp
            else:
                pad = np.zeros((5,) + tuple(shape), dtype)
                pad[(slice(None),) + at] = self.kernels
            self._edge_spectra[key] = sp_fft.rfft2(pad, axes=(-2, -1), workers=workers)
        return self._edge_spectra[key]

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


def _framed(view, shape, c):
    """The C-contiguous array of ``shape`` whose ``[c:, c:]`` is ``view`` (the
    swept-area operator's padded output, no copy), else a copy of ``view``
    placed there."""
    base = view.base
    if base is not None and base.shape == shape and base.flags.c_contiguous \
            and base.dtype == view.dtype:
        start = view.__array_interface__["data"][0] - base.__array_interface__["data"][0]
        if start == (c * shape[1] + c) * base.itemsize and view.strides == base.strides:
            return base
    out = np.zeros(shape, view.dtype)
    out[c:c + view.shape[0], c:c + view.shape[1]] = view
    return out


def _map_store(names, shape, dtype):
    """Storage of the maps ``names``: the slot of each of :data:`LINEAR_MAPS`
    in the store (-1: not kept; the area's own array when kept), the store
    (k, ny, nx) of ``dtype`` for dx, dy, e1, e2, the area (float64, always:
    it is 1 plus a signal that can be below single precision's 6e-8), and
    the maps in ``names`` order."""
    others = [k for k in names if k != "area"]
    store = np.empty((len(others),) + tuple(shape), dtype)
    area = np.empty(tuple(shape) if "area" in names else (0, 0))
    slot = np.array([0 if (k == "area" and k in names) else
                     others.index(k) if k in others else -1 for k in LINEAR_MAPS], np.int64)
    outs = [area if k == "area" else store[others.index(k)] for k in names]
    return slot, store, area, outs


class FirstOrderPass:
    """The first-order maps of one charge image, filled block by block.

    The swept-area operator (:class:`~lsst_bfdrift.templates.swept.SweptAreas`)
    transforms each block of rows of the image once; three more kernels
    (:meth:`LinearKernels.edge_spectra`: the first moments of the vertical
    and of the horizontal edges' normal displacements, and the
    second-moment part of e1) share that transform, and the five maps
    follow per pixel from the swept areas and those three fields:

    * area ``1 + sv_R - sv_L + sh_T - sh_B``;
    * ``dx = (sv_L + sv_R) / 2 + m1h_T - m1h_B``,
      ``dy = (sh_B + sh_T) / 2 + m1v_R - m1v_L``;
    * ``e1 = 6 ((sv_R - sv_L - sh_T + sh_B) / 4 + p3)``,
      ``e2 = 6 (m1v_L + m1v_R + m1h_B + m1h_T)``

    (L, R, B, T: the pixel's left, right, bottom, top edges), the kernels of
    :attr:`LinearKernels.kernels` rearranged. A correction that applies the
    operator to the image (the drift series' first order, the astier23
    pass) gives the maps at the cost of three inverse transforms per block.

    Parameters
    ----------
    template : DistortionTemplate
        The operator's template.
    shape : (int, int)
        The image's shape (ny, nx).
    maps : sequence of str, optional
        Maps to keep, of :data:`LINEAR_MAPS` (default: all five; every map's
        signal is tracked).
    samples : int, optional
        As for :func:`linear_moment_maps` (the same kernels).
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the stored centroid and ellipticity maps (float32
        rounds them to 6e-8 of their value; they are computed in float64
        from the operator's fields either way); the area is float64.

    Attributes
    ----------
    outs : list of ndarray
        The kept maps (area float64, the others ``dtype``), in ``maps``
        order; rows not yet done are undefined.
    smax : ndarray, shape (5,)
        max abs(map - nominal) over the rows done, per map of
        :data:`LINEAR_MAPS`.
    rows : int
        Rows done (blocks come in order from row 0).
    """

    def __init__(self, template, shape, *, maps=None, samples=None, dtype=np.float64):
        self.lk = linear_kernels(template, samples=samples)
        self.names = LINEAR_MAPS if maps is None else tuple(maps)
        self.shape = (int(shape[0]), int(shape[1]))
        if np.dtype(dtype) not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise InputError(f"dtype must be float64 or float32, got {dtype!r}")
        self.dtype = np.dtype(dtype)
        self._slot, self._store, self._area, self.outs = _map_store(self.names, self.shape,
                                                                    self.dtype)
        self.smax = np.zeros(len(LINEAR_MAPS))
        self.rows = 0

    @property
    def complete(self):
        """True when every row is done."""
        return self.rows >= self.shape[0]

    def spectra(self, op):
        """The three kernels' transforms for operator ``op``'s padded shape."""
        return self.lk.edge_spectra(op.fshape, op.dtype, op.workers)

    def add(self, sv, sh, more, a, r0, r1):
        """Maps of image rows r0..r1-1 from a block that starts at image row ``a``.

        Parameters
        ----------
        sv, sh : ndarray
            The block's swept areas (the operator's outputs, px^2).
        more : list of ndarray
            The operator's convolutions with :meth:`spectra` (whole padded
            arrays).
        a, r0, r1 : int
            Image rows: the block's first, and the rows to fill (within
            the block, at least the template's reach from its cut sides).
        """
        if r0 != self.rows:
            raise InputError(f"blocks must come in order: expected row {self.rows}, got {r0}")
        c = self.lk.reach - 1
        nx = self.shape[1]
        if self.lk.decomposed:
            # the operator's whole padded outputs (contiguous): sv, sh are views
            # starting at (c, c)
            full = more[0].shape
            combine_rows(_framed(sv, full, c), _framed(sh, full, c), more[0], more[1], more[2],
                         c, r0 - a, r0, r1, self._slot, self._store, self._area, self.smax)
        else:
            store_tile(np.stack(more)[:, r0 - a:], c, r0, 0, r1 - r0, nx, _NOMINAL,
                       self._slot, self._store, self._area, self.smax)
        self.rows = r1

    def run(self, q, ops, *, rows=512, progress=None):
        """Fill every row from ``q`` with the operators ``ops`` (an
        :class:`~lsst_bfdrift.templates.swept.OperatorCache`), ``rows`` per
        block (each with a halo of the template's reach); ``progress`` is
        called with the fraction of the image's rows done after each block."""
        ny, nx = self.shape
        r = self.lk.reach
        for r0 in range(self.rows, ny, rows):
            r1 = min(r0 + rows, ny)
            a, z = max(r0 - r, 0), min(r1 + r, ny)
            op = ops((z - a, nx))
            # the previous block's outputs are freed only once these exist (no
            # page faults for memory given back and taken again)
            sv, sh, more = op(q[a:z], extra=self.spectra(op))
            self.add(sv, sh, more, a, r0, r1)
            if progress is not None:
                progress(self.rows / ny)
        return self


def convolved_first_order_maps(lk, q, names, *, tile, dtype, workers=1, progress=None):
    """The first-order maps by direct FFT convolution with the five map kernels.

    The reference of :class:`FirstOrderPass` (which gets the same maps from
    the swept-area operator's transforms); also the first-order maps of the
    small uniform image from which
    :func:`~lsst_bfdrift.geometry.linear.linear_moment_maps` takes the exact
    second-order terms near the image border.

    Parameters
    ----------
    lk : LinearKernels
        The kernels (:attr:`LinearKernels.kernels`).
    q : ndarray, shape (ny, nx), float64
        Charge (e).
    names : sequence of str
        Maps to keep, of :data:`LINEAR_MAPS`.
    tile : (int, int)
        Tile shape (rows, columns) of the convolutions (each with a halo of
        the template's reach).
    dtype : {numpy.float64, numpy.float32}
        Precision of the transforms.
    workers : int, optional
        FFT threads.
    progress : callable, optional
        Called with the fraction of the rows done after each row of tiles.

    Returns
    -------
    maps : list of ndarray
        The maps (float64), in ``names`` order.
    smax : ndarray, shape (5,)
        max abs(map - nominal) per map of :data:`LINEAR_MAPS` (all five).
    """
    ny, nx = q.shape
    r = lk.reach
    th, tw = min(tile[0], ny), min(tile[1], nx)
    fshape = (sp_fft.next_fast_len(th + 2 * r), sp_fft.next_fast_len(tw + 2 * r))
    spec = lk.spectra(fshape, dtype, workers)
    slot, store, area, outs = _map_store(names, (ny, nx), np.float64)
    smax = np.zeros(len(LINEAR_MAPS))
    pad = np.zeros(fshape, dtype)
    for y0 in range(0, ny, th):
        h = min(th, ny - y0)
        for x0 in range(0, nx, tw):
            w = min(tw, nx - x0)
            a0, a1, b0, b1 = (max(y0 - r, 0), min(y0 + h + r, ny),
                              max(x0 - r, 0), min(x0 + w + r, nx))
            pad[:] = 0.0
            pad[a0 - (y0 - r):a1 - (y0 - r), b0 - (x0 - r):b1 - (x0 - r)] = q[a0:a1, b0:b1]
            f = sp_fft.rfft2(pad, workers=workers)
            res = sp_fft.irfft2(spec * f, fshape, axes=(-2, -1), workers=workers,
                                overwrite_x=True)
            store_tile(res, r, y0, x0, h, w, _NOMINAL, slot, store, area, smax)
        if progress is not None:
            progress((y0 + h) / ny)
    return outs, smax
