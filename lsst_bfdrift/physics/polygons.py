"""Polygon moments (Rasmussen 2015, eqs. 3.12-3.17) and point-in-polygon tests.

Polygons are arrays of vertices ``x, y`` of shape (..., N), ordered
clockwise (so that the paper's shoelace formulas give positive area as
written) and closed implicitly (vertex N is vertex 0). Units are whatever
the vertices are in (pixel units throughout the package).
"""

import numba
import numpy as np
from lsst_bfdrift.utils.errors import InputError

__all__ = ["PolygonMoments", "polygon_moments", "points_in_polygons", "pixel_polygons",
           "locate_points", "inside_polygon"]


class PolygonMoments:
    """Moments of polygons.

    Attributes
    ----------
    area : ndarray
        A (units^2).
    x, y : ndarray
        Centroid IX, IY.
    ixx, iyy, ixy : ndarray
        Central second moments (about the centroid), per unit area.
    e1, e2 : ndarray
        (Ixx - Iyy) / (Ixx + Iyy) and 2 Ixy / (Ixx + Iyy) of the central moments.
    """

    def __init__(self, area, x, y, ixx, iyy, ixy):
        self.area, self.x, self.y = area, x, y
        self.ixx, self.iyy, self.ixy = ixx, iyy, ixy
        tr = ixx + iyy
        self.e1 = (ixx - iyy) / tr
        self.e2 = 2.0 * ixy / tr

    def __repr__(self):
        return f"PolygonMoments(shape={np.shape(self.area)})"


def polygon_moments(x, y, *, origin=None):
    """Area, centroid, central second moments and ellipticity of polygons.

    The raw moments follow the paper's generalised shoelace formulas
    (eqs. 3.12-3.17), evaluated about ``origin`` for numerical precision.

    Parameters
    ----------
    x, y : array_like, shape (..., N)
        Clockwise vertices.
    origin : tuple of array_like, optional
        (x0, y0) broadcastable to ``x.shape[:-1]``, subtracted before the sums
        and added back to the centroid. Default: the vertex mean.

    Returns
    -------
    PolygonMoments

    Examples
    --------
    A unit square (clockwise vertices): area 1, centroid at the origin,
    second moments 1/12, no ellipticity:

    >>> import numpy as np
    >>> from lsst_bfdrift import polygon_moments
    >>> m = polygon_moments(np.array([-0.5, -0.5, 0.5, 0.5]), np.array([-0.5, 0.5, 0.5, -0.5]))
    >>> float(m.area), float(m.x), float(m.ixx), float(m.iyy), float(m.e1)
    (1.0, 0.0, 0.0833..., 0.0833..., 0.0)
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    if x.shape != y.shape or x.ndim < 1 or x.shape[-1] < 3:
        raise InputError(f"x and y must have equal shape (..., N>=3), got {x.shape}, {y.shape}")
    if origin is None:
        x0 = x.mean(axis=-1)
        y0 = y.mean(axis=-1)
    else:
        x0 = np.broadcast_to(np.asarray(origin[0], float), x.shape[:-1])
        y0 = np.broadcast_to(np.asarray(origin[1], float), x.shape[:-1])
    xa = x - x0[..., None]
    ya = y - y0[..., None]
    xb = np.roll(xa, -1, axis=-1)
    yb = np.roll(ya, -1, axis=-1)
    dx = xb - xa
    dy = yb - ya
    area = 0.5 * np.sum(xb * ya - xa * yb, axis=-1)
    sxx = -np.sum(dy * (xa * xa + xb * xb) * (xa + xb), axis=-1) / 12.0
    syy = np.sum(dx * (ya * ya + yb * yb) * (ya + yb), axis=-1) / 12.0
    sxy = (np.sum(dx * xa * (ya * ya + yb * yb + ya * yb), axis=-1) / 6.0
           + np.sum(dx * dx * (ya * ya + 3.0 * yb * yb + 2.0 * ya * yb), axis=-1) / 24.0)
    sx = -np.sum(dy * (xa * xa + xb * xb + xa * xb), axis=-1) / 6.0
    sy = np.sum(dx * (ya * ya + yb * yb + ya * yb), axis=-1) / 6.0
    cx = sx / area
    cy = sy / area
    ixx = sxx / area - cx * cx
    iyy = syy / area - cy * cy
    ixy = sxy / area - cx * cy
    return PolygonMoments(area, cx + x0, cy + y0, ixx, iyy, ixy)


def points_in_polygons(px, py, x, y):
    """Crossing-number test of each point against its own polygon.

    Parameters
    ----------
    px, py : array_like, shape (M,)
        Points.
    x, y : array_like, shape (M, N)
        One polygon per point (any orientation).

    Returns
    -------
    ndarray of bool, shape (M,)
    """
    px = np.asarray(px, float)[..., None]
    py = np.asarray(py, float)[..., None]
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    xb = np.roll(x, -1, axis=-1)
    yb = np.roll(y, -1, axis=-1)
    straddle = (y > py) != (yb > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        xcross = x + (py - y) * (xb - x) / (yb - y)
    crossings = np.sum(straddle & (px < xcross), axis=-1)
    return (crossings % 2) == 1


def pixel_polygons(corners, vedge, hedge, fractions, *, i0=0, j0=0, vedge_t=None,
                   hedge_t=None):
    """Clockwise vertex arrays of a block of pixels from shared boundaries.

    Parameters
    ----------
    corners : ndarray, shape (ny + 1, nx + 1, 2)
        Absolute corner positions (pixel units).
    vedge : ndarray, shape (ny, nx + 1, ns)
        x of the column-boundary samples.
    hedge : ndarray, shape (ny + 1, nx, ns)
        y of the row-boundary samples.
    fractions : ndarray, shape (ns,)
        Nominal sample fractions along each edge.
    i0, j0 : int, optional
        Index of the lower-left pixel (sets the nominal sample positions).
    vedge_t, hedge_t : ndarray, optional
        Tangential displacements (y of vertical, x of horizontal samples).

    Returns
    -------
    x, y : ndarray, shape (ny, nx, 4 + 4 ns)
        Vertices, clockwise from the lower-left corner.
    """
    ny, nx1, ns = vedge.shape
    nx = nx1 - 1
    fr = np.asarray(fractions, float)
    jj = (np.arange(ny) + j0 - 0.5)[:, None, None]
    ii = (np.arange(nx) + i0 - 0.5)[None, :, None]
    # vertical edge samples: nominal y
    vy = jj + fr[None, None, :] + (0.0 if vedge_t is None else vedge_t)
    vy = np.broadcast_to(vy, vedge.shape)
    hx = ii + fr[None, None, :] + (0.0 if hedge_t is None else hedge_t)
    hx = np.broadcast_to(hx, hedge.shape)
    c = corners
    xs = [c[:-1, :-1, 0, None], vedge[:, :-1, :], c[1:, :-1, 0, None],
          hx[1:, :, :], c[1:, 1:, 0, None], vedge[:, 1:, ::-1], c[:-1, 1:, 0, None],
          hx[:-1, :, ::-1]]
    ys = [c[:-1, :-1, 1, None], vy[:, :-1, :], c[1:, :-1, 1, None],
          hedge[1:, :, :], c[1:, 1:, 1, None], vy[:, 1:, ::-1], c[:-1, 1:, 1, None],
          hedge[:-1, :, ::-1]]
    return np.concatenate(xs, axis=-1), np.concatenate(ys, axis=-1)


def locate_points(px, py, x, y, *, i0=0, j0=0):
    """Pixel containing each point, given the block's pixel polygons.

    Tests the nominal pixel first, then its 8 neighbours.

    Parameters
    ----------
    px, py : array_like
        Points (pixel units).
    x, y : ndarray, shape (ny, nx, N)
        Pixel polygons (from :func:`pixel_polygons`).
    i0, j0 : int, optional
        Index of the block's lower-left pixel.

    Returns
    -------
    i, j : ndarray of int
        Pixel indices; -1 (both) for points in no polygon of the block.
    """
    px = np.asarray(px, float).ravel()
    py = np.asarray(py, float).ravel()
    ny, nx = x.shape[:2]
    ii = np.full(px.size, -1)
    jj = np.full(px.size, -1)
    todo = np.arange(px.size)
    ci = np.rint(px).astype(int) - i0
    cj = np.rint(py).astype(int) - j0
    for di, dj in [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1),
                   (-1, -1)]:
        if todo.size == 0:
            break
        ti = ci[todo] + di
        tj = cj[todo] + dj
        ok = (ti >= 0) & (ti < nx) & (tj >= 0) & (tj < ny)
        cand = todo[ok]
        inside = points_in_polygons(px[cand], py[cand], x[tj[ok], ti[ok]], y[tj[ok], ti[ok]])
        hit = cand[inside]
        ii[hit] = ci[hit] + di + i0
        jj[hit] = cj[hit] + dj + j0
        todo = np.setdiff1d(todo, hit, assume_unique=True)
    return ii, jj


@numba.njit(cache=True)
def inside_polygon(px, py, xs, ys):
    """Whether (px, py) lies inside the polygon (xs, ys): compiled crossing-number test.

    The same operations as :func:`points_in_polygons` for one point, callable
    from other numba kernels.
    """
    n = xs.shape[0]
    count = 0
    for a in range(n):
        b = a + 1 if a + 1 < n else 0
        ya = ys[a]
        yb = ys[b]
        if (ya > py) != (yb > py):
            xa = xs[a]
            xcross = xa + (py - ya) * (xs[b] - xa) / (yb - ya)
            if px < xcross:
                count += 1
    return count % 2 == 1
