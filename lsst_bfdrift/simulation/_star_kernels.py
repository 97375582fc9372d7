"""Compiled (numba) kernels of the star simulation: incremental boundaries and
photon assignment.

The boundaries of a stamp are linear in its charge, so after a batch of
conversions only the pixels that received charge (dq_k electrons at pixel k)
change them: every boundary array gains dq_k / Q times the template placed
on pixel k (a direct sum over the changed pixels, clipped to the stamp).
This equals a fresh FFT superposition of the whole charge image
(:func:`lsst_bfdrift.geometry.superpose.superpose_boundaries`) to rounding, and costs
O(changed pixels x template size) instead of O(stamp x kernels x log).

Photons are assigned with a crossing-number test identical, operation by
operation, to :func:`lsst_bfdrift.physics.polygons.points_in_polygons`, on pixel
polygons built on the fly from the shared boundaries in the vertex order of
:func:`lsst_bfdrift.physics.polygons.pixel_polygons`; candidates are the nominal pixel
first, then its neighbours (``NEIGHBOUR_ORDER``). A point inside the nominal
pixel's inner box (right of every left-side vertex, left of every right-side
vertex, above every bottom-side vertex and below every top-side vertex, with a
1e-9 px margin) is inside its polygon by the crossing test too (the horizontal
ray meets only the right side, an odd number of times), so it is accepted
without the full test; the boxes are refreshed where the boundaries moved.

Layouts (pixel (i, j) centred on (i, j), absolute positions in pixel units):
corners (ny + 1, nx + 1, 2), vedge (ny, nx + 1, ns), hedge (ny + 1, nx, ns),
vt like vedge, ht like hedge (tangential; ignored unless ``has_t``).
"""

import numba
import numpy as np

from lsst_bfdrift.physics.polygons import inside_polygon
from lsst_bfdrift.templates.galsim_rules import BOX_MARGIN, add_shifted, collect_batch

__all__ = ["NEIGHBOUR_ORDER", "BOX_MARGIN", "add_templates", "inner_boxes", "locate",
           "accumulate"]

#: Order in which candidate pixels (di, dj) are tested (nominal pixel first).
NEIGHBOUR_ORDER = np.array([(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1),
                            (-1, 1), (-1, -1)], dtype=np.int64)


@numba.njit(cache=True)
def inner_boxes(corners, vedge, hedge, fr, vt, ht, has_t, j0, j1, i0, i1, box):
    """Inner boxes (x_lo, x_hi, y_lo, y_hi) of pixels j0 <= j < j1, i0 <= i < i1."""
    ns = fr.shape[0]
    for j in range(j0, j1):
        for i in range(i0, i1):
            xl = max(corners[j, i, 0], corners[j + 1, i, 0])
            xr = min(corners[j, i + 1, 0], corners[j + 1, i + 1, 0])
            yb = max(corners[j, i, 1], corners[j, i + 1, 1])
            yt = min(corners[j + 1, i, 1], corners[j + 1, i + 1, 1])
            for k in range(ns):
                xl = max(xl, vedge[j, i, k])
                xr = min(xr, vedge[j, i + 1, k])
                yb = max(yb, hedge[j, i, k])
                yt = min(yt, hedge[j + 1, i, k])
            box[j, i, 0] = xl + BOX_MARGIN
            box[j, i, 1] = xr - BOX_MARGIN
            box[j, i, 2] = yb + BOX_MARGIN
            box[j, i, 3] = yt - BOX_MARGIN


@numba.njit(cache=True)
def _add_one(q, ja, ia, c, corners, vedge, hedge, vt, ht, has_t, kc, kv, kh, kvt, kht):
    """Add q times the template centred on pixel (ia, ja) to the boundary arrays."""
    j0 = ja - c
    i0 = ia - c
    add_shifted(corners, kc, q, j0, i0, corners.shape[0], corners.shape[1])
    add_shifted(vedge, kv, q, j0, i0, vedge.shape[0], vedge.shape[1])
    add_shifted(hedge, kh, q, j0, i0, hedge.shape[0], hedge.shape[1])
    if has_t:
        add_shifted(vt, kvt, q, j0, i0, vt.shape[0], vt.shape[1])
        add_shifted(ht, kht, q, j0, i0, ht.shape[0], ht.shape[1])


@numba.njit(cache=True)
def add_templates(dq, scale, c, corners, vedge, hedge, vt, ht, has_t, kc, kv, kh, kvt, kht):
    """Add ``dq[j, i] * scale`` times the template on every pixel with dq != 0."""
    for ja in range(dq.shape[0]):
        for ia in range(dq.shape[1]):
            if dq[ja, ia] != 0.0:
                _add_one(dq[ja, ia] * scale, ja, ia, c, corners, vedge, hedge, vt, ht, has_t,
                         kc, kv, kh, kvt, kht)


@numba.njit(cache=True)
def _build(J, I, corners, vedge, hedge, fr, vt, ht, has_t, xs, ys):
    """Clockwise vertices of pixel (I, J), as geometry.pixel_polygons builds them."""
    ns = fr.shape[0]
    m = 0
    xs[m] = corners[J, I, 0]
    ys[m] = corners[J, I, 1]
    m += 1
    for k in range(ns):
        xs[m] = vedge[J, I, k]
        ys[m] = (J - 0.5 + fr[k]) + (vt[J, I, k] if has_t else 0.0)
        m += 1
    xs[m] = corners[J + 1, I, 0]
    ys[m] = corners[J + 1, I, 1]
    m += 1
    for k in range(ns):
        xs[m] = (I - 0.5 + fr[k]) + (ht[J + 1, I, k] if has_t else 0.0)
        ys[m] = hedge[J + 1, I, k]
        m += 1
    xs[m] = corners[J + 1, I + 1, 0]
    ys[m] = corners[J + 1, I + 1, 1]
    m += 1
    for k in range(ns - 1, -1, -1):
        xs[m] = vedge[J, I + 1, k]
        ys[m] = (J - 0.5 + fr[k]) + (vt[J, I + 1, k] if has_t else 0.0)
        m += 1
    xs[m] = corners[J, I + 1, 0]
    ys[m] = corners[J, I + 1, 1]
    m += 1
    for k in range(ns - 1, -1, -1):
        xs[m] = (I - 0.5 + fr[k]) + (ht[J, I, k] if has_t else 0.0)
        ys[m] = hedge[J, I, k]
        m += 1


@numba.njit(cache=True)
def _locate_one(px, py, corners, vedge, hedge, fr, vt, ht, has_t, order, box, xs, ys):
    ny = vedge.shape[0]
    nx = hedge.shape[1]
    ci = int(np.floor(px + 0.5))
    cj = int(np.floor(py + 0.5))
    if 0 <= ci < nx and 0 <= cj < ny:
        if (box[cj, ci, 0] < px < box[cj, ci, 1]) and (box[cj, ci, 2] < py < box[cj, ci, 3]):
            return ci, cj
    for o in range(order.shape[0]):
        i = ci + order[o, 0]
        j = cj + order[o, 1]
        if i < 0 or i >= nx or j < 0 or j >= ny:
            continue
        _build(j, i, corners, vedge, hedge, fr, vt, ht, has_t, xs, ys)
        if inside_polygon(px, py, xs, ys):
            return i, j
    return -1, -1


@numba.njit(cache=True)
def locate(px, py, corners, vedge, hedge, fr, vt, ht, has_t, order, box, oi, oj):
    """Pixel (oi, oj) containing each point; -1 where no candidate contains it."""
    nv = 4 + 4 * fr.shape[0]
    xs = np.empty(nv)
    ys = np.empty(nv)
    for p in range(px.shape[0]):
        oi[p], oj[p] = _locate_one(px[p], py[p], corners, vedge, hedge, fr, vt, ht, has_t,
                                   order, box, xs, ys)


@numba.njit(cache=True)
def accumulate(px, py, batch, image, nominal, corners, vedge, hedge, fr, vt, ht, has_t, order,
               box, scale, c, kc, kv, kh, kvt, kht):
    """Convert photons in order, updating the boundaries after every ``batch``.

    Adds to ``image`` (pixel found by the moving polygons) and ``nominal``
    (undistorted grid) in place; returns the number of photons that landed in
    no pixel of the stamp. After each batch the charge it added is
    superposed with the template (``scale`` = 1 / template charge). The
    binning of a batch is :func:`~lsst_bfdrift.templates.galsim_rules.collect_batch`,
    shared with GalSim's layout.
    """
    nv = 4 + 4 * fr.shape[0]
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
            oi[p - s], oj[p - s] = _locate_one(px[p], py[p], corners, vedge, hedge, fr, vt, ht,
                                               has_t, order, box, xs, ys)
        nch, nl, jlo, jhi, ilo, ihi = collect_batch(oi[:e - s], oj[:e - s], px[s:e], py[s:e],
                                                    image, nominal, dq, changed)
        lost += nl
        for m in range(nch):
            j = changed[m] // nx
            i = changed[m] - j * nx
            _add_one(dq[j, i] * scale, j, i, c, corners, vedge, hedge, vt, ht, has_t,
                     kc, kv, kh, kvt, kht)
            dq[j, i] = 0.0
        if nch > 0:
            # pixels whose boundaries moved: within c + 1 of a changed pixel
            inner_boxes(corners, vedge, hedge, fr, vt, ht, has_t, max(jlo - c - 1, 0),
                        min(jhi + c + 2, ny), max(ilo - c - 1, 0), min(ihi + c + 2, nx), box)
    return lost
