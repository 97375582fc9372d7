"""Tests of polygon moments and pixel polygons in :mod:`lsst_bfdrift.physics.polygons`.

References are independent of the package: fine-grid integrals of rasterised
polygons (``matplotlib.path.Path.contains_points``), closed-form moments of
squares, rectangles and right triangles worked out by hand, a shoelace area
written out here, and ``matplotlib`` point-in-polygon tests.
"""

import numpy as np
import pytest
from matplotlib.path import Path
from numpy.testing import assert_allclose, assert_array_equal

from lsst_bfdrift.physics.polygons import (
    PolygonMoments,
    locate_points,
    pixel_polygons,
    points_in_polygons,
    polygon_moments,
)


# ---------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------

def star_polygon(rng, n, centre=(0.0, 0.0), rmin=0.3, rmax=1.0):
    """Clockwise star-shaped polygon: sorted random angles, random radii.

    With rmin well below rmax the polygon is generally non-convex.
    """
    theta = np.sort(rng.uniform(0.0, 2.0 * np.pi, n))
    r = rng.uniform(rmin, rmax, n)
    x = centre[0] + r * np.cos(theta)
    y = centre[1] + r * np.sin(theta)
    return x[::-1].copy(), y[::-1].copy()  # counter-clockwise -> clockwise


def shoelace_area_cw(x, y):
    """Area of a clockwise polygon (positive), written out independently."""
    total = 0.0
    n = len(x)
    for k in range(n):
        k1 = (k + 1) % n
        total += x[k1] * y[k] - x[k] * y[k1]
    return 0.5 * total


def grid_moments(x, y, n=2000):
    """Area, centroid and central moments of a polygon on an n x n grid."""
    x0, x1 = x.min(), x.max()
    y0, y1 = y.min(), y.max()
    hx = (x1 - x0) / n
    hy = (y1 - y0) / n
    xc = x0 + hx * (np.arange(n) + 0.5)
    yc = y0 + hy * (np.arange(n) + 0.5)
    gx, gy = np.meshgrid(xc, yc)
    inside = Path(np.column_stack([x, y])).contains_points(
        np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
    px = gx[inside]
    py = gy[inside]
    area = inside.sum() * hx * hy
    cx, cy = px.mean(), py.mean()
    # cell second moment h^2 / 12 added for the finite pixel size
    ixx = np.mean((px - cx) ** 2) + hx**2 / 12
    iyy = np.mean((py - cy) ** 2) + hy**2 / 12
    ixy = np.mean((px - cx) * (py - cy))
    return area, cx, cy, ixx, iyy, ixy


def nominal_block(nx, ny, ns, i0, j0):
    """Undistorted boundaries of an nx x ny block of unit pixels."""
    jj, ii = np.meshgrid(np.arange(ny + 1) + j0 - 0.5, np.arange(nx + 1) + i0 - 0.5,
                         indexing="ij")
    corners = np.stack([ii, jj], axis=-1)
    vedge = np.broadcast_to((np.arange(nx + 1) + i0 - 0.5)[None, :, None],
                            (ny, nx + 1, ns)).copy()
    hedge = np.broadcast_to((np.arange(ny + 1) + j0 - 0.5)[:, None, None],
                            (ny + 1, nx, ns)).copy()
    fractions = (np.arange(ns) + 0.5) / ns
    return corners, vedge, hedge, fractions


def distorted_block(rng, nx, ny, ns, i0, j0, amp=0.05, tangential=True):
    """Nominal block with independent random shifts of all shared boundaries.

    ``amp`` is kept below half the spacing of the samples nearest a corner so
    that the pixel polygons stay simple (non self-intersecting).
    """
    corners, vedge, hedge, fractions = nominal_block(nx, ny, ns, i0, j0)
    corners = corners + rng.uniform(-amp, amp, corners.shape)
    vedge = vedge + rng.uniform(-amp, amp, vedge.shape)
    hedge = hedge + rng.uniform(-amp, amp, hedge.shape)
    kw = {}
    if tangential:
        kw["vedge_t"] = rng.uniform(-0.2 * amp, 0.2 * amp, vedge.shape)
        kw["hedge_t"] = rng.uniform(-0.2 * amp, 0.2 * amp, hedge.shape)
    return corners, vedge, hedge, fractions, kw


def outer_boundary(corners, vedge, hedge, fractions, i0, j0, vedge_t=None,
                   hedge_t=None):
    """Clockwise outer boundary of a block, built vertex by vertex."""
    ny, nx1, ns = vedge.shape
    nx = nx1 - 1
    vt = np.zeros(vedge.shape) if vedge_t is None else vedge_t
    ht = np.zeros(hedge.shape) if hedge_t is None else hedge_t
    pts = []
    for j in range(ny):  # left side, upwards
        pts.append(tuple(corners[j, 0]))
        for k in range(ns):
            pts.append((vedge[j, 0, k], j0 + j - 0.5 + fractions[k] + vt[j, 0, k]))
    for i in range(nx):  # top side, rightwards
        pts.append(tuple(corners[ny, i]))
        for k in range(ns):
            pts.append((i0 + i - 0.5 + fractions[k] + ht[ny, i, k], hedge[ny, i, k]))
    for j in reversed(range(ny)):  # right side, downwards
        pts.append(tuple(corners[j + 1, nx]))
        for k in reversed(range(ns)):
            pts.append((vedge[j, nx, k], j0 + j - 0.5 + fractions[k] + vt[j, nx, k]))
    for i in reversed(range(nx)):  # bottom side, leftwards
        pts.append(tuple(corners[0, i + 1]))
        for k in reversed(range(ns)):
            pts.append((i0 + i - 0.5 + fractions[k] + ht[0, i, k], hedge[0, i, k]))
    pts = np.array(pts)
    return pts[:, 0], pts[:, 1]


# ---------------------------------------------------------------------------
# polygon_moments
# ---------------------------------------------------------------------------

class TestPolygonMoments:
    @pytest.mark.parametrize("seed,n", [(11, 7), (12, 15), (13, 40)])
    def test_random_polygons_vs_fine_grid(self, seed, n):
        rng = np.random.default_rng(seed)
        x, y = star_polygon(rng, n, centre=rng.uniform(-3, 3, 2))
        # stretch and shear to get non-zero e1, e2
        a = np.array([[1.3, 0.4], [0.1, 0.8]])
        x, y = a @ np.vstack([x, y])
        mom = polygon_moments(x, y)
        area, cx, cy, ixx, iyy, ixy = grid_moments(x, y)
        tr = ixx + iyy
        size = np.sqrt(area)
        assert_allclose(mom.area, area, rtol=1e-3)
        assert_allclose([mom.x, mom.y], [cx, cy], atol=1e-3 * size)
        assert_allclose([mom.ixx, mom.iyy, mom.ixy], [ixx, iyy, ixy], atol=1e-3 * tr)
        assert_allclose([mom.e1, mom.e2], [(ixx - iyy) / tr, 2 * ixy / tr], atol=2e-3)
        assert mom.area > 0

    def test_unit_square(self):
        # clockwise: up the left side, across the top, down the right side
        mom = polygon_moments([0.0, 0.0, 1.0, 1.0], [0.0, 1.0, 1.0, 0.0])
        assert_allclose([mom.area, mom.x, mom.y], [1.0, 0.5, 0.5], rtol=1e-14)
        assert_allclose([mom.ixx, mom.iyy], [1 / 12, 1 / 12], rtol=1e-13)
        assert_allclose([mom.ixy, mom.e1, mom.e2], 0.0, atol=1e-14)

    def test_rectangle(self):
        w, h, x0, y0 = 3.0, 1.5, -2.0, 5.0
        x = np.array([x0, x0, x0 + w, x0 + w])
        y = np.array([y0, y0 + h, y0 + h, y0])
        mom = polygon_moments(x, y)
        assert_allclose(mom.area, w * h, rtol=1e-14)
        assert_allclose([mom.x, mom.y], [x0 + w / 2, y0 + h / 2], rtol=1e-14)
        assert_allclose([mom.ixx, mom.iyy], [w**2 / 12, h**2 / 12], rtol=1e-12)
        assert_allclose(mom.ixy, 0.0, atol=1e-14)
        assert_allclose(mom.e1, (w**2 - h**2) / (w**2 + h**2), rtol=1e-12)
        assert_allclose(mom.e2, 0.0, atol=1e-14)

    def test_right_triangle(self):
        # Legs a along x and b along y from the origin. By hand:
        # A = ab/2, centroid (a/3, b/3), <x^2> = a^2/6 -> ixx = a^2/18,
        # iyy = b^2/18, <xy> = ab/12 -> ixy = ab/12 - ab/9 = -ab/36.
        a, b = 2.0, 3.0
        mom = polygon_moments([0.0, 0.0, a], [0.0, b, 0.0])  # clockwise
        assert_allclose(mom.area, a * b / 2, rtol=1e-14)
        assert_allclose([mom.x, mom.y], [a / 3, b / 3], rtol=1e-14)
        assert_allclose([mom.ixx, mom.iyy, mom.ixy],
                        [a**2 / 18, b**2 / 18, -a * b / 36], rtol=1e-12)
        tr = (a**2 + b**2) / 18
        assert_allclose([mom.e1, mom.e2],
                        [(a**2 - b**2) / 18 / tr, -2 * a * b / 36 / tr], rtol=1e-12)

    def test_collinear_extra_vertices_change_nothing(self):
        x = np.array([0.0, 0.0, 0.0, 2.0, 2.0, 1.0])
        y = np.array([0.0, 0.5, 1.0, 1.0, 0.0, 0.0])
        ref = polygon_moments([0.0, 0.0, 2.0, 2.0], [0.0, 1.0, 1.0, 0.0])
        mom = polygon_moments(x, y)
        for name in ("area", "x", "y", "ixx", "iyy", "ixy", "e1", "e2"):
            assert_allclose(getattr(mom, name), getattr(ref, name), rtol=1e-12,
                            atol=1e-14)

    def test_translation_invariance_far_from_origin(self):
        rng = np.random.default_rng(21)
        x, y = star_polygon(rng, 25)
        base = polygon_moments(x, y)
        far = polygon_moments(x + 1e4, y - 1e4)
        assert_allclose(far.area, base.area, rtol=1e-10)
        assert_allclose([far.x - 1e4, far.y + 1e4], [base.x, base.y], atol=1e-10)
        for name in ("ixx", "iyy", "ixy"):
            assert_allclose(getattr(far, name), getattr(base, name), rtol=1e-9,
                            atol=1e-12)
        assert_allclose([far.e1, far.e2], [base.e1, base.e2], atol=1e-9)

    def test_explicit_origin(self):
        rng = np.random.default_rng(22)
        x, y = star_polygon(rng, 12, centre=(5.0, -3.0))
        a = polygon_moments(x, y)
        b = polygon_moments(x, y, origin=(4.0, -2.0))
        for name in ("area", "x", "y", "ixx", "iyy", "ixy"):
            assert_allclose(getattr(b, name), getattr(a, name), rtol=1e-12, atol=1e-14)

    def test_counter_clockwise_gives_negative_area(self):
        rng = np.random.default_rng(23)
        x, y = star_polygon(rng, 10)
        cw = polygon_moments(x, y)
        ccw = polygon_moments(x[::-1], y[::-1])
        assert cw.area > 0 > ccw.area
        assert_allclose(ccw.area, -cw.area, rtol=1e-13)
        assert_allclose(ccw.area, -shoelace_area_cw(x, y), rtol=1e-13)
        # ratios of raw moments to area are orientation independent
        for name in ("x", "y", "ixx", "iyy", "ixy"):
            assert_allclose(getattr(ccw, name), getattr(cw, name), rtol=1e-12,
                            atol=1e-14)

    def test_batched_shapes(self):
        rng = np.random.default_rng(24)
        polys = [star_polygon(rng, 9, centre=rng.uniform(-5, 5, 2)) for _ in range(6)]
        x = np.array([p[0] for p in polys]).reshape(2, 3, 9)
        y = np.array([p[1] for p in polys]).reshape(2, 3, 9)
        mom = polygon_moments(x, y)
        assert isinstance(mom, PolygonMoments)
        assert mom.area.shape == (2, 3)
        for k, (px, py) in enumerate(polys):
            single = polygon_moments(px, py)
            idx = np.unravel_index(k, (2, 3))
            for name in ("area", "x", "y", "ixx", "iyy", "ixy", "e1", "e2"):
                assert_allclose(getattr(mom, name)[idx], getattr(single, name),
                                rtol=1e-12, atol=1e-14)
        # per-polygon origins broadcast over the batch
        org = polygon_moments(x, y, origin=(x.mean(-1) + 0.1, y.mean(-1)))
        assert_allclose(org.ixx, mom.ixx, rtol=1e-11)

    def test_bad_shapes(self):
        with pytest.raises(ValueError, match="shape"):
            polygon_moments([0.0, 1.0], [0.0, 1.0])
        with pytest.raises(ValueError, match="shape"):
            polygon_moments([0.0, 1.0, 2.0], [0.0, 1.0])


# ---------------------------------------------------------------------------
# points_in_polygons
# ---------------------------------------------------------------------------

class TestPointsInPolygons:
    @pytest.mark.parametrize("seed", [31, 32])
    def test_vs_matplotlib(self, seed):
        rng = np.random.default_rng(seed)
        m, n = 400, 11
        xs = np.empty((m, n))
        ys = np.empty((m, n))
        for k in range(m):
            xs[k], ys[k] = star_polygon(rng, n, centre=rng.uniform(-2, 2, 2), rmin=0.2)
        px = rng.uniform(-1.0, 1.0, m) + xs.mean(axis=1)
        py = rng.uniform(-1.0, 1.0, m) + ys.mean(axis=1)
        got = points_in_polygons(px, py, xs, ys)
        ref = np.array([Path(np.column_stack([xs[k], ys[k]])).contains_points([[px[k], py[k]]])[0]
                        for k in range(m)])
        assert 0.2 < ref.mean() < 0.8  # both outcomes well represented
        assert_array_equal(got, ref)
        # orientation does not matter
        assert_array_equal(points_in_polygons(px, py, xs[:, ::-1], ys[:, ::-1]), ref)

    def test_simple_square(self):
        x = np.tile([0.0, 0.0, 1.0, 1.0], (4, 1))
        y = np.tile([0.0, 1.0, 1.0, 0.0], (4, 1))
        got = points_in_polygons([0.5, 1.5, 0.99, -0.01], [0.5, 0.5, 0.01, 0.5], x, y)
        assert_array_equal(got, [True, False, True, False])


# ---------------------------------------------------------------------------
# pixel_polygons
# ---------------------------------------------------------------------------

class TestPixelPolygons:
    def test_undistorted_unit_squares(self):
        nx, ny, ns, i0, j0 = 4, 3, 5, 7, -2
        corners, vedge, hedge, fr = nominal_block(nx, ny, ns, i0, j0)
        x, y = pixel_polygons(corners, vedge, hedge, fr, i0=i0, j0=j0)
        assert x.shape == y.shape == (ny, nx, 4 + 4 * ns)
        mom = polygon_moments(x, y)
        jj, ii = np.meshgrid(np.arange(ny) + j0, np.arange(nx) + i0, indexing="ij")
        assert_allclose(mom.area, 1.0, rtol=1e-13)
        assert_allclose(mom.x, ii, atol=1e-12)
        assert_allclose(mom.y, jj, atol=1e-12)
        assert_allclose(mom.ixx, 1 / 12, rtol=1e-12)
        assert_allclose(mom.iyy, 1 / 12, rtol=1e-12)
        assert_allclose([mom.e1, mom.e2], 0.0, atol=1e-12)
        # every vertex lies on the boundary of its nominal square
        dx = np.abs(x - ii[..., None])
        dy = np.abs(y - jj[..., None])
        assert np.all(np.maximum(dx, dy) == pytest.approx(0.5, abs=1e-12))
        # first vertex is the lower-left corner
        assert_allclose(x[..., 0], ii - 0.5)
        assert_allclose(y[..., 0], jj - 0.5)

    @pytest.mark.parametrize("tangential", [False, True])
    def test_distorted_block_tiles(self, tangential):
        rng = np.random.default_rng(41 + tangential)
        nx, ny, ns, i0, j0 = 5, 4, 6, -3, 10
        corners, vedge, hedge, fr, kw = distorted_block(rng, nx, ny, ns, i0, j0,
                                                        tangential=tangential)
        x, y = pixel_polygons(corners, vedge, hedge, fr, i0=i0, j0=j0, **kw)
        mom = polygon_moments(x, y)
        # clockwise: positive area, close to 1
        assert np.all(mom.area > 0)
        assert_allclose(mom.area, 1.0, atol=0.5)
        ox, oy = outer_boundary(corners, vedge, hedge, fr, i0, j0, **kw)
        outer = shoelace_area_cw(ox, oy)
        assert_allclose(mom.area.sum(), outer, rtol=0, atol=1e-12)
        # each pixel's area equals an independent shoelace of its vertices
        for j in range(ny):
            for i in range(nx):
                assert_allclose(mom.area[j, i], shoelace_area_cw(x[j, i], y[j, i]),
                                rtol=1e-12)

    def test_neighbours_share_edges(self):
        rng = np.random.default_rng(43)
        nx, ny, ns = 3, 3, 4
        corners, vedge, hedge, fr, kw = distorted_block(rng, nx, ny, ns, 0, 0)
        x, y = pixel_polygons(corners, vedge, hedge, fr, **kw)
        left = slice(0, ns + 2)                # LL corner, left samples, UL corner
        right = slice(2 * ns + 2, 3 * ns + 4)  # UR corner, right samples, LR corner
        # right edge of (i, j), reversed, is the left edge of (i + 1, j)
        assert_array_equal(x[:, :-1, right][..., ::-1], x[:, 1:, left])
        assert_array_equal(y[:, :-1, right][..., ::-1], y[:, 1:, left])
        top = slice(ns + 1, 2 * ns + 3)        # UL corner, top samples, UR corner
        bottom = np.r_[3 * ns + 3:4 * ns + 4, 0]  # LR corner, bottom samples, LL corner
        assert_array_equal(x[1:, :, bottom][..., ::-1], x[:-1, :, top])
        assert_array_equal(y[1:, :, bottom][..., ::-1], y[:-1, :, top])


# ---------------------------------------------------------------------------
# locate_points
# ---------------------------------------------------------------------------

class TestLocatePoints:
    @pytest.mark.parametrize("seed", [51, 52])
    def test_vs_matplotlib(self, seed):
        rng = np.random.default_rng(seed)
        nx, ny, ns, i0, j0 = 5, 4, 4, 3, -6
        corners, vedge, hedge, fr, kw = distorted_block(rng, nx, ny, ns, i0, j0,
                                                        amp=0.06)
        x, y = pixel_polygons(corners, vedge, hedge, fr, i0=i0, j0=j0, **kw)
        npt = 3000
        px = rng.uniform(i0 - 1.0, i0 + nx, npt)
        py = rng.uniform(j0 - 1.0, j0 + ny, npt)
        got_i, got_j = locate_points(px, py, x, y, i0=i0, j0=j0)
        ref_i = np.full(npt, -1)
        ref_j = np.full(npt, -1)
        pts = np.column_stack([px, py])
        for j in range(ny):
            for i in range(nx):
                inside = Path(np.column_stack([x[j, i], y[j, i]])).contains_points(pts)
                assert not np.any(inside & (ref_i >= 0)), "pixel polygons overlap"
                ref_i[inside] = i + i0
                ref_j[inside] = j + j0
        assert 0.5 < np.mean(ref_i >= 0) < 0.95  # points inside and outside
        # some points lie in a pixel other than the nominal one (neighbour search)
        moved = (ref_i >= 0) & ((ref_i != np.rint(px)) | (ref_j != np.rint(py)))
        assert moved.sum() > 10
        assert_array_equal(got_i, ref_i)
        assert_array_equal(got_j, ref_j)

    def test_far_outside_gives_minus_one(self):
        corners, vedge, hedge, fr = nominal_block(3, 3, 2, 0, 0)
        x, y = pixel_polygons(corners, vedge, hedge, fr)
        i, j = locate_points([10.0, -5.0, 1.0, 1.2], [1.0, 1.0, -3.0, 1.1], x, y)
        assert_array_equal(i, [-1, -1, -1, 1])
        assert_array_equal(j, [-1, -1, -1, 1])
