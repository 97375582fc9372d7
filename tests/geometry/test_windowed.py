"""Tests of lsst_bfdrift.geometry._windowed: first-order maps in windows (the
windowed route of ``linear_moment_maps``).

The bound is checked against direct sums (CORRECTNESS: an independent
reference); the maps against the exact polygon moments of ``moment_maps``
and against the full-image first-order route (CONSISTENCY: the package's
own model).
"""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from tests.geometry.conftest import star_field

from lsst_bfdrift.geometry._windowed import (expected_route, first_order_bound, signal_floor)
from lsst_bfdrift.geometry.bounds import reference_level
from lsst_bfdrift.geometry.first_order import (LINEAR_MAPS, FirstOrderPass,
                                               convolved_first_order_maps, linear_kernels)
from lsst_bfdrift.geometry.linear import linear_moment_maps
from lsst_bfdrift.geometry.superpose import moment_maps

NOMINAL = np.array([1.0, 0.0, 0.0, 0.0, 0.0])


def _direct_abs_sum(kernel, g):
    """sum_s kernel(s) g(p - s) over the kernel's offsets, g zero outside (loops)."""
    m = kernel.shape[0]
    r = m // 2
    ny, nx = g.shape
    pad = np.zeros((ny + 2 * r, nx + 2 * r))
    pad[r:r + ny, r:r + nx] = g
    out = np.zeros((ny, nx))
    for t in range(m):
        for u in range(m):
            # offset (t - r, u - r) from the aggressor to the pixel
            out += kernel[t, u] * pad[2 * r - t:2 * r - t + ny, 2 * r - u:2 * r - u + nx]
    return out


@pytest.mark.parametrize("b", [1, 2, 3])
def test_first_order_bound_holds(default_template, b):
    """CORRECTNESS: with bin 1 the bound is the direct sum of max_k w_k abs(K_k)
    times abs(q - qbar) (to its stated margin); with any bin it is at least
    each weighted first-order response of q - qbar (direct double-precision
    convolution) in every pixel of the bin."""
    rng = np.random.default_rng(3)
    q = star_field(61, 4e5, rng, sky=800.0)
    lk = linear_kernels(default_template, samples=8)
    qbar = reference_level(q)
    w = np.array([3.0, 7.0, 5.0, 11.0, 2.0]) * 1e4
    m = first_order_bound(lk, q, qbar, w, bin=b, workers=1)
    pix = np.repeat(np.repeat(m, b, 0), b, 1)[:q.shape[0], :q.shape[1]]
    comb = np.max(np.abs(lk.kernels) * w[:, None, None], axis=0)
    direct = _direct_abs_sum(comb, np.abs(q - qbar))
    if b == 1:
        assert_allclose(m, direct, rtol=2e-5, atol=2e-5 * direct.max())
    assert np.all(pix >= direct)
    resp, _ = convolved_first_order_maps(lk, q - qbar, LINEAR_MAPS, tile=q.shape,
                                         dtype=np.float64)
    for k in range(5):
        lin = w[k] * np.abs(resp[k] - NOMINAL[k])
        assert np.all(pix >= lin), LINEAR_MAPS[k]


def test_signal_floor_is_the_box_maximum(default_template):
    """CONSISTENCY: the floor is the first-order maps' largest deviation over
    the box around the brightest pixel (the full-image maps), at most the
    maps' signal."""
    rng = np.random.default_rng(4)
    q = star_field(70, 1e6, rng, sky=1000.0)
    lk = linear_kernels(default_template, samples=8)
    floor, (y0, y1, x0, x1) = signal_floor(lk, q, reference_level(q))
    j, i = np.unravel_index(np.argmax(q), q.shape)
    assert y0 <= j < y1 and x0 <= i < x1 and (y1 - y0, x1 - x0) == (9, 9)
    maps, smax = convolved_first_order_maps(lk, q, LINEAR_MAPS, tile=(32, 32),
                                            dtype=np.float64)
    box = [np.abs(m[y0:y1, x0:x1] - n).max() for m, n in zip(maps, NOMINAL)]
    assert_allclose(floor, box, rtol=1e-12)
    assert np.all(floor <= smax * (1 + 1e-12))
    assert floor[0] == pytest.approx(smax[0], rel=1e-12)  # the area's peak is the star's


# (seed, n, stars per side of grid, sky, noise, rtol)
FIELDS = [(5, 200, 1, 1000.0, False, 1e-3), (6, 224, 2, 20.0, True, 1e-2),
          (7, 192, 2, 100.0, True, 3e-2), (8, 160, 1, 0.0, False, 1e-3)]


def _field(seed, n, grid, sky, noise):
    """A bright star at the centre and faint ones, plus a grid x grid lattice
    of 1e5 e stars; Poisson sky (``noise``) or a uniform one."""
    rng = np.random.default_rng(seed)
    q = star_field(n, 1.5e6, rng, sky=sky) if noise else \
        star_field(n, 1.5e6, rng, sky=0.0) + sky
    yy, xx = np.mgrid[0:n, 0:n]
    for a in range(grid):
        for c in range(grid):
            y, x = (a + 0.5) * n / grid + 7.3, (c + 0.5) * n / grid - 5.1
            q += 1e5 * np.exp(-0.5 * ((xx - x)**2 + (yy - y)**2) / 1.8**2) / (2 * np.pi * 1.8**2)
    return q


@pytest.mark.parametrize("field", FIELDS)
def test_windowed_maps_within_tolerance(default_template, field):
    """CONSISTENCY: on star fields of several seeds, densities and sky levels
    (uniform and Poisson) the windowed maps are within rtol x signal of the
    exact maps and of the full-image route's maps; the windows cover part of
    the image only; the signal is the full route's. (On these small images
    the windows' margins make a large share: window_fraction raised.)"""
    seed, n, grid, sky, noise, rtol = field
    q = _field(seed, n, grid, sky, noise)
    win, full = {}, {}
    mw = linear_moment_maps(default_template, q, samples=8, rtol=rtol, info=win,
                            window_fraction=0.7)
    mf = linear_moment_maps(default_template, q, samples=8, rtol=rtol, info=full,
                            route="full")
    assert win["route"] == "windows" and full["route"] == "full"
    assert 0 < win["first_order_fraction"] < 0.9 and full["first_order_fraction"] == 1.0
    assert win["exact_fraction"] > 0
    exact = moment_maps(default_template, q, samples=8)
    for k in LINEAR_MAPS:
        s = win["signal"][k]
        assert s == pytest.approx(full["signal"][k], rel=1e-5), k
        assert np.abs(getattr(mw, k) - getattr(exact, k)).max() <= rtol * s, k
        assert np.abs(getattr(mw, k) - getattr(mf, k)).max() <= rtol * s, k
    # the uniform value is returned somewhere: the routes differ (the test
    # would pass with the full route's maps returned otherwise)
    assert not np.array_equal(mw.e1, mf.e1)
    # the dtypes are the full route's
    assert mw.area.dtype == np.float64 and mw.e1.dtype == mf.e1.dtype


def test_noisy_sky_takes_the_full_route(default_template):
    """A 1000 e Poisson sky at rtol 1e-3: its noise alone exceeds what the
    tolerance leaves (the sample's guess says so); 'auto' takes the full route,
    the same arrays as route='full'."""
    rng = np.random.default_rng(9)
    q = star_field(128, 1.5e6, rng, sky=1000.0)
    lk = linear_kernels(default_template, samples=8)
    qbar = reference_level(q)
    floor, _ = signal_floor(lk, q, qbar)
    assert expected_route(lk, q, qbar, floor, 1e-3) == "full"
    # a loose tolerance leaves room (the windows' share not limited here)
    assert expected_route(lk, q, qbar, floor, 0.3, window_fraction=1.0) == "windows"
    info = {}
    m = linear_moment_maps(default_template, q, samples=8, info=info)
    f = linear_moment_maps(default_template, q, samples=8, route="full")
    assert info["route"] == "full"
    for k in LINEAR_MAPS:
        assert np.array_equal(getattr(m, k), getattr(f, k)), k


def test_windows_over_most_of_the_image_take_the_full_route(default_template):
    """A crowded field on a uniform sky: the sky allows windows, but the
    sources' would cover more than window_fraction of the image: full route.
    Forced ('windows'), the maps are still within the tolerance of the
    exact ones."""
    q = _field(11, 160, 8, 1000.0, False)
    info, forced = {}, {}
    lk = linear_kernels(default_template, samples=8)
    qbar = reference_level(q)
    floor, _ = signal_floor(lk, q, qbar)
    # the sky (uniform: no noise) leaves room; the sources' estimated windows
    # do not, but one source's do
    assert np.median(np.abs(q - qbar)) < 1.0
    assert expected_route(lk, q, qbar, floor, 1e-3) == "full"
    one = _field(11, 160, 0, 1000.0, False)
    qb1 = reference_level(one)
    assert expected_route(lk, one, qb1, signal_floor(lk, one, qb1)[0], 1e-3,
                          window_fraction=0.9) == "windows"
    m = linear_moment_maps(default_template, q, samples=8, info=info)
    assert info["route"] == "full"
    w = linear_moment_maps(default_template, q, samples=8, info=forced, route="windows")
    assert forced["route"] == "windows" and forced["first_order_fraction"] > 0.3
    exact = moment_maps(default_template, q, samples=8)
    for k in LINEAR_MAPS:
        s = forced["signal"][k]
        assert np.abs(getattr(w, k) - getattr(exact, k)).max() <= 1e-3 * s, k
        assert np.abs(getattr(m, k) - getattr(w, k)).max() <= 1e-3 * s, k


def test_small_image_and_zero_signal_take_the_full_route(small_template, default_template):
    """An image smaller than the uniform one (2 reach + 1 px) and a uniform
    image of no charge (no signal floor) take the full route even when
    'windows' is asked."""
    info = {}
    n = 2 * (small_template.center + 1)
    q = np.full((n, n + 5), 500.0)
    q[n // 2, n // 2] = 3e4
    linear_moment_maps(small_template, q, route="windows", info=info)
    assert info["route"] == "full"
    info = {}
    m = linear_moment_maps(default_template, np.zeros((30, 30)), route="windows", info=info)
    assert info["route"] == "full" and np.array_equal(m.area, np.ones((30, 30)))


def test_progress_and_map_subset(default_template):
    """Progress is reported from 0 to 1, never decreasing; a subset of the
    maps gives the same arrays as all five (the signal of the maps left out
    is at most theirs: a smaller tolerance)."""
    q = _field(5, 200, 1, 1000.0, False)
    seen = []
    info_all, info_sub = {}, {}
    full = linear_moment_maps(default_template, q, samples=8, progress=seen.append,
                              info=info_all, window_fraction=0.7)
    sub = linear_moment_maps(default_template, q, samples=8, maps=("dx", "e2"), info=info_sub,
                             window_fraction=0.7)
    assert info_all["route"] == info_sub["route"] == "windows"
    assert seen[0] == 0.0 and seen[-1] == 1.0 and np.all(np.diff(seen) >= 0)
    assert sub.area is None and sub.e1 is None
    assert np.array_equal(sub.dx, full.dx) and np.array_equal(sub.e2, full.e2)
    for k in LINEAR_MAPS:
        assert info_sub["signal"][k] <= info_all["signal"][k] * (1 + 1e-12)


@pytest.mark.parametrize("kw, match", [
    ({"route": "tiles"}, "route must be 'auto', 'full' or 'windows'"),
    ({"window_fraction": 0.0}, r"window_fraction must be in \(0, 1\]"),
    ({"route": "windows", "bound": "analytic"}, "route='windows' needs bound='measured'"),
])
def test_bad_route_options(default_template, kw, match):
    q = np.full((30, 30), 100.0)
    before = q.copy()
    with pytest.raises(ValueError, match=match):
        linear_moment_maps(default_template, q, **kw)
    assert np.array_equal(q, before)


def test_windows_refused_with_a_first_order_pass(default_template):
    q = np.full((30, 30), 100.0)
    fo = FirstOrderPass(default_template, q.shape)
    with pytest.raises(ValueError, match="no first_order"):
        linear_moment_maps(default_template, q, first_order=fo, route="windows")
