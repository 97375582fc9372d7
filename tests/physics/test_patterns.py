"""Tests of lsst_bfdrift.physics.patterns: tearing onset, bamboo, PRNU structure functions."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.patterns import (bamboo, bamboo_summary, block_geometry,
                                   channel_stop_area_map, expected_structure_function,
                                   jitter_area_map, structure_function, tearing_onset,
                                   tearing_summary)
from lsst_bfdrift.validation.paper_figures import paper_parameters

P = paper_parameters()


# -- structure functions (pure numerics) ------------------------------------

def _direct_d(a, lag, axis):
    """Mean squared difference at ``lag`` by explicit loops."""
    total, n = 0.0, 0
    ny, nx = a.shape
    for y in range(ny):
        for x in range(nx):
            y2, x2 = (y + lag, x) if axis == "parallel" else (y, x + lag)
            if y2 < ny and x2 < nx:
                total += (a[y2, x2] - a[y, x]) ** 2
                n += 1
    return total / n


def test_structure_function_matches_direct_loop():
    rng = np.random.default_rng(11)
    a = rng.normal(size=(9, 13)) + np.cos(np.arange(13) * 0.7)[None, :]
    for axis in ("serial", "parallel"):
        lags, d = structure_function(a, 6, axis=axis)
        assert_allclose(lags, np.arange(1, 7))
        assert_allclose(d, [_direct_d(a, k, axis) for k in lags], rtol=1e-12)
    # a pure column pattern has no structure along the parallel axis, and a
    # sawtooth of period 2 along rows has D(1) = (2 h)^2, D(2) = 0
    cols = np.tile(np.arange(5.0), (4, 1))
    assert_allclose(structure_function(cols, 3, axis="parallel")[1], 0.0)
    saw = np.tile(np.array([0.3, -0.3] * 4)[:, None], (1, 3))
    assert_allclose(structure_function(saw, 2, axis="parallel")[1], [0.36, 0.0], atol=1e-15)


def test_structure_function_rejects_bad_input():
    with pytest.raises(ValueError, match="2-D"):
        structure_function(np.ones(5), 1, axis="serial")
    with pytest.raises(ValueError, match="axis"):
        structure_function(np.ones((4, 4)), 1, axis="diagonal")
    with pytest.raises(ValueError, match="max_lag"):
        structure_function(np.ones((4, 4)), 4, axis="serial")
    bad = np.ones((4, 4))
    bad[1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        structure_function(bad, 1, axis="serial")


def test_expected_structure_function_matches_monte_carlo():
    # white inputs through a short antisymmetric kernel (like clock jitter)
    kernel = np.array([0.05, -1.2, 1.2, -0.05])
    sigma = 0.3
    rng = np.random.default_rng(5)
    s = rng.normal(0, sigma, 400_000)
    a = np.convolve(s, kernel, mode="valid")
    mc = np.array([np.mean((a[k:] - a[:-k]) ** 2) for k in range(1, 6)])
    lags, d = expected_structure_function(kernel, sigma, 5)
    assert_allclose(d, mc, rtol=0.01)
    # beyond the kernel's length the structure function is flat at 2 var
    assert_allclose(d[-1], 2 * sigma**2 * np.sum(kernel**2))


# -- clock jitter -----------------------------------------------------------

@pytest.fixture(scope="module")
def one_shift():
    delta = 0.3  # um
    out = {}
    for d in (delta, -delta):
        t = block_geometry(P.replace(row_shifts=((0.0, d),)), (0, 1), (-3, 3),
                           edge_samples=4, tol=1e-5)
        out[d] = np.asarray(t["area"]) - 1
    return delta, out


@pytest.mark.slow
def test_one_row_jitter_moves_one_boundary(one_shift):
    delta, dA = one_shift
    up = dA[delta]  # rows -3 .. 2; the displaced pair is on row boundary 0
    # geometry: moving the boundary between rows -1 and 0 up by delta gives
    # row -1 +delta/p and row 0 -delta/p of area, to first order
    dp = delta / P.pixel_pitch
    assert up[2] > 0 > up[3]
    assert_allclose(up[2], -up[3], rtol=0.02)
    assert 0.8 * dp < up[2] < 1.5 * dp
    # rows further away change much less, and the total is conserved
    assert np.max(np.abs(up[[0, 1, 4, 5]])) < 0.1 * up[2]
    assert abs(np.sum(up)) < 0.02 * np.sum(np.abs(up))
    # mirror: the opposite shift gives the row-reversed, sign-flipped pattern
    # (reflection y -> -y about row boundary 0 maps row j to row -1 - j)
    assert_allclose(dA[-delta], up[::-1], atol=3e-5)


@pytest.mark.slow
def test_zero_jitter_and_zero_variation_give_the_uniform_grid():
    a, shifts = jitter_area_map(P, sigma=0.0, shape=(2, 3), seed=3, edge_samples=4, tol=1e-5)
    assert np.all(shifts == 0) and a.shape == (2, 3)
    assert_allclose(a, 1.0, atol=1e-4)
    c, deltas = channel_stop_area_map(P, sigma=0.0, shape=(2, 2), seed=3, edge_samples=4,
                                      tol=1e-5)
    assert np.all(deltas == 0)
    assert_allclose(c, 1.0, atol=1e-4)


# -- bamboo -----------------------------------------------------------------

@pytest.mark.slow
def test_bamboo_conserves_area_and_is_mirror_symmetric():
    t = bamboo(P, amplitudes=(0.0, 1.0), period=6, n_periods=3, edge_samples=4, tol=1e-4)
    flat = np.asarray(t[t["setting"] == 0.0]["area"])
    assert_allclose(flat, 1.0, atol=3e-4)
    area = np.asarray(t[t["setting"] == 1.0]["area"])
    # the boundaries are only rearranged: a full period holds `period` px^2
    assert abs(area.sum() - area.size) < 0.02 * np.sum(np.abs(area - 1))
    # cos(2 pi b / P) is even about boundary 0: column i mirrors column -1 - i,
    # i.e. P - 1 - i in the period
    assert_allclose(area, area[::-1], atol=5e-4)
    # a weaker stop (a > 0 against xi_CS < 0) widens the columns beside it
    assert area[0] > 1.01 and area[len(area) // 2] < 0.99
    s = bamboo_summary(t)["a=1"]
    assert_allclose(s["area_peak_to_peak"], np.ptp(area))


# -- tearing onset ----------------------------------------------------------

@pytest.fixture(scope="module")
def tearing():
    return tearing_onset(P, weakening=(0.0, 1.0), i_range=(-2, 2), j_range=(-2, 2),
                         edge_samples=4, tol=1e-4)


@pytest.mark.slow
def test_tearing_limits_and_mirror(tearing):
    none = tearing[tearing["setting"] == 0.0]
    assert_allclose(np.asarray(none["area"]), 1.0, atol=3e-4)
    full = tearing[tearing["setting"] == 1.0]
    area = np.asarray(full["area"]).reshape(4, 4)  # [j, i], i = -2 .. 1
    dx = np.asarray(full["dx"]).reshape(4, 4)
    # mirror about the weakened stop (column boundary 0): i -> -1 - i
    assert_allclose(area, area[:, ::-1], atol=1e-3)
    assert_allclose(dx, -dx[:, ::-1], atol=1e-3)
    # below the truncation the stop is intact: two rows down the distortion is
    # a fraction of the one above it, where the columns beside the missing
    # stop grow
    assert abs(area[0, 2] - 1) < 0.25 * abs(area[3, 2] - 1)
    assert area[3, 2] > 1.1 and area[3, 1] > 1.1
    summ = tearing_summary(tearing)
    assert summ["f=0"]["max_abs_dA"] < 3e-4 < summ["f=1"]["max_abs_dA"]


def test_truncated_stop_far_inside_equals_uniform_override():
    # far beyond its end, the truncated weakening acts like the same change
    # applied along the whole column boundary (a plain LineDipole override)
    f = 0.5
    trunc = P.replace(truncations=((0.0, 0.0, 1.0, -f * P.xi_cs),))
    unif = P.replace(column_overrides=((0.0, -f * P.xi_cs),))
    far = block_geometry(trunc, (-1, 1), (30, 31), edge_samples=4, tol=1e-4)
    ref = block_geometry(unif, (-1, 1), (0, 1), edge_samples=4, tol=1e-4)
    assert_allclose(np.asarray(far["area"]), np.asarray(ref["area"]), atol=2e-3)
    before = block_geometry(trunc, (-1, 1), (-31, -30), edge_samples=4, tol=1e-4)
    assert_allclose(np.asarray(before["area"]), 1.0, atol=2e-3)


def test_tearing_rejects_bad_fraction():
    with pytest.raises(ValueError, match="weakening"):
        tearing_onset(P, weakening=(1.5,))
