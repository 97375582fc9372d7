"""GalSim's boundary layout and photon-assignment rule (option of the star simulation).

galsim.SiliconSensor (GalSim >= 2.4) does not keep one shared position per
pixel corner. Every pixel edge is a polyline of its own, with its two end
corners, taken from the sensor file's pixel nearest the aggressor (left
edges from pixels with i <= c, right edges from i >= c, bottom edges from
j <= c, top edges from j >= c). A pixel's polygon is its four edge polylines
in turn (4 n + 8 vertices), so the four copies of a corner differ slightly
and pixels leave small gaps or overlaps there. A conversion is tested in its
nominal pixel first, then in the eight neighbours in an order that starts
with the nearest side; one found in no pixel goes, with equal probability,
to the nominal pixel or to the first neighbour tried. A conversion whose
nominal pixel is off the stamp is lost. (GalSim also drops a conversion
that misses an edge pixel of the stamp on the outer side; that rule is not
reproduced, it only matters at stamp edges.) As in GalSim, the stamp's
rightmost column boundary and topmost row boundary never move.

This module re-implements that layout and rule (written from the
behaviour described above, which we read in GalSim's BSD-licensed source;
no code copied) so that the two simulators can be compared photon for
photon. The package's own default is the shared, tiling layout of
:mod:`lsst_bfdrift.simulation._star_kernels`.

Layouts (pixel (i, j) centred on (i, j), absolute positions, pixel units):
``V`` (ny, nx + 1, n + 2, 2): vertical edge polylines, bottom to top;
``H`` (ny + 1, nx, n + 2, 2): horizontal edge polylines, left to right.
"""

import numba
import numpy as np

from lsst_bfdrift.physics.polygons import inside_polygon
from lsst_bfdrift.utils.errors import InputError

__all__ = ["galsim_edge_templates", "nominal_edges", "edge_boxes", "galsim_boxes",
           "add_templates_galsim", "accumulate_galsim", "locate_galsim", "layout_areas",
           "collect_batch", "add_shifted"]

# GalSim's neighbour offsets, indexed 0 (nominal) and 1..8 around the pixel
_XOFF = np.array([0, 1, 1, 0, -1, -1, -1, 0, 1], dtype=np.int64)
_YOFF = np.array([0, 0, 1, 1, 1, 0, -1, -1, -1], dtype=np.int64)

#: Margin (px) by which the inner boxes of both layouts are shrunk: far above
#: the rounding of the crossing test (~1e-15 px), far below any physical distance.
BOX_MARGIN = 1e-9


def galsim_edge_templates(template, *, qdist=None):
    """Per-edge polylines of a template's per-pixel table, by GalSim's rule.

    Parameters
    ----------
    template : DistortionTemplate
        Normally from :func:`~lsst_bfdrift.templates.galsim_io.import_galsim_sensor` (its per-pixel
        table keeps the file's vertices).
    qdist : int, optional
        GalSim's ``qdist`` (its default is 3): an aggressor moves only the
        vertical edges within columns -qdist..qdist+1 and rows -qdist..qdist
        of it (boundary index relative to the aggressor's left/bottom edge),
        and the horizontal edges within columns -qdist..qdist and rows
        -qdist..qdist+1. None keeps the whole template.

    Returns
    -------
    tv : ndarray, shape (N, N + 1, n + 2, 2)
        Displacements (dx, dy) of vertical edge polylines (bottom to top).
    th : ndarray, shape (N + 1, N, n + 2, 2)
        Displacements of horizontal edge polylines (left to right).
    """
    tab = template.to_table()
    n, c, ns = template.size, template.center, template.edge_samples
    rows = {(int(r["di"]), int(r["dj"]), str(r["edge"]).strip()): r for r in tab}
    tv = np.zeros((n, n + 1, ns + 2, 2))
    th = np.zeros((n + 1, n, ns + 2, 2))

    def line(r, vertical):
        d = np.zeros((ns + 2, 2))
        d[0] = r["c0x"], r["c0y"]
        d[-1] = r["c1x"], r["c1y"]
        if vertical:
            d[1:-1, 0], d[1:-1, 1] = r["normal"], r["tangent"]
        else:
            d[1:-1, 0], d[1:-1, 1] = r["tangent"], r["normal"]
        return d

    for J in range(n):
        for I in range(n + 1):
            # boundary I lies between pixels I - 1 and I (template indices)
            if I <= c:
                tv[J, I] = line(rows[(I - c, J - c, "left")], True)
            else:
                tv[J, I] = line(rows[(I - 1 - c, J - c, "right")], True)
    for J in range(n + 1):
        for I in range(n):
            if J <= c:
                th[J, I] = line(rows[(I - c, J - c, "bottom")], False)
            else:
                th[J, I] = line(rows[(I - c, J - 1 - c, "top")], False)
    if qdist is not None:
        q = int(qdist)
        if q < 0:
            raise InputError(f"qdist must be >= 0, got {qdist!r}")
        keep_v = np.zeros(tv.shape[:2], bool)
        keep_v[max(c - q, 0):c + q + 1, max(c - q, 0):c + q + 2] = True
        keep_h = np.zeros(th.shape[:2], bool)
        keep_h[max(c - q, 0):c + q + 2, max(c - q, 0):c + q + 1] = True
        tv[~keep_v] = 0.0
        th[~keep_h] = 0.0
    return tv, th


def nominal_edges(ny, nx, fractions):
    """Undistorted edge polylines (absolute positions) of an ny x nx stamp."""
    f = np.concatenate([[0.0], np.asarray(fractions, float), [1.0]])
    v = np.zeros((ny, nx + 1, f.size, 2))
    v[..., 0] = (np.arange(nx + 1) - 0.5)[None, :, None]
    v[..., 1] = (np.arange(ny) - 0.5)[:, None, None] + f[None, None, :]
    h = np.zeros((ny + 1, nx, f.size, 2))
    h[..., 0] = (np.arange(nx) - 0.5)[None, :, None] + f[None, None, :]
    h[..., 1] = (np.arange(ny + 1) - 0.5)[:, None, None]
    return v, h


@numba.njit(cache=True)
def _build(J, I, V, H, xs, ys):
    """Vertices of pixel (I, J): left (up), top (right), right (down), bottom (left)."""
    m = V.shape[2]
    k = 0
    for a in range(m):
        xs[k] = V[J, I, a, 0]
        ys[k] = V[J, I, a, 1]
        k += 1
    for a in range(m):
        xs[k] = H[J + 1, I, a, 0]
        ys[k] = H[J + 1, I, a, 1]
        k += 1
    for a in range(m - 1, -1, -1):
        xs[k] = V[J, I + 1, a, 0]
        ys[k] = V[J, I + 1, a, 1]
        k += 1
    for a in range(m - 1, -1, -1):
        xs[k] = H[J, I, a, 0]
        ys[k] = H[J, I, a, 1]
        k += 1


@numba.njit(cache=True)
def layout_areas(V, H):
    """Shoelace areas (px^2) of every pixel polygon of the layout."""
    ny = V.shape[0]
    nx = H.shape[1]
    nv = 4 * V.shape[2]
    xs = np.empty(nv)
    ys = np.empty(nv)
    out = np.empty((ny, nx))
    for j in range(ny):
        for i in range(nx):
            _build(j, i, V, H, xs, ys)
            a = 0.0
            for k in range(nv):
                b = k + 1 if k + 1 < nv else 0
                a += (xs[k] - i) * (ys[b] - j) - (xs[b] - i) * (ys[k] - j)
            out[j, i] = abs(0.5 * a)
    return out


@numba.njit(cache=True)
def edge_boxes(V, H, j0, j1, i0, i1, box):
    """Inner boxes of pixels j0 <= j < j1, i0 <= i < i1 (every corner copy is
    counted on both sides it touches, so the box lies inside the polygon)."""
    m = V.shape[2]
    for j in range(j0, j1):
        for i in range(i0, i1):
            xl = max(H[j, i, 0, 0], H[j + 1, i, 0, 0])
            xr = min(H[j, i, m - 1, 0], H[j + 1, i, m - 1, 0])
            yb = max(V[j, i, 0, 1], V[j, i + 1, 0, 1])
            yt = min(V[j, i, m - 1, 1], V[j, i + 1, m - 1, 1])
            for a in range(m):
                xl = max(xl, V[j, i, a, 0])
                xr = min(xr, V[j, i + 1, a, 0])
                yb = max(yb, H[j, i, a, 1])
                yt = min(yt, H[j + 1, i, a, 1])
            box[j, i, 0] = xl + BOX_MARGIN
            box[j, i, 1] = xr - BOX_MARGIN
            box[j, i, 2] = yb + BOX_MARGIN
            box[j, i, 3] = yt - BOX_MARGIN


@numba.njit(cache=True)
def galsim_boxes(V, H, j0, j1, i0, i1, box):
    """GalSim's own "trivially inside" boxes: start from the bounding box of
    all vertices; every vertex within 45 degrees of the +x (-x, +y, -y)
    direction seen from the bounding box's centre caps the right (left, top,
    bottom) side. Unlike :func:`edge_boxes` this box is not guaranteed to lie
    inside the polygon: a point in it is accepted without the polygon test."""
    m = V.shape[2]
    nv = 4 * m
    xs = np.empty(nv)
    ys = np.empty(nv)
    for j in range(j0, j1):
        for i in range(i0, i1):
            _build(j, i, V, H, xs, ys)
            x0 = xs.min()
            x1 = xs.max()
            y0 = ys.min()
            y1 = ys.max()
            cx = 0.5 * (x0 + x1)
            cy = 0.5 * (y0 + y1)
            lo_x, hi_x, lo_y, hi_y = x0, x1, y0, y1
            for a in range(nv):
                dx = xs[a] - cx
                dy = ys[a] - cy
                if dx >= abs(dy) and xs[a] < hi_x:
                    hi_x = xs[a]
                if dx <= -abs(dy) and xs[a] > lo_x:
                    lo_x = xs[a]
                if dy >= abs(dx) and ys[a] < hi_y:
                    hi_y = ys[a]
                if dy <= -abs(dx) and ys[a] > lo_y:
                    lo_y = ys[a]
            box[j, i, 0] = lo_x
            box[j, i, 1] = hi_x
            box[j, i, 2] = lo_y
            box[j, i, 3] = hi_y


@numba.njit(cache=True)
def _inside(px, py, J, I, V, H, box, xs, ys):
    ny = V.shape[0]
    nx = H.shape[1]
    if I < 0 or I >= nx or J < 0 or J >= ny:
        return False
    if (box[J, I, 0] <= px <= box[J, I, 1]) and (box[J, I, 2] <= py <= box[J, I, 3]):
        return True
    _build(J, I, V, H, xs, ys)
    return inside_polygon(px, py, xs, ys)


@numba.njit(cache=True)
def _locate_one(px, py, u, V, H, box, xs, ys):
    """GalSim's rule: nominal pixel, then neighbours from the nearest side;
    not found: nominal or first neighbour with equal probability (u uniform)."""
    ix = int(np.floor(px + 0.5))
    iy = int(np.floor(py + 0.5))
    if ix < 0 or ix >= H.shape[1] or iy < 0 or iy >= V.shape[0]:
        return -1, -1  # GalSim drops photons whose nominal pixel is off the image
    if _inside(px, py, iy, ix, V, H, box, xs, ys):
        return ix, iy
    x = px - ix + 0.5
    y = py - iy + 0.5
    if x > y and x > 1.0 - y:
        step = 1
    elif x < y and x < 1.0 - y:
        step = 7
    elif x < y and x > 1.0 - y:
        step = 3
    else:
        step = 5
    n = step
    for _ in range(8):
        jx = ix + _XOFF[n]
        jy = iy + _YOFF[n]
        if _inside(px, py, jy, jx, V, H, box, xs, ys):
            return jx, jy
        n = ((n - 1) + step) % 8 + 1
    n = 0 if u > 0.5 else step
    return ix + _XOFF[n], iy + _YOFF[n]


@numba.njit(cache=True)
def locate_galsim(px, py, u, V, H, box, oi, oj):
    """Pixel of each point by GalSim's rule (may lie outside the stamp)."""
    nv = 4 * V.shape[2]
    xs = np.empty(nv)
    ys = np.empty(nv)
    for p in range(px.shape[0]):
        oi[p], oj[p] = _locate_one(px[p], py[p], u[p], V, H, box, xs, ys)


@numba.njit(cache=True)
def add_shifted(a, k, q, j0, i0, jmax, imax):
    """Add ``q`` times the kernel ``k`` placed with its element (0, 0) on
    element (j0, i0) of ``a``, where it overlaps the rows 0 <= j < ``jmax``
    and the columns 0 <= i < ``imax`` (at most those of ``a``).

    ``a`` (rows, columns, m) is a boundary array of a stamp and ``k`` (rows,
    columns, m) a template's displacements of it, per e, with the same last
    axis (samples along an edge and their components, flattened). The one
    superposition step of both layouts: :func:`add_templates_galsim` here,
    ``add_templates`` and ``accumulate`` of
    :mod:`lsst_bfdrift.simulation._star_kernels` (the shared layout).
    """
    for jt in range(k.shape[0]):
        js = jt + j0
        if js < 0 or js >= jmax:
            continue
        for it in range(k.shape[1]):
            is_ = it + i0
            if is_ < 0 or is_ >= imax:
                continue
            for m in range(k.shape[2]):
                a[js, is_, m] += q * k[jt, it, m]


@numba.njit(cache=True)
def _by_edge(a):
    """View (rows, columns, vertices x 2) of a C-contiguous polyline array."""
    return a.reshape(a.shape[0], a.shape[1], -1)


@numba.njit(cache=True)
def _add_one(q, ja, ia, c, V, H, tv, th):
    """Add ``q`` times the edge templates centred on pixel (ia, ja) to the
    polylines ``V``, ``H`` (C-contiguous)."""
    ny = V.shape[0]
    nx = H.shape[1]
    # GalSim never moves the stamp's rightmost vertical and topmost
    # horizontal boundaries (its update loops run over pixels); same here
    add_shifted(_by_edge(V), _by_edge(tv), q, ja - c, ia - c, ny, nx)
    add_shifted(_by_edge(H), _by_edge(th), q, ja - c, ia - c, ny, nx)


@numba.njit(cache=True)
def add_templates_galsim(dq, scale, c, V, H, tv, th):
    """Add ``dq[j, i] * scale`` times the edge templates on every charged pixel."""
    for ja in range(dq.shape[0]):
        for ia in range(dq.shape[1]):
            if dq[ja, ia] != 0.0:
                _add_one(dq[ja, ia] * scale, ja, ia, c, V, H, tv, th)


@numba.njit(cache=True)
def collect_batch(oi, oj, px, py, image, nominal, dq, changed):
    """Bin one batch of located conversions; shared by both layouts' accumulation.

    ``oi``, ``oj``: pixel of each conversion by the moving boundaries (one
    off the stamp is lost); ``px``, ``py``: its position, binned on the
    undistorted grid into ``nominal``. Adds to ``image`` and ``nominal`` and
    to the batch's charge ``dq`` in place, and lists the pixels whose ``dq``
    became non-zero in ``changed`` (flat indices, in order of their first
    conversion). Returns (number changed, number lost, jlo, jhi, ilo, ihi),
    the last four the bounding box of the changed pixels (empty: ny, -1,
    nx, -1).
    """
    ny, nx = image.shape
    nch = 0
    lost = 0
    jlo, jhi, ilo, ihi = ny, -1, nx, -1
    for p in range(oi.shape[0]):
        i = oi[p]
        j = oj[p]
        if 0 <= i < nx and 0 <= j < ny:
            image[j, i] += 1.0
            if dq[j, i] == 0.0:
                changed[nch] = j * nx + i
                nch += 1
                jlo, jhi, ilo, ihi = min(jlo, j), max(jhi, j), min(ilo, i), max(ihi, i)
            dq[j, i] += 1.0
        else:
            lost += 1
        i0 = int(np.floor(px[p] + 0.5))
        j0 = int(np.floor(py[p] + 0.5))
        if 0 <= i0 < nx and 0 <= j0 < ny:
            nominal[j0, i0] += 1.0
    return nch, lost, jlo, jhi, ilo, ihi


@numba.njit(cache=True)
def accumulate_galsim(px, py, u, batch, image, nominal, V, H, box, scale, c, tv, th,
                      galsim_box):
    """As :func:`lsst_bfdrift.simulation._star_kernels.accumulate`, with GalSim's layout and
    rule."""
    nv = 4 * V.shape[2]
    xs = np.empty(nv)
    ys = np.empty(nv)
    ny, nx = image.shape
    dq = np.zeros((ny, nx))
    changed = np.empty(ny * nx, dtype=np.int64)
    oi = np.empty(min(batch, px.shape[0]), dtype=np.int64)
    oj = np.empty_like(oi)
    lost = 0
    n = px.shape[0]
    for s in range(0, n, batch):
        e = min(s + batch, n)
        for p in range(s, e):
            oi[p - s], oj[p - s] = _locate_one(px[p], py[p], u[p], V, H, box, xs, ys)
        nch, nl, jlo, jhi, ilo, ihi = collect_batch(oi[:e - s], oj[:e - s], px[s:e], py[s:e],
                                                    image, nominal, dq, changed)
        lost += nl
        for m in range(nch):
            j = changed[m] // nx
            i = changed[m] - j * nx
            _add_one(dq[j, i] * scale, j, i, c, V, H, tv, th)
            dq[j, i] = 0.0
        if nch > 0:
            if galsim_box:
                galsim_boxes(V, H, max(jlo - c - 1, 0), min(jhi + c + 2, ny),
                             max(ilo - c - 1, 0), min(ihi + c + 2, nx), box)
            else:
                edge_boxes(V, H, max(jlo - c - 1, 0), min(jhi + c + 2, ny),
                           max(ilo - c - 1, 0), min(ihi + c + 2, nx), box)
    return lost
