"""First-order maps only where the charge varies: the windowed route of
:func:`~lsst_bfdrift.geometry.linear.linear_moment_maps`.

The first-order map k of an image q is ``L_k(q) = L_k(qbar) + L_k(q - qbar)``
(qbar: the image's reference level). ``L_k(qbar)`` is the response of a
uniform image, computed on a small uniform image (its values depend only on
a pixel's distances to the border, up to the reach). The second term is at
most ``beta_k(p) = sum_s abs(K_k(s)) abs(q - qbar)(p - s)`` (K_k: the map's
kernel); where that bound is below what the tolerance leaves, the uniform
response is returned, elsewhere ``L_k(q)`` is computed in windows (FFT
convolutions of a packed canvas of boxes, :func:`windowed_maps`).

:func:`signal_floor` gives a lower bound of each map's signal (the maps of
a box around the pixel farthest from qbar); :func:`first_order_bound` bounds
``max_k beta_k / (rtol S_k)`` per bin with one single-precision FFT
convolution; :func:`expected_route` tells, from a sample of the image,
whether the windows can cover less than the image (a sky whose noise alone
exceeds the tolerance makes them cover all of it).
"""

import numpy as np
from scipy import fft as sp_fft

from lsst_bfdrift.geometry._exact import packed_canvas
from lsst_bfdrift.geometry._linear_kernels import abs_dev_cell_max
from lsst_bfdrift.geometry.bounds import bin_abs_dev, reference_level
from lsst_bfdrift.geometry.first_order import (_NOMINAL, LINEAR_MAPS, _bin_kernel, _map_store,
                                               convolved_first_order_maps)

__all__ = ["signal_floor", "expected_route", "first_order_bound", "windowed_maps"]

#: Half side (px) of the box around the pixel farthest from the reference
#: level whose first-order maps give :func:`signal_floor`.
_FLOOR_HALF = 4

#: Cell side (px) of :func:`expected_route`'s estimate of the windows' area.
_CELL = 16

#: Largest typical bound (``max_k beta_k / (rtol S_k)`` over the sky, from a
#: sample) for which :func:`expected_route` expects windows: above it, noise
#: alone flags a large share of the bins.
_EXPECTED_SKY = 0.5


def _index_map(size, n):
    """Pixel index in the n-pixel uniform image
    (:func:`~lsst_bfdrift.geometry.linear._uniform_response`) of
    every pixel along an axis of ``size`` >= n pixels."""
    r = n // 2
    m = np.full(size, r)
    m[:r] = np.arange(r)
    m[size - r:] = np.arange(r + 1, n)
    return m


def signal_floor(lk, q, qbar):
    """Lower bound of each map's signal and the box it comes from.

    Parameters
    ----------
    lk : LinearKernels
    q : ndarray, shape (ny, nx), float64
        Charge (e).
    qbar : float
        Reference level (e).

    Returns
    -------
    floor : ndarray, shape (5,)
        max abs(L_k(q) - nominal) over the box, per map of :data:`LINEAR_MAPS`:
        at most the signal of the first-order maps.
    box : (int, int, int, int)
        (y0, y1, x0, x1), the box: ``2 * _FLOOR_HALF + 1`` pixels a side
        around the pixel farthest from ``qbar`` (clipped to the image).
    """
    ny, nx = q.shape
    r = lk.reach
    hi, lo = int(np.argmax(q)), int(np.argmin(q))
    j, i = divmod(hi if q.flat[hi] - qbar >= qbar - q.flat[lo] else lo, nx)
    h = _FLOOR_HALF
    y0, y1, x0, x1 = max(j - h, 0), min(j + h + 1, ny), max(i - h, 0), min(i + h + 1, nx)
    a0, a1, b0, b1 = max(y0 - r, 0), min(y1 + r, ny), max(x0 - r, 0), min(x1 + r, nx)
    cut = q[a0:a1, b0:b1]
    # the cut-out holds every aggressor of the box's pixels (zero beyond the
    # image, as the image's own transforms give): their maps are exact
    maps, _ = convolved_first_order_maps(lk, cut, LINEAR_MAPS, tile=cut.shape,
                                         dtype=np.float64)
    floor = np.array([np.abs(m[y0 - a0:y1 - a0, x0 - b0:x1 - b0] - nom).max()
                      for m, nom in zip(maps, _NOMINAL)])
    return floor, (y0, y1, x0, x1)


def _weighted_kernel(lk, weights):
    """``max_k weights[k] abs(K_k)`` per offset (shape of the kernels)."""
    return np.max(np.abs(lk.kernels) * np.asarray(weights)[:, None, None], axis=0)


def expected_route(lk, q, qbar, floor, rtol, *, bin=2, window_fraction=0.3):
    """'windows' when the sky's bound, estimated from a sample of the image,
    leaves room for windows; else 'full'.

    Parameters
    ----------
    lk : LinearKernels
    q : ndarray, shape (ny, nx), float64
    qbar : float
        Reference level (e).
    floor : ndarray, shape (5,)
        :func:`signal_floor`.
    rtol : float
        The maps' tolerance (fraction of each map's signal).
    bin : int, optional
        Bin side (px) of :func:`first_order_bound`.
    window_fraction : float, optional
        Largest share of the image the windows may cover.

    Notes
    -----
    A guess, not a bound (the route does not change the accuracy, only the
    time). First the typical :func:`first_order_bound` (weights ``1 / (rtol
    floor_k)``) of the sky, with the median of ``abs(q - qbar)`` over at most
    ~65000 pixels on a grid in every pixel: above ``_EXPECTED_SKY`` the
    windows would cover most of the image. Then the windows' area: every
    ``_CELL`` x ``_CELL`` cell holding a pixel whose own term of the bound
    exceeds 1 where it lies (a source) is taken for a window of the cell
    and the template's reach around it; 'full' when those cover more than
    ``window_fraction`` of the image (a crowded field).
    """
    if not np.all(floor > 0.0):
        return "full"
    b = int(bin)
    step = max(1, int(np.sqrt(q.size / 65536.0)))
    g = float(np.median(np.abs(q[::step, ::step] - qbar)))
    kernel = _weighted_kernel(lk, 1.0 / (rtol * floor))
    if g * b * b * _bin_kernel(kernel, b).sum() > _EXPECTED_SKY:
        return "full"
    cells = np.empty((-(-q.shape[0] // _CELL), -(-q.shape[1] // _CELL)))
    abs_dev_cell_max(np.ascontiguousarray(q, dtype=np.float64), float(qbar), _CELL, cells)
    hot = int(np.count_nonzero(cells * kernel.max() > 1.0))
    area = hot * (_CELL + 2 * lk.reach) ** 2
    return "windows" if area <= window_fraction * q.size else "full"


def first_order_bound(lk, q, qbar, weights, *, bin, workers, bin_sums=None):
    """Upper bound of ``max_k weights[k] beta_k(p)`` over each bin's pixels.

    Parameters
    ----------
    lk : LinearKernels
    q : ndarray, shape (ny, nx), float64
        Charge (e).
    qbar : float
        Reference level (e).
    weights : ndarray, shape (5,)
        Per map of :data:`LINEAR_MAPS` (per map unit).
    bin : int
        Bin side (px).
    workers : int
        FFT threads.
    bin_sums : ndarray, optional
        :func:`~lsst_bfdrift.geometry.bounds.bin_abs_dev` of ``q`` (``qbar``,
        ``bin``, nothing outside) when already computed.

    Returns
    -------
    ndarray, shape (ceil(ny / bin), ceil(nx / bin))

    Notes
    -----
    As :func:`~lsst_bfdrift.geometry.bounds.displacement_bound` with nothing
    outside the image: the sums G of ``abs(q - qbar)`` over the bins
    convolved with the largest weighted kernel ``max_k weights[k]
    abs(K_k)`` between any pixels of two bins that far apart (single
    precision, a margin of 1e-5 of the largest value and 1e-5 relative for
    its rounding). A bound of each ``weights[k] beta_k``: each map's kernel
    is at most the combined one at every offset.
    """
    b = int(bin)
    ny, nx = q.shape
    kb = _bin_kernel(_weighted_kernel(lk, weights), b)
    rb = kb.shape[0] // 2
    nby, nbx = -(-ny // b), -(-nx // b)
    g = np.zeros((nby + 2 * rb, nbx + 2 * rb))
    g[rb:rb + nby, rb:rb + nbx] = bin_abs_dev(q, qbar, b, 0.0) if bin_sums is None \
        else bin_sums
    shape = (sp_fft.next_fast_len(g.shape[0] + 2 * rb),
             sp_fft.next_fast_len(g.shape[1] + 2 * rb))
    kpad = np.zeros(shape, np.float32)
    idx = np.arange(-rb, rb + 1)
    kpad[np.ix_(idx % shape[0], idx % shape[1])] = kb
    d = sp_fft.irfft2(sp_fft.rfft2(g.astype(np.float32), shape, workers=workers)
                      * sp_fft.rfft2(kpad, workers=workers), shape, workers=workers)
    d = d[rb:rb + nby, rb:rb + nbx].astype(np.float64)
    d += 1e-5 * d.max()
    d *= 1.0 + 1e-5
    return d


def windowed_maps(lk, q, boxes, uniform_lin, names, *, map_dtype, dtype, workers, strip):
    """First-order maps: the uniform response, and ``L_k(q)`` in ``boxes``.

    Parameters
    ----------
    lk : LinearKernels
    q : ndarray, shape (ny, nx), float64
        Charge (e); at least 2 reach + 1 pixels a side.
    boxes : list of (int, int, int, int)
        (y0, y1, x0, x1) of the windows.
    uniform_lin : ndarray, shape (5, n, n)
        First-order maps (nominal included) of the uniform image of the
        reference level, n = 2 reach + 1
        (:func:`~lsst_bfdrift.geometry.linear._uniform_response`).
    names : tuple of str
        Maps to keep, of :data:`LINEAR_MAPS`.
    map_dtype, dtype : numpy dtype
        Of the stored maps but the area (float64), and of the windows' FFTs.
    workers, strip : int
        FFT threads; rows per tile of the windows' canvas.

    Returns
    -------
    outs : list of ndarray
        The maps in ``names`` order.
    smax : ndarray, shape (5,)
        max abs(map - nominal) over the image, per map of :data:`LINEAR_MAPS`.
    canvas_size : int
        Pixels of the windows' canvas (margins included).
    """
    ny, nx = q.shape
    r = lk.reach
    n = 2 * r + 1
    _, _, _, outs = _map_store(names, (ny, nx), map_dtype)
    rm, cm = _index_map(ny, n), _index_map(nx, n)
    smax = np.zeros(len(LINEAR_MAPS))
    # 1. the uniform response everywhere (its interior value, then the
    # border strips from the small image)
    for name, o in zip(names, outs):
        u = uniform_lin[LINEAR_MAPS.index(name)]
        o.fill(u[r, r])
        for rows in (slice(0, r), slice(ny - r, ny)):
            o[rows] = u[rm[rows]][:, cm]
        for cols in (slice(0, r), slice(nx - r, nx)):
            o[r:ny - r, cols] = u[r, cm[cols]]
    # 2. L_k(q) in the windows (all five maps tracked for the signal)
    size = 0
    if boxes:
        canvas, place = packed_canvas(q, boxes, r)
        size = canvas.size
        maps, _ = convolved_first_order_maps(lk, canvas, LINEAR_MAPS,
                                             tile=(int(strip), canvas.shape[1]), dtype=dtype,
                                             workers=workers)
        for cy, cx, (y0, y1, x0, x1) in place:
            for k, (m, nom) in enumerate(zip(maps, _NOMINAL)):
                part = m[cy:cy + y1 - y0, cx:cx + x1 - x0]
                smax[k] = max(smax[k], float(np.abs(part - nom).max()))
                if LINEAR_MAPS[k] in names:
                    outs[names.index(LINEAR_MAPS[k])][y0:y1, x0:x1] = part
    # 3. the signal over the pixels left uniform: the interior value (the
    # windows never cover the whole interior on this route) and the border
    # strips as they are now (of a map not kept: the interior value only, a
    # lower bound, which makes the tolerance smaller)
    for k, name in enumerate(LINEAR_MAPS):
        v = abs(uniform_lin[k][r, r] - _NOMINAL[k])
        if name in names:
            o = outs[names.index(name)]
            for part in (o[:r], o[ny - r:], o[:, :r], o[:, nx - r:]):
                v = max(v, float(np.abs(part - _NOMINAL[k]).max()))
        smax[k] = max(smax[k], v)
    return outs, smax, size
