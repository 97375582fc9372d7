"""Inverse series with its higher-order terms computed only where they matter.

The third-order inverse series of :mod:`lsst_bfdrift.correction.solvers` is

    F = I - b/2 + x2 + x3,  b = B(I, I),  x2 = c/4 + (1/4 - a3) d,
    c = B(b, I),  d = B(I, b),  x3 = -B(x2, I)/2 + (a3/2 - 1/8) B(b, b) + B(I, y),

with B(f, Q) the edge transfer for densities from f and swept areas from Q.
The first-order term b needs the swept areas of the image (one operator
application over the whole image, :func:`first_order_terms`: the work of the
astier23 pass); x2 and x3 need two more applications (swept areas of b and
of y). On a sky image those are negligible almost everywhere: they are
second and third order in the brighter-fatter strength and scale with abs(b),
which is large only in and around bright sources. Here they are computed
on windows around those sources (batched FFTs of the windows, zero-padded
to a few standard shapes).

Bound for what is left out. For a charge image g whose largest value
within the template's reach of a pixel p is G, every swept area at p is at
most K G (K: the largest sum of abs(kernel) over one edge,
:attr:`~lsst_bfdrift.templates.swept.OperatorCache.kernel_abs_sum`) and every edge
density at most 4/3 max abs(I) within 2 pixels (the four-point stencils), so
abs(B(I, g)(p)) <= 5.4 K max abs(I) G and abs(B(g, I)(p)) <= 5.4 K max abs(I) G. With
r = K max abs(I) (< 0.2 for any sensor this package models), abs(c) <= 5.4 r max abs(b),
and the terms left out where b is at most beta are bounded by
abs(c)/4 + abs(d)/12 + abs(x3) <= (1.34 + 0.45 + O(r)) r beta < 2 r beta. A cell of
``cell`` x ``cell`` pixels is *active* when

    safety K max abs(I) max abs(b) > min limit,

max abs(b) over the cell, max abs(I) and min limit over the 5 x 5 cells around it
(the template's reach and the stencil fit in two cells), ``safety`` = 20,
so that everything left out is below 0.1 x limit. Windows are the active
cells dilated by ``dilate`` cells, overlapping boxes merged; inside a
window the terms are exact up to the contributions of the inactive cells
beyond it (same bound). Each window is solved with its border edges closed
(its terms sum to zero, so the correction conserves flux exactly). Two
checks guard the truncation: the computed terms within 2..5 pixels of a
window's border must be below ``ring_fraction`` x limit (else all windows
grow by one cell, at most twice), and the a-priori fourth-order estimate of
the dense solver must pass in every window. When a check fails,
:func:`sparse_series` returns None and the caller uses the dense solver.
When the windows would cover more than ``max_fraction`` of the image (a
bright flat, a crowded field), a second tier takes over
(:mod:`lsst_bfdrift.correction.tiles`: a tighter per-cell bound and
overlapping windows with a halo) unless its windows would cover more than
``second_max_fraction`` of it.
"""

import numba
import numpy as np
from scipy import ndimage

from lsst_bfdrift.correction._edge_kernels import density_weight, fused_serial, fused_transfer
from lsst_bfdrift.correction.settings import RECOMMENDED
from lsst_bfdrift.correction.tiles import (bound_constants, cell_bound, halo_windows,
                                           window_sides)
from lsst_bfdrift.utils.errors import InputError

__all__ = ["first_order_terms", "active_cells", "active_from_stats", "tolerance", "window_boxes",
           "apriori_ok", "sparse_series"]


def first_order_terms(img, blocked, ops, *, strip, cubic, stop=None, keep_swept=True,
                      cell=None, maps=None):
    """F1 = I - b/2 (b = B(I, I)) and the swept areas of I, by strips of rows.

    Parameters
    ----------
    img : ndarray, shape (ny, nx), float64
        Recorded image (e), finite (non-finite pixels set to 0 and blocked).
    blocked : ndarray of bool
        Pixels that neither give nor receive flux.
    ops : OperatorCache
        Operators of the template.
    strip : int or None
        Rows per block (None: whole image). Blocks overlap by
        ``(N + 1) // 2 + 2`` rows, which makes b exact.
    cubic : bool or str
        Edge flux density (see :func:`lsst_bfdrift.correction._edge_kernels.fused_transfer`).
    stop : callable, optional
        Called as ``stop(r1, stats, (first, sv, sh))`` after each block (rows
        ``0..r1-1`` of ``first`` and ``sv`` done, of ``sh`` rows ``0..r1-1``;
        ``stats`` as returned, None without ``cell``); when it returns True
        the work is abandoned and None returned.
    keep_swept : bool, optional
        Keep the swept areas (False: ``sv`` and ``sh`` are returned as None;
        the astier23 pass needs only ``first``).
    cell : int, optional
        Also gather, per ``cell`` x ``cell`` cell, max abs(I), min I and
        max abs(b) (the statistics of :func:`active_cells`) while each block
        is in cache.
    maps : FirstOrderPass, optional
        First-order geometry maps of ``img``
        (:class:`~lsst_bfdrift.geometry.first_order.FirstOrderPass`), computed
        block by block from the same transforms of the image as the swept
        areas (the swept areas and ``first`` are the same, bit for bit).

    Returns
    -------
    first : ndarray, shape (ny, nx), float64
        First-order corrected image (e); the first-order transfer is
        b = 2 (I - first) (exact to rounding: no copy of b is kept).
    sv : ndarray, shape (ny, nx + 1)
    sh : ndarray, shape (ny + 1, nx)
        Swept areas of the image's edges (px^2, operator precision): work
        arrays of ``ops`` (:meth:`~lsst_bfdrift.templates.swept.OperatorCache.scratch`),
        overwritten by the next call.
    stats : tuple of ndarray or None
        ``(imax, imin, bmax)``, each of shape ``(ceil(ny / cell),
        ceil(nx / cell))``; None without ``cell``.
    """
    ny, nx = img.shape
    strip = ny if strip is None else min(int(strip), ny)
    halo = (ops.template.size + 1) // 2 + 2
    first = np.empty((ny, nx))
    sv = ops.scratch("sv", (ny, nx + 1), ops.dtype) if keep_swept else None
    sh = ops.scratch("sh", (ny + 1, nx), ops.dtype) if keep_swept else None
    if cell is None:
        stats, cs, arrs = None, 1, (np.empty((1, 1)),) * 3
    else:
        cs = int(cell)
        shape = (-(-ny // cs), -(-nx // cs))
        stats = arrs = (np.zeros(shape), np.full(shape, np.inf), np.zeros(shape))
    img_c = np.ascontiguousarray(img, dtype=np.float64)
    for r0 in range(0, ny, strip):
        r1 = min(r0 + strip, ny)
        a, z = max(r0 - halo, 0), min(r1 + halo, ny)
        op = ops((z - a, nx))
        if maps is None:
            bsv, bsh = op(img[a:z])
        else:
            bsv, bsh, more = op(img[a:z], extra=maps.spectra(op))
            maps.add(bsv, bsh, more, a, r0, r1)
        bb = fused_transfer(bsv, bsh, img[a:z], blocked[a:z], cubic=cubic)
        _finish_rows(img_c, bb, a, r0, r1, first, cs, *arrs, stats is not None)
        if keep_swept:
            sv[r0:r1] = bsv[r0 - a:r1 - a]
            top = r1 + 1 if r1 == ny else r1  # the last block also owns the top edge row
            sh[r0:top] = bsh[r0 - a:top - a]
        # bsv, bsh, bb (and the maps' fields) stay alive until the next block
        # has allocated its own: freed first, their memory would go back to
        # the system and be page-faulted in again (docs/benchmarks.rst)
        if stop is not None and r1 < ny and stop(r1, stats, (first, sv, sh)):
            return None
    return first, sv, sh, stats


@numba.njit(parallel=True, cache=True)
def _finish_rows(img, bb, off, r0, r1, first, cell, imax, imin, bmax, do_stats):
    """Rows r0..r1-1: first = I - b/2 (b = ``bb`` shifted by ``off`` rows)
    and, if ``do_stats``, the cell statistics of those rows accumulated into
    ``imax`` (max abs(I)), ``imin`` (min I) and ``bmax`` (max abs(b))."""
    nx = img.shape[1]
    for cy in numba.prange(r0 // cell, (r1 - 1) // cell + 1):
        ja, jb = max(cy * cell, r0), min((cy + 1) * cell, r1)
        if not do_stats:
            for j in range(ja, jb):
                for i in range(nx):
                    first[j, i] = img[j, i] - 0.5 * bb[j - off, i]
            continue
        hi, lo, bm = imax[cy].copy(), imin[cy].copy(), bmax[cy].copy()
        for j in range(ja, jb):  # row by row: the arrays are read as they lie in memory
            for cx in range(hi.size):
                h, w, m = hi[cx], lo[cx], bm[cx]
                for i in range(cx * cell, min((cx + 1) * cell, nx)):
                    v = img[j, i]
                    bv = bb[j - off, i]
                    first[j, i] = v - 0.5 * bv
                    h = max(h, abs(v))
                    w = min(w, v)
                    m = max(m, abs(bv))
                hi[cx], lo[cx], bm[cx] = h, w, m
        imax[cy], imin[cy], bmax[cy] = hi, lo, bm


def active_cells(img, b, kernel_abs_sum, *, noise_tol=None, limit=None, cell=16,
                 safety=20.0):
    """Cells whose first-order transfer needs the higher-order terms.

    Parameters
    ----------
    img, b : ndarray, shape (ny, nx)
        Image and first-order transfer (e).
    kernel_abs_sum : float
        K (px^2 per electron), see the module docstring.
    noise_tol : float, optional
        Tolerance ``noise_tol * sqrt(max(I, 1))`` per pixel (e); else
    limit : float
        one tolerance for every pixel (e).
    cell : int, optional
        Cell size (px).
    safety : float, optional
        Factor of the bound.

    Returns
    -------
    ndarray of bool, shape (ceil(ny / cell), ceil(nx / cell))

    Notes
    -----
    :func:`sparse_series` gathers the same statistics during its first-order
    pass (:func:`first_order_terms` with ``cell``); this is that loop on its
    own, for a given ``b``.
    """
    img = np.ascontiguousarray(img, dtype=np.float64)
    ny, nx = img.shape
    shape = (-(-ny // cell), -(-nx // cell))
    stats = (np.zeros(shape), np.full(shape, np.inf), np.zeros(shape))
    _finish_rows(img, np.ascontiguousarray(b, dtype=np.float64), 0, 0, ny, np.empty((ny, nx)),
                 int(cell), *stats, True)
    return active_from_stats(*stats, kernel_abs_sum, noise_tol=noise_tol, limit=limit,
                             safety=safety)


def active_from_stats(imax, imin, bmax, kernel_abs_sum, *, noise_tol=None, limit=None,
                      safety=20.0):
    """:func:`active_cells` from the cell statistics (max abs(I), min I,
    max abs(b) per cell, as gathered by :func:`first_order_terms`)."""
    if noise_tol is not None:
        lmin = tolerance(imin, noise_tol)
    else:
        lmin = np.full(imax.shape, float(limit))
    imax = ndimage.maximum_filter(imax, size=5, mode="nearest")
    lmin = ndimage.minimum_filter(lmin, size=5, mode="nearest")
    return safety * kernel_abs_sum * imax * bmax > lmin


def tolerance(img, noise_tol):
    """Per-pixel tolerance ``noise_tol * sqrt(max(I, 1))`` (e): the chosen
    fraction of each pixel's Poisson noise."""
    return float(noise_tol) * np.sqrt(np.maximum(img, 1.0))


def window_boxes(active, shape, *, cell=16, dilate=1):
    """Non-overlapping pixel boxes (y0, y1, x0, x1) covering the active cells.

    The active cells are dilated by ``dilate`` cells; the bounding boxes of
    the connected groups are merged until none overlap.
    """
    if not active.any():
        return []
    grown = ndimage.binary_dilation(active, structure=np.ones((3, 3), bool),
                                    iterations=int(dilate)) if dilate > 0 else active
    labels, _ = ndimage.label(grown, structure=np.ones((3, 3), int))
    boxes = [[s[0].start, s[0].stop, s[1].start, s[1].stop]
             for s in ndimage.find_objects(labels)]
    merged = True
    while merged:
        merged = False
        out = []
        for bx in boxes:
            for o in out:
                if bx[0] < o[1] and o[0] < bx[1] and bx[2] < o[3] and o[2] < bx[3]:
                    o[:] = [min(o[0], bx[0]), max(o[1], bx[1]), min(o[2], bx[2]),
                            max(o[3], bx[3])]
                    merged = True
                    break
            else:
                out.append(list(bx))
        boxes = out
    ny, nx = shape
    return [(y0 * cell, min(y1 * cell, ny), x0 * cell, min(x1 * cell, nx))
            for y0, y1, x0, x1 in boxes]


def apriori_ok(x2, x3, limit):
    """True when the neglected fourth-order term is far below ``limit``.

    The series' terms shrink by r = max abs(x3) / max abs(x2) (the brighter-fatter
    strength); the next term is estimated as r times the largest abs(x3) within
    2 pixels, with a safety factor 4.
    """
    m2 = np.abs(x2).max()
    if m2 == 0.0:
        return True
    a3 = np.abs(x3)
    r = a3.max() / m2
    if 4.0 * r * a3.max() <= np.min(limit):
        return True
    return bool(np.all(4.0 * r * ndimage.maximum_filter(a3, size=5, mode="nearest") <= limit))


def _window_terms(ops, boxes, img, blk, first, sv, sh, a3, a4, cubic, *, pad=None):
    """Per window: the terms beyond first order (c/4 + (1/4 - a3) d + x3),
    x2 and x3, in ``boxes`` order; each window zero-padded to the shape
    ``pad(h, w)`` (default: :func:`_nice` of each side)."""
    pad = (lambda h, w: (_nice(h), _nice(w))) if pad is None else pad
    groups = {}
    for k, (y0, y1, x0, x1) in enumerate(boxes):
        groups.setdefault(pad(y1 - y0, x1 - x0), []).append(k)
    extra, x2s, x3s = [None] * len(boxes), [None] * len(boxes), [None] * len(boxes)
    k1 = 0.5 * a3 - 0.125
    w = density_weight(cubic)

    def transfer(sv_, sh_, f, kw, rows):
        # fused_transfer's one-thread kernel called directly: the windows are
        # small, their inputs contiguous and checked once per window
        out = np.empty(f.shape)
        fused_serial(sv_, sh_, f, kw, rows, w, out)
        return out

    for shape, ks in groups.items():
        # windows are zero-padded to a few standard shapes (the convolution
        # of a zero-padded window is the window's own), so that operators
        # and their kernel transforms are shared
        op = ops(shape)
        stack = np.zeros((len(ks),) + shape, op.dtype)
        win = []
        for m, k in enumerate(ks):
            y0, y1, x0, x1 = boxes[k]
            iw = np.ascontiguousarray(img[y0:y1, x0:x1])
            bw = iw - first[y0:y1, x0:x1]
            bw *= 2.0                                                         # b
            stack[m, :y1 - y0, :x1 - x0] = bw
            kw = np.ascontiguousarray(blk[y0:y1, x0:x1])
            win.append((iw, bw, kw, kw.any(axis=1),
                        np.ascontiguousarray(sv[y0:y1, x0:x1 + 1]),
                        np.ascontiguousarray(sh[y0:y1 + 1, x0:x1])))
        svb, shb = op.apply_stack(stack)
        ds = []
        for m, k in enumerate(ks):
            iw, bw, kw, rows, svw, shw = win[m]
            h, wd = iw.shape
            sbv = np.ascontiguousarray(svb[m, :h, :wd + 1])
            sbh = np.ascontiguousarray(shb[m, :h + 1, :wd])
            c = transfer(svw, shw, bw, kw, rows)                              # B(b, I)
            d = transfer(sbv, sbh, iw, kw, rows)                              # B(I, b)
            x2 = c * 0.25 + (0.25 - a3) * d
            x3 = k1 * transfer(sbv, sbh, bw, kw, rows)                        # B(b, b)
            x3 -= 0.5 * transfer(svw, shw, x2, kw, rows)                      # B(x2, I)
            stack[m, :h, :wd] = k1 * c + (a3 - a4 - 0.125) * d                 # y
            ds.append(x2)
            x2s[k], x3s[k] = x2, x3
        del svb, shb
        svy, shy = op.apply_stack(stack)
        for m, k in enumerate(ks):
            iw, bw, kw, rows, svw, shw = win[m]
            h, wd = iw.shape
            x3s[k] += transfer(np.ascontiguousarray(svy[m, :h, :wd + 1]),
                               np.ascontiguousarray(shy[m, :h + 1, :wd]), iw, kw, rows)  # B(I, y)
            extra[k] = ds[m] + x3s[k]
        del svy, shy, stack, ds, win
    return extra, x2s, x3s


def _nice(n):
    """Smallest of 32, 48, 64, 96, 128, 192, ... (2^k or 3 x 2^k) at least n."""
    m = 32
    while m < n:
        m = m * 3 // 2 if (m & (m - 1)) == 0 else m * 4 // 3
    return m


def _dilated_area(active, shape, cell, dilate):
    """Pixels of the active cells dilated by ``dilate`` cells (the part of the
    image the first tier's windows cover at least)."""
    grown = ndimage.binary_dilation(active, structure=np.ones((3, 3), bool),
                                    iterations=int(dilate)) if dilate > 0 else active
    ny, nx = shape
    rows = np.minimum(cell, ny - cell * np.arange(grown.shape[0]))
    cols = np.minimum(cell, nx - cell * np.arange(grown.shape[1]))
    return float(rows @ grown.astype(float) @ cols)


def _padded(n):
    """Window side for the second tier: :func:`_nice` up to 256 px, then the
    next multiple of 128 px (long windows along a flat's border)."""
    return _nice(n) if n <= 256 else -(-n // 128) * 128


def _ring_ok(term, box, shape, lim, fraction):
    """Computed terms 2..5 px inside the window's border (image borders
    excepted) are below ``fraction`` x the tolerance ``lim`` (window)."""
    y0, y1, x0, x1 = box
    h, w = term.shape
    ring = np.zeros((h, w), bool)
    ring[2:h - 2, 2:w - 2] = True
    ring[6:h - 6, 6:w - 6] = False
    # sides on the image border are exact (nothing beyond them): not checked
    if y0 == 0:
        ring[:6] = False
    if y1 == shape[0]:
        ring[h - 6:] = False
    if x0 == 0:
        ring[:, :6] = False
    if x1 == shape[1]:
        ring[:, w - 6:] = False
    return bool(np.all(np.abs(term[ring]) <= fraction * lim[ring]))


def sparse_series(img, blocked, ops, *, noise_tol=RECOMMENDED.noise_tol, rtol=RECOMMENDED.rtol,
                  order=RECOMMENDED.order, density=RECOMMENDED.density,
                  strip=RECOMMENDED.strip, cell=16, dilate=1, safety=20.0, ring_fraction=0.25,
                  max_fraction=0.5, second_tier=True, fraction=0.5, group=6,
                  second_max_fraction=0.75, info=None, maps=None):
    """Third-order inverse series with windowed higher-order terms.

    Parameters
    ----------
    img : ndarray, shape (ny, nx), float64
        Recorded image (e), finite.
    blocked : ndarray of bool
        Pixels that neither give nor receive flux.
    ops : OperatorCache
        Operators of the template.
    noise_tol : float or None, optional
        Tolerance ``noise_tol * sqrt(max(I, 1))`` per pixel (e); None: that of
        ``rtol``. Defaults here and below: the recommended settings
        (:data:`~lsst_bfdrift.correction.settings.RECOMMENDED`).
    rtol : float, optional
        ``rtol * max abs(I)`` for every pixel.
    order : int, optional
        Terms of the forward series.
    density : {'mean2', 'cubic4', 'fv4'}, optional
        Edge flux density.
    strip : int or None, optional
        Rows per block of the first operator application.
    cell, dilate, safety, ring_fraction, max_fraction
        See the module docstring.
    second_tier : bool, optional
        Where the windows would cover more than ``max_fraction`` of the
        image, bound the higher orders cell by cell with the tighter bound of
        :mod:`lsst_bfdrift.correction.tiles` and compute them in windows with
        a halo around the cells where that bound exceeds ``fraction`` x the
        tolerance (``group``: cells per tile side), before giving up for the
        dense solver. Images whose first-tier windows pass are not affected.
    fraction, group
        See :mod:`lsst_bfdrift.correction.tiles`.
    second_max_fraction : float, optional
        Largest area of the second tier's windows (they may overlap), as a
        fraction of the image's; beyond it the dense solver is used.
        Windows over the whole image would cost about two to three
        first-order passes, the dense series about four (on the crowded field
        of ``benchmarks/performance/profile_drift.py``), hence a larger limit than the
        first tier's.
    info : dict, optional
        Filled with ``windows`` (number), ``window_fraction`` (of the image
        area), ``dilate`` (cells used), ``tier`` (1 or 2; 2: the second tier,
        with ``active_fraction``, the fraction of the cells it computes) and
        ``reason`` (why None was returned).
    maps : FirstOrderPass, optional
        Filled by the first-order pass (:func:`first_order_terms`);
        incomplete when that pass stops early.

    Returns
    -------
    ndarray or None
        Corrected image (e), or None when the dense solver must be used.
    """
    info = {} if info is None else info
    cubic = density
    a3 = 1.0 / 6.0 if order >= 3 else 0.0
    a4 = 1.0 / 24.0 if order >= 4 else 0.0
    reach = (ops.template.size + 1) // 2 + 3
    if cell < reach:
        raise InputError(f"cell must be at least {reach} px for this template, got {cell}")
    if not 0.0 < fraction <= 1.0:
        raise InputError(f"fraction must be in (0, 1] (of the tolerance), got {fraction}")
    if int(group) < 1:
        raise InputError(f"group must be at least 1 cell, got {group}")
    scalar = None if noise_tol is not None else rtol * max(np.abs(img).max(), 1e-300)

    def window_limit(y0, y1, x0, x1):
        if scalar is not None:
            return np.full((y1 - y0, x1 - x0), scalar)
        return tolerance(img[y0:y1, x0:x1], noise_tol)

    ny = img.shape[0]

    def active(stats):
        return active_from_stats(*stats, ops.kernel_abs_sum, noise_tol=noise_tol, limit=scalar,
                                 safety=safety)

    consts = bound_constants(ops.template, density) if second_tier else None
    # reach of the swept-area kernels: the transfer at a pixel depends on
    # the charge within R px
    r_k = ops.template.size // 2 + 1
    margins = (min(4, r_k), r_k, 2 * r_k)  # a template under 7 x 7 px reaches < 4 px

    def _tier2_active(stats, arrays, blk, refine=True):
        # cells whose higher orders may exceed fraction x the tolerance (rows
        # of blk: those of the statistics)
        k = blk.shape[0]
        first_, sv_, sh_ = arrays
        lmin = (tolerance(stats[1], noise_tol) if scalar is None
                else np.full(stats[1].shape, scalar))
        lmin = ndimage.minimum_filter(lmin, size=3, mode="nearest")
        bound, p_coef = cell_bound(img[:k], first_[:k], sv_[:k], sh_[:k + 1], stats, blk,
                                   consts, cell=cell, margins=margins, order=order,
                                   threshold=fraction * lmin, refine=refine)
        return bound > fraction * lmin, p_coef, lmin

    checked = []

    def stop(r1, stats, arrays):
        # the windows cover at least the active cells: when the first quarter
        # of the rows shows more than max_fraction of them active (a flat, a
        # crowded field), the dense solver will be needed; stop early (one
        # check, so that the cost stays a quarter of one cell pass)
        rows = r1 // cell
        if checked or rows * cell < ny // 4:
            return False
        checked.append(rows)
        part = tuple(x[:rows] for x in stats)
        if active(part).mean() <= max_fraction:
            return False
        if not second_tier:
            return True
        # the second tier's coarse bound on the cell rows done but the last
        # (the swept areas of its top edges are not all there yet); its
        # windows counted on those rows but the last two (which the bound
        # takes for the image border)
        rows -= 1
        if rows < 4:
            return True
        k = rows * cell
        part = tuple(x[:rows] for x in stats)
        act, p_coef, lmin = _tier2_active(part, arrays, blocked[:k], refine=False)

        def sides(cells_box):
            return window_sides(cells_box, part[2], p_coef, fraction * lmin, order=order)[0]

        wins = halo_windows(act[:rows - 2], (k - 2 * cell, img.shape[1]), cell=cell,
                            group=group, halo=sides)
        area = sum((y1 - y0) * (x1 - x0) for (y0, y1, x0, x1), _ in wins)
        return area > second_max_fraction * (k - 2 * cell) * img.shape[1]

    terms = first_order_terms(img, blocked, ops, strip=strip, cubic=cubic, stop=stop, cell=cell,
                              maps=maps)
    if terms is None:
        info.update(windows=None, window_fraction=None, dilate=dilate, tier=1,
                    reason=f"more than {max_fraction:.0%} of the cells need the higher orders")
        return None
    out, sv, sh, stats = terms
    act = active(stats)
    for grow in range(3):
        # the boxes cover the dilated active cells without overlapping: when
        # those alone exceed max_fraction (a crowded field), so do the boxes
        floor = _dilated_area(act, img.shape, cell, dilate + grow) / img.size
        boxes = (window_boxes(act, img.shape, cell=cell, dilate=dilate + grow)
                 if floor <= max_fraction or not second_tier else None)
        frac = floor if boxes is None else \
            sum((y1 - y0) * (x1 - x0) for y0, y1, x0, x1 in boxes) / img.size
        info.update(windows=None if boxes is None else len(boxes), window_fraction=frac,
                    dilate=dilate + grow, tier=1)
        if frac > max_fraction:
            info["reason"] = f"windows cover {frac:.0%} of the image"
            if second_tier:
                return _second_tier(img, blocked, ops, out, sv, sh, stats, _tier2_active,
                                    window_limit, cell=cell, group=group, order=order,
                                    cubic=cubic, a3=a3, a4=a4, fraction=fraction,
                                    max_fraction=second_max_fraction, info=info)
            return None
        extra, x2s, x3s = _window_terms(ops, boxes, img, blocked, out, sv, sh, a3, a4, cubic)
        lims = [window_limit(*bx) for bx in boxes]
        if all(_ring_ok(e, bx, img.shape, lim, ring_fraction)
               for e, bx, lim in zip(extra, boxes, lims)):
            break
    else:
        info["reason"] = "window borders above the tolerance"
        return None
    for e, x2, x3, lim, (y0, y1, x0, x1) in zip(extra, x2s, x3s, lims, boxes):
        if not apriori_ok(x2, x3, lim):
            info["reason"] = "fourth-order estimate above the tolerance"
            return None
        out[y0:y1, x0:x1] += e
    info["reason"] = None
    return out


def _second_tier(img, blocked, ops, out, sv, sh, stats, tier2_active, window_limit, *, cell,
                 group, order, cubic, a3, a4, fraction, max_fraction, info):
    """The higher orders in windows with a halo around the cells where the
    bound of :mod:`lsst_bfdrift.correction.tiles` exceeds ``fraction`` x the
    tolerance; ``out`` (the first-order image) completed in place, or None
    (``info['reason']``) when the windows would cover more than
    ``max_fraction`` of the image or the fourth-order estimate fails."""
    act, p_coef, lmin = tier2_active(stats, (out, sv, sh), blocked)

    def sides(cells_box):
        return window_sides(cells_box, stats[2], p_coef, fraction * lmin, order=order)[0]

    chosen = halo_windows(act, img.shape, cell=cell, group=group, halo=sides)
    boxes = [box for box, _ in chosen]
    frac = sum((y1 - y0) * (x1 - x0) for y0, y1, x0, x1 in boxes) / img.size
    info.update(tier=2, windows=len(boxes), window_fraction=frac,
                active_fraction=float(act.mean()))
    if frac > max_fraction:
        info["reason"] = (f"second-tier windows cover {frac:.0%} of the image (at most "
                          f"{max_fraction:.0%})")
        return None
    if not boxes:
        info["reason"] = None
        return out
    extra, x2s, x3s = _window_terms(ops, boxes, img, blocked, out, sv, sh, a3, a4, cubic,
                                    pad=lambda h, w: (_padded(h), _padded(w)))
    for k, (y0, y1, x0, x1) in enumerate(boxes):
        if not apriori_ok(x2s[k], x3s[k], window_limit(y0, y1, x0, x1)):
            info["reason"] = "fourth-order estimate above the tolerance"
            return None
    del x2s, x3s
    for (box, keep), e in zip(chosen, extra):
        y0, y1, x0, x1 = box
        view = out[y0:y1, x0:x1]
        view[keep] += e[keep]
    info["reason"] = None
    return out
