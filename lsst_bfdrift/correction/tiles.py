"""Second tier of the windowed series: a per-cell bound on the higher orders
and windows with a halo, for images where the first tier's windows would
cover most of the image (bright flats, crowded fields).

The first tier (:func:`lsst_bfdrift.correction.series.sparse_series`) flags a
cell when ``2 K max abs(I) max abs(b)`` exceeds a tenth of the tolerance and
merges the windows around the flagged cells into non-overlapping boxes. On a
bright flat that bound is loose (a uniform level moves no charge: the
swept areas of a constant image vanish and the transfer of a constant
density is the divergence of the swept areas), so every cell is flagged; on
a crowded field the boxes merge until they cover the image. Either way the
dense series was used, three operator applications over the whole image.

Bound. With the notation of :mod:`lsst_bfdrift.correction.series`
(B(f, Q)(p) = sum over the four edges e of p of +-w_e(f) S_e(Q), w_e the
edge density with stencil weights of absolute sum W = 1 + 4 abs(w_o),
S_e the swept area), for any pixel p of a cell and any constant m:

* abs(S_e(g)) <= K max abs(g) (K: the largest sum of abs(kernel) of one edge);
* sum_e +-S_e(g)(p) = (D * g)(p), D the divergence of the swept-area kernels
  (the area kernel), so abs(sum_e +-S_e(g)) <= A max abs(g), A = sum abs(D);
* w_e(I) = m + w_e(I - m) on edges whose stencil holds no blocked pixel and
  that are not on the image border, hence
  abs(B(I, g)(p)) <= P max abs(g), P = abs(m) A + 4 W K max abs(I - m);
  elsewhere (cells near blocked pixels or the border) P = 4 W K max abs(I);
* abs(B(g, I)(p)) <= 4 W S max abs(g), S the largest abs(S_e(I)) at the
  edges of the pixels concerned (computed by the first-order pass).

With b the first-order transfer, x2 = c/4 + (1/4 - a3) d, c = B(b, I),
d = B(I, b), y = k1 c + k2 d (k1 = a3/2 - 1/8, k2 = a3 - a4 - 1/8) and
x3 = -B(x2, I)/2 + k1 B(b, b) + B(I, y). The transfer at a pixel takes
densities within 2 px and swept areas of charge within R px (R = N // 2 + 1,
11 px for the default template of N = 21), so with the maxima taken within
4, R and 2 R px of the cell (:func:`local_stats`; subscripts 4, R, 2R) or
over its 3 x 3 cells (subscript 3; cells of at least R + 2 px):

    abs(x2) <= (W S_4 beta_4 + abs(1/4 - a3) P_4 beta_R)            in the cell,
    abs(x2) <= X2' = W S_4 beta_4 + abs(1/4 - a3) P_4 beta_3       within 2 px,
    abs(y) <= Y = 4 W abs(k1) S_3 beta_3 + abs(k2) P_3 beta_2R      within R px,
    abs(x3) <= 2 W S_4 X2' + 4 W K abs(k1) beta_4 beta_R + P_4 Y     in the cell,

beta the largest abs(b). The sum of the two bounds in the cell, times 1.05
for the rounding of the single-precision transforms, is the cell's bound
T. On a 1e5 e flat T is 2 to 3 times the largest term actually found
(tests/correction/test_tiles.py); the first tier's bound is 25 to 40 times
it.

A cell is *active* when T > ``fraction`` x the smallest tolerance over its
3 x 3 cells (``fraction`` = 0.5: the terms left out are at most half the
tolerance of the series, ``noise_tol`` x sqrt(I), in every pixel). The
active cells are grouped by tiles of ``group`` x ``group`` cells; per tile
the terms are computed on the bounding box of its active cells grown by a
halo of one cell (zero-padded windows, batched, as in the first tier) and
kept on the active cells only. At least a cell (>= R + 2 px) inside a
window, x2 and the first two parts of x3 see all their sources and are
exact; y, needed within R px of a kept pixel, misses the sources up to R
px beyond the window, so the kept terms differ from the dense series' by
at most abs(k2) P_3^2 beta_o (beta_o: the largest abs(b) in the cells
just beyond the window, :func:`window_sides`). Each side where that exceeds
``fraction`` x the tolerance gets a halo of two cells (>= 2 R + 2 px:
nothing is missed there).
Windows overlap, and each pixel takes the terms of at most one window.

What this gives up: flux conservation of the higher orders. The first
tier's windows are closed (their terms sum to zero); here the terms are
kept on active cells only, so the image's total changes by the terms left
out in the inactive cells, each below ``fraction`` x the tolerance and of
both signs (a few e on a 512 x 512 flat of 1e5 e, 1e-10 of its flux). The
first-order transfer, which carries almost all of the correction,
conserves flux exactly as before.
"""

import numba
import numpy as np
from scipy import ndimage

from lsst_bfdrift.correction._edge_kernels import density_weight
from lsst_bfdrift.templates.swept import swept_area_kernels
from lsst_bfdrift.utils.errors import InputError

__all__ = ["bound_constants", "local_stats", "coarse_stats", "LOCAL_STATS",
           "higher_order_bound", "cell_bound", "halo_windows", "window_sides",
           "ROUNDING_MARGIN"]

#: Factor on the bound for the rounding of the single-precision transforms
#: (relative accuracy ~1e-6 of the swept areas) and of the float64 sums.
ROUNDING_MARGIN = 1.05


def bound_constants(template, density):
    """K, A, W and S0 of the bound (module docstring, :func:`coarse_stats`).

    Parameters
    ----------
    template : DistortionTemplate
        Green's function.
    density : {'mean2', 'cubic4', 'fv4'}
        Edge flux density.

    Returns
    -------
    dict
        ``K`` (largest sum of abs(swept-area kernel) over one edge, px^2 per
        e), ``A`` (sum of abs of the area kernel, the divergence of the
        swept-area kernels, px^2 per e), ``W`` (absolute sum of the
        density stencil's weights) and ``S0`` (largest abs(sum of a
        swept-area kernel): the swept area per e of a uniform level, 0 to
        rounding for the bundled template).
    """
    kv, kh = swept_area_kernels(template)
    q = 1.0 / template.charge
    kv, kh = kv * q, kh * q
    # sum over the edges of one pixel of +-S_e: right minus left vertical
    # edges, top minus bottom horizontal edges (the charge at a fixed
    # offset contributes kv[., u + 1] - kv[., u] and kh[v + 1, .] - kh[v, .],
    # the kernels being zero beyond their ends)
    n = kh.shape[1]
    dv = np.diff(np.pad(kv, ((0, 0), (1, 1))), axis=1)   # (n, n + 2)
    dh = np.diff(np.pad(kh, ((1, 1), (0, 0))), axis=0)   # (n + 2, n)
    area = np.zeros((n + 2, n + 2))
    area[1:-1, :] += dv
    area[:, 1:-1] += dh
    return dict(K=float(max(np.abs(kv).sum(), np.abs(kh).sum())),
                A=float(np.abs(area).sum()), W=1.0 + 4.0 * abs(density_weight(density)),
                S0=float(max(abs(kv.sum()), abs(kh.sum()))))


@numba.njit(parallel=True, cache=True)
def _local_cells(img, first, sv, sh, cell, m0, m1, m2, cy, cx, out):
    ny, nx = img.shape
    for n in numba.prange(cy.size):
        top, left = cy[n] * cell, cx[n] * cell
        bot, right = min(top + cell, ny), min(left + cell, nx)
        h, w, t, x0, x1, x2 = -np.inf, np.inf, 0.0, 0.0, 0.0, 0.0
        for j in range(max(top - m2, 0), min(bot + m2, ny)):
            dj = max(top - j, j - bot + 1, 0)
            for i in range(max(left - m2, 0), min(right + m2, nx)):
                d = max(dj, left - i, i - right + 1)
                bv = 2.0 * abs(img[j, i] - first[j, i])
                x2 = max(x2, bv)
                if d <= m1:
                    x1 = max(x1, bv)
                if d <= m0:
                    v = img[j, i]
                    h = max(h, abs(v))
                    w = min(w, v)
                    x0 = max(x0, bv)
                    t = max(t, abs(sv[j, i]), abs(sv[j, i + 1]), abs(sh[j, i]),
                            abs(sh[j + 1, i]))
        out[0, n], out[1, n], out[2, n] = h, w, t
        out[3, n], out[4, n], out[5, n] = x0, x1, x2


@numba.njit(parallel=True, cache=True)
def _block_stats(img, first, sv, sh, q, hi, lo, sm, bm):
    """Per block of q x q pixels: max abs(I), min I, max abs(swept area) over
    the pixels' edges, max abs(b)."""
    ny, nx = img.shape
    for by in numba.prange(hi.shape[0]):
        for bx in range(hi.shape[1]):
            h, w, t, x = -np.inf, np.inf, 0.0, 0.0
            for j in range(by * q, min((by + 1) * q, ny)):
                for i in range(bx * q, min((bx + 1) * q, nx)):
                    v = img[j, i]
                    h = max(h, abs(v))
                    w = min(w, v)
                    x = max(x, 2.0 * abs(v - first[j, i]))
                    t = max(t, abs(sv[j, i]), abs(sv[j, i + 1]), abs(sh[j, i]),
                            abs(sh[j + 1, i]))
            hi[by, bx], lo[by, bx], sm[by, bx], bm[by, bx] = h, w, t, x


@numba.njit(parallel=True, cache=True)
def _cells_from_blocks(hi, lo, sm, bm, cb, m0, m1, m2, cy, cx, out):
    """Statistics of the listed cells (``cb`` blocks a side) grown by m0, m1,
    m2 blocks, from the block statistics of :func:`_block_stats`."""
    nby, nbx = hi.shape
    for n in numba.prange(cy.size):
        top, left = cy[n] * cb, cx[n] * cb
        bot, right = min(top + cb, nby), min(left + cb, nbx)
        h, w, t, x0, x1, x2 = -np.inf, np.inf, 0.0, 0.0, 0.0, 0.0
        for j in range(max(top - m2, 0), min(bot + m2, nby)):
            dj = max(top - j, j - bot + 1, 0)
            for i in range(max(left - m2, 0), min(right + m2, nbx)):
                d = max(dj, left - i, i - right + 1)
                x = bm[j, i]
                x2 = max(x2, x)
                if d <= m1:
                    x1 = max(x1, x)
                if d <= m0:
                    h = max(h, hi[j, i])
                    w = min(w, lo[j, i])
                    t = max(t, sm[j, i])
                    x0 = max(x0, x)
        out[0, n], out[1, n], out[2, n] = h, w, t
        out[3, n], out[4, n], out[5, n] = x0, x1, x2


#: Names of the statistics of :func:`local_stats`, in the order of its arrays.
LOCAL_STATS = ("imax", "imin", "smax", "b0", "b1", "b2")


def local_stats(img, first, sv, sh, *, cell, margins=(4, 11, 22), cells=None):
    """Statistics of each cell grown by a few pixels on every side (clipped to
    the image).

    Parameters
    ----------
    img, first : ndarray, shape (ny, nx), float64
        Image and first-order corrected image (e).
    sv : ndarray, shape (ny, nx + 1)
    sh : ndarray, shape (ny + 1, nx)
        Swept areas of the image (px^2).
    cell : int
        Cell size (px).
    margins : tuple of int, optional
        m0 <= m1 <= m2 (px).
    cells : ndarray of bool, optional
        Only these cells (the others are NaN); default all. Beyond a tenth
        of the cells the statistics are gathered by blocks of 4 x 4 pixels
        first (one pass over the image), with the margins rounded up to
        multiples of 4 px (at least the values with the margins as given).

    Returns
    -------
    dict of ndarray
        Each of shape (ceil(ny / cell), ceil(nx / cell)): ``imax`` (max
        abs(I)), ``imin`` (min I), ``smax`` (largest abs(swept area of I)
        over the edges of the pixels) and ``b0`` (max abs(b), b = 2 (I -
        first)) within m0 px of the cell, ``b1`` and ``b2``: max abs(b) within
        m1 and m2 px.
    """
    m0, m1, m2 = (int(v) for v in margins)
    if not 0 <= m0 <= m1 <= m2:
        raise InputError(f"margins must be increasing and non-negative, got {margins}")
    ny, nx = img.shape
    shape = (-(-ny // cell), -(-nx // cell))
    if cells is None:
        cells = np.ones(shape, bool)
    cy, cx = np.nonzero(cells)
    vals = np.empty((len(LOCAL_STATS), cy.size))
    img = np.ascontiguousarray(img, dtype=np.float64)
    first = np.ascontiguousarray(first, dtype=np.float64)
    q = 4
    if cy.size > 0.1 * cells.size and cell % q == 0:
        nb = (-(-ny // q), -(-nx // q))
        blocks = tuple(np.empty(nb) for _ in range(4))
        _block_stats(img, first, sv, sh, q, *blocks)
        _cells_from_blocks(*blocks, int(cell) // q, -(-m0 // q), -(-m1 // q), -(-m2 // q),
                           cy, cx, vals)
    else:
        _local_cells(img, first, sv, sh, int(cell), m0, m1, m2, cy, cx, vals)
    out = {}
    for k, name in enumerate(LOCAL_STATS):
        out[name] = np.full(shape, np.nan)
        out[name][cy, cx] = vals[k]
    return out


def coarse_stats(stats, consts):
    """The statistics of :func:`local_stats` with margins of at most one cell
    (two for ``b2``) from the cell statistics: each at least the local one,
    so that :func:`higher_order_bound` of these bounds that of the local ones.

    Parameters
    ----------
    stats : tuple of ndarray
        Per cell: max abs(I), min I, max abs(b).
    consts : dict
        :func:`bound_constants`.

    Returns
    -------
    dict of ndarray

    Notes
    -----
    The swept areas are bounded without reading them: where the kernels'
    reach (R px) stays inside the image, abs(S_e(I)) <= S0 abs(m) + K
    max abs(I - m) within R px (m the midrange of I over the 3 x 3 cells),
    elsewhere K max abs(I); plus 1e-6 K max abs(I) over the image for the
    rounding of the single-precision transforms.
    """
    imax, imin, bmax = stats
    near = dict(size=3, mode="nearest")
    b3 = ndimage.maximum_filter(bmax, **near)
    hi = ndimage.maximum_filter(imax, **near)
    lo = ndimage.minimum_filter(imin, **near)
    K = consts["K"]
    smax = consts["S0"] * np.abs(0.5 * (hi + lo)) + K * 0.5 * (hi - lo)
    edge = np.zeros(imax.shape, bool)
    edge[:2], edge[-2:], edge[:, :2], edge[:, -2:] = True, True, True, True
    smax[edge] = (K * hi)[edge]
    smax += 1e-6 * K * float(imax.max())
    return dict(imax=hi, imin=lo, smax=ndimage.maximum_filter(smax, **near), b0=b3, b1=b3,
                b2=ndimage.maximum_filter(bmax, size=5, mode="nearest"))


def _exposed_cells(blocked, cell):
    """Cells where the edge densities of a constant are not all that constant:
    with an edge on the image border, or within 8 px of a blocked pixel (the
    pixels within 4 px of the cell and their stencils)."""
    ny, nx = blocked.shape
    my, mx = -(-ny // cell), -(-nx // cell)
    rows = np.flatnonzero(blocked.any(axis=1))
    near = np.zeros((my, mx), bool)
    if rows.size:
        j, i = np.nonzero(blocked[rows])
        near[rows[j] // cell, i // cell] = True
        near = ndimage.binary_dilation(near, structure=np.ones((3, 3), bool))
    near[0], near[-1], near[:, 0], near[:, -1] = True, True, True, True
    return near


def higher_order_bound(stats, local, blocked, consts, *, cell, order=3, exposed=None):
    """Bound on abs(x2 + x3) in every pixel of each cell (module docstring), e.

    Parameters
    ----------
    stats : tuple of ndarray
        Per cell: max abs(I), min I, max abs(b) (as gathered by
        :func:`~lsst_bfdrift.correction.series.first_order_terms`).
    local : dict of ndarray
        :func:`local_stats` with margins (4, R, 2 R), R the reach of the
        swept-area kernels (11 px for the default template).
    blocked : ndarray of bool, shape (ny, nx)
        Pixels that neither give nor receive flux.
    consts : dict
        :func:`bound_constants`.
    cell : int
        Cell size (px), at least R + 2.
    order : int, optional
        Terms of the forward series.
    exposed : ndarray of bool, optional
        Cells near blocked pixels or the image border, if already known
        (from ``blocked``).

    Returns
    -------
    bound : ndarray
        Per cell (e).
    p_wide : ndarray
        P per cell over its 3 x 3 cells (the factor of the bound on
        abs(B(I, g)) per max abs(g), :func:`window_sides`).
    """
    K, A, W = consts["K"], consts["A"], consts["W"]
    a3 = 1.0 / 6.0 if order >= 3 else 0.0
    a4 = 1.0 / 24.0 if order >= 4 else 0.0
    k1, k2 = 0.5 * a3 - 0.125, a3 - a4 - 0.125
    imax, imin, bmax = stats
    near = dict(size=3, mode="nearest")
    if exposed is None:
        exposed = _exposed_cells(blocked, cell)

    def p_of(hi, lo, exposed):
        # I lies in [lo, hi] (hi is max abs(I) >= max I): m = midrange
        p = np.abs(0.5 * (hi + lo)) * A + 4.0 * W * K * 0.5 * (hi - lo)
        p[exposed] = (4.0 * W * K * hi)[exposed]
        return p

    # within 4 px of the cell (the pixels within 2 px and their stencils)
    pn = p_of(local["imax"], local["imin"], exposed)
    sn, b0 = local["smax"], local["b0"]
    # within a cell of it (pixels within the kernels' reach and their stencils)
    p3 = p_of(ndimage.maximum_filter(imax, **near), ndimage.minimum_filter(imin, **near),
              ndimage.binary_dilation(exposed, structure=np.ones((3, 3), bool)))
    s3 = ndimage.maximum_filter(sn, **near)
    beta3 = ndimage.maximum_filter(bmax, **near)
    # x2 in the cell: c from b within 2 px, d from b within the reach R
    x2 = W * sn * b0 + abs(0.25 - a3) * pn * local["b1"]
    # x2 within 2 px of the cell (for B(x2, I)): b within R + 2
    x2_near = W * sn * b0 + abs(0.25 - a3) * pn * beta3
    # y within R of the cell: c from b within R + 2, d from b within 2 R
    y = 4.0 * W * abs(k1) * s3 * beta3 + abs(k2) * p3 * local["b2"]
    x3 = 2.0 * W * sn * x2_near + 4.0 * W * K * abs(k1) * b0 * local["b1"] + pn * y
    return ROUNDING_MARGIN * (x2 + x3), p3


def cell_bound(img, first, sv, sh, stats, blocked, consts, *, cell, margins, threshold,
               order=3, refine=True):
    """:func:`higher_order_bound` from the cell statistics, refined with
    :func:`local_stats` in the cells where it exceeds ``threshold``.

    Parameters
    ----------
    img, first, sv, sh
        As for :func:`local_stats`.
    stats : tuple of ndarray
        Per cell: max abs(I), min I, max abs(b).
    blocked : ndarray of bool
        Pixels that neither give nor receive flux.
    consts : dict
        :func:`bound_constants`.
    cell : int
        Cell size (px).
    margins : tuple of int
        (4, R, 2 R), R the reach of the swept-area kernels (px).
    threshold : ndarray
        Per cell (e).
    order : int, optional
        Terms of the forward series.
    refine : bool, optional
        False: the coarse bound alone (an estimate of the windows to come).

    Returns
    -------
    bound, p_wide : ndarray
        As for :func:`higher_order_bound`.

    Notes
    -----
    Each coarse statistic (:func:`coarse_stats`, from the cell statistics
    alone) is at least the local one and the bound grows with each, so the
    coarse bound bounds the refined one: only the cells it flags need the
    local statistics (the border of a flat, the surroundings of bright
    stars), which read the image, b and the swept areas around them again.
    """
    coarse = coarse_stats(stats, consts)
    exposed = _exposed_cells(blocked, cell)
    bound, p_wide = higher_order_bound(stats, coarse, blocked, consts, cell=cell, order=order,
                                       exposed=exposed)
    flagged = bound > threshold
    if refine and flagged.any():
        local = local_stats(img, first, sv, sh, cell=cell, margins=margins, cells=flagged)
        for name in LOCAL_STATS:
            local[name] = np.where(flagged, local[name], coarse[name])
        fine = higher_order_bound(stats, local, blocked, consts, cell=cell, order=order,
                                  exposed=exposed)[0]
        bound = np.where(flagged, np.minimum(fine, bound), bound)
    return bound, p_wide


def halo_windows(active, shape, *, cell, group=6, halo=1):
    """Windows for the active cells: per tile of ``group`` x ``group`` cells,
    the bounding box of its active cells grown by a halo.

    Parameters
    ----------
    active : ndarray of bool
        Per cell.
    shape : tuple of int
        Image shape (ny, nx).
    cell, group : int
        Cell size (px), tile size (cells).
    halo : int or callable
        Halo (cells), or a function of the kept cells' bounding box
        (cy0, cy1, cx0, cx1) (cells) giving the halos of its four sides
        (top, bottom, left, right), e.g. :func:`window_sides`.

    Returns
    -------
    list of tuple
        ``(box, keep)`` with ``box`` = (y0, y1, x0, x1) in pixels (clipped
        to the image) and ``keep`` the boolean mask of the window's pixels
        that take its terms (the tile's active cells). Every active cell is
        kept by exactly one window. Windows whose common bounding box is no
        larger than the two together are merged (their kept cells keep at
        least their halos).
    """
    ny, nx = shape
    my, mx = active.shape
    out = []
    for ty in range(0, my, group):
        for tx in range(0, mx, group):
            sub = active[ty:ty + group, tx:tx + group]
            if not sub.any():
                continue
            rows, cols = np.flatnonzero(sub.any(axis=1)), np.flatnonzero(sub.any(axis=0))
            cy0, cy1 = ty + rows[0], ty + rows[-1] + 1
            cx0, cx1 = tx + cols[0], tx + cols[-1] + 1
            ht, hb, hl, hr = halo((cy0, cy1, cx0, cx1)) if callable(halo) else (halo,) * 4
            wy0, wy1 = max(cy0 - ht, 0), min(cy1 + hb, my)
            wx0, wx1 = max(cx0 - hl, 0), min(cx1 + hr, mx)
            out.append([wy0, wy1, wx0, wx1, [(cy0, cy1, cx0, cx1)], ty // group, tx // group])
    out = _merged(out)
    wins = []
    for wy0, wy1, wx0, wx1, kept in out:
        keep_cells = np.zeros((wy1 - wy0, wx1 - wx0), bool)
        for cy0, cy1, cx0, cx1 in kept:
            keep_cells[cy0 - wy0:cy1 - wy0, cx0 - wx0:cx1 - wx0] = active[cy0:cy1, cx0:cx1]
        box = (wy0 * cell, min(wy1 * cell, ny), wx0 * cell, min(wx1 * cell, nx))
        keep = np.kron(keep_cells, np.ones((cell, cell), bool))
        wins.append((box, keep[:box[1] - box[0], :box[3] - box[2]]))
    return wins


def _merged(wins):
    """Windows of neighbouring tiles merged while the bounding box of the two
    is no larger than they are together (a band along the image border
    becomes one long window): first along each row of tiles, then along each
    column of tiles for the windows still of one tile. Each merged window
    keeps its tiles' cells and contains their windows.

    ``wins``: [wy0, wy1, wx0, wx1, kept boxes, tile row, tile column].
    """
    def area(w):
        return (w[1] - w[0]) * (w[3] - w[2])

    def join(a, b):
        box = [min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3])]
        if (box[1] - box[0]) * (box[3] - box[2]) > area(a) + area(b):
            return None
        return box + [a[4] + b[4]]

    def sweep(items, line, pos):
        # runs of windows in consecutive tiles of one line, merged left to right
        out = []  # (window, line, position of its last tile, first tile's (row, col))
        for w in sorted(items, key=lambda w: (w[line], w[pos])):
            if out and out[-1][1] == w[line] and w[pos] - out[-1][2] == 1:
                m = join(out[-1][0], w)
                if m is not None:
                    out[-1] = (m, w[line], w[pos], out[-1][3])
                    continue
            out.append((w[:5], w[line], w[pos], (w[5], w[6])))
        return out

    rows = sweep(wins, 5, 6)
    multi = [w for w, _, _, _ in rows if len(w[4]) > 1]
    single = [w + list(t) for w, _, _, t in rows if len(w[4]) == 1]
    return multi + [w for w, _, _, _ in sweep(single, 6, 5)]


def window_sides(cells_box, bmax, p_coef, limit, *, order=3):
    """Halo of each side of a window (1 or 2 cells) and the bound on its kept
    terms' difference from the dense series' (module docstring).

    Parameters
    ----------
    cells_box : tuple of int
        (cy0, cy1, cx0, cx1): bounding box of the kept cells (cells).
    bmax, p_coef : ndarray
        Per cell: max abs(b) and P over the 3 x 3 cells
        (:func:`higher_order_bound`).
    limit : ndarray or float
        Largest difference allowed (e), per cell (the smallest over the kept
        cells' box is used) or one value; ``np.inf``: every side gets one
        cell.
    order : int, optional
        Terms of the forward series.

    Returns
    -------
    halos : tuple of int
        (top, bottom, left, right), cells.
    bound : float
        abs(k2) P^2 beta_o (e), P the largest over the window with a halo of
        one cell and beta_o the largest abs(b) in the cells just outside the
        sides that keep one cell: beyond a one-cell halo y misses sources
        within R px; beyond two cells (>= 2 R + 2 px) nothing is missed.
    """
    a3 = 1.0 / 6.0 if order >= 3 else 0.0
    a4 = 1.0 / 24.0 if order >= 4 else 0.0
    cy0, cy1, cx0, cx1 = cells_box
    my, mx = bmax.shape
    wy0, wy1, wx0, wx1 = max(cy0 - 1, 0), min(cy1 + 1, my), max(cx0 - 1, 0), min(cx1 + 1, mx)
    if np.ndim(limit):
        limit = float(np.min(limit[cy0:cy1, cx0:cx1]))
    coef = ROUNDING_MARGIN * abs(a3 - a4 - 0.125) * float(p_coef[wy0:wy1, wx0:wx1].max()) ** 2
    ya, yb, xa, xb = max(wy0 - 1, 0), min(wy1 + 1, my), max(wx0 - 1, 0), min(wx1 + 1, mx)
    rings = (bmax[ya:wy0, xa:xb], bmax[wy1:yb, xa:xb], bmax[ya:yb, xa:wx0],
             bmax[ya:yb, wx1:xb])  # top, bottom, left, right: beyond the image, empty
    halos, bound = [], 0.0
    for ring in rings:
        err = coef * float(ring.max()) if ring.size else 0.0
        if err > limit:
            halos.append(2)
        else:
            halos.append(1)
            bound = max(bound, err)
    return tuple(halos), bound
