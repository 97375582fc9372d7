"""Tests of lsst_bfdrift.physics.boundaries: bisection of edges and corners."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.boundaries import (bisect_boundary, centred_boundaries, locate_corners,
                                             pixel_boundaries, uniform_fractions)
from lsst_bfdrift.physics.drift import drift_lines, landing_pixels
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters

P = 10.0


def _land(model, xpix, ypix):
    """Landing pixel of lines started at image-frame pixel coordinates."""
    return landing_pixels(model, (np.asarray(xpix) + 0.5) * P, (np.asarray(ypix) + 0.5) * P)


def test_backdrop_only_gives_square_pixels():
    m = SensorModel(SensorParameters.paper(xi_cs=0.0, xi_ck=0.0))
    g = pixel_boundaries(m, (-1, 2), (0, 2), edge_samples=3, tol=1e-4)
    nom = g.nominal()
    for a, b in zip(g.displacements(), (0, 0, 0)):
        assert np.abs(a).max() <= 1e-4
    x, y = pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions, i0=-1, j0=0)
    assert_allclose(polygon_moments(x, y).area, 1.0, atol=1e-3)
    assert nom.corners.shape == g.corners.shape


def test_symmetric_model_without_charge_is_square():
    g = pixel_boundaries(SensorModel(SensorParameters.paper()), (0, 2), (0, 1), edge_samples=2, tol=1e-4)
    for d in g.displacements():
        assert np.abs(d).max() <= 1e-4


@pytest.mark.parametrize("axis", ["x", "y"])
def test_edge_is_where_landing_pixel_changes(axis):
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 2e4})
    along = np.array([-0.3, 0.1, 0.35])
    b = bisect_boundary(m, along, 0.5, axis, 0, tol=1e-4)
    assert np.all(np.abs(b - 0.5) > 1e-3)  # the aggressor moved its edge
    for sign, expect in ((-1, 0), (1, 1)):
        pos = b + sign * 2e-4
        if axis == "x":
            i, _ = _land(m, pos, along)
            assert np.all(i == expect)
        else:
            _, j = _land(m, along, pos)
            assert np.all(j == expect)


def test_bracket_is_widened_when_boundary_lies_outside():
    # a 2e4 e aggressor moves its edge by ~0.05 px: far outside a 0.002 px bracket
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 2e4})
    b = bisect_boundary(m, [0.0], 0.5, "x", 0, tol=1e-4, half_width=0.002)
    assert 0.5 - b[0] > 0.01
    i_lo, _ = _land(m, b - 2e-4, 0.0)
    i_hi, _ = _land(m, b + 2e-4, 0.0)
    assert (i_lo[0], i_hi[0]) == (0, 1)



def test_brackets_per_sample_are_widened_each_on_its_own():
    """CORRECTNESS: a bracket per sample, too narrow for some (the 2e4 e
    aggressor moves its edge by ~0.05 px): each finds its boundary, where
    the landing pixel changes, as one wide bracket does."""
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 2e4})
    along = np.array([0.0, 0.0, 0.3, 0.3])
    b = bisect_boundary(m, along, [0.5, 0.49, 0.5, 0.45], "x", 0, tol=1e-4,
                        half_width=[0.002, 0.02, 0.45, 1e-3])
    assert_allclose(b, bisect_boundary(m, along, 0.5, "x", 0, tol=1e-4), rtol=0, atol=2e-4)
    i_lo, _ = _land(m, b - 2e-4, along)
    i_hi, _ = _land(m, b + 2e-4, along)
    assert np.all(i_lo == 0) and np.all(i_hi == 1)
    with pytest.raises(ValueError, match="half_width must be positive"):
        bisect_boundary(m, along, 0.5, "x", 0, half_width=[0.1, 0.0, 0.1, 0.1])



def test_numpy_engine_bisection_agrees_with_the_compiled_one():
    """CONSISTENCY: the bisection's numpy path (drift_lines per step, used for
    models the compiled engine does not know), with brackets per sample and
    one too narrow, finds the boundaries the compiled loop finds, to tol."""
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 3e4})
    along, widths = np.array([-0.3, 0.0, 0.3]), [0.45, 0.002, 0.05]
    fast = bisect_boundary(m, along, 0.5, "x", 0, tol=1e-4, half_width=widths)
    slow = bisect_boundary(m, along, 0.5, "x", 0, tol=1e-4, half_width=widths,
                           drift_kwargs={"engine": "numpy"})
    assert np.abs(fast - 0.5).max() > 1e-2  # moved beyond the narrow bracket
    assert_allclose(slow, fast, rtol=0, atol=1e-4)

def test_edges_traced_from_their_corners_lie_where_the_landing_pixel_changes():
    """CORRECTNESS: the edge samples of a block around an aggressor, started
    from the chord between their corners in narrow brackets: lines started
    3 tol either side of each land in the two pixels it separates."""
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 3e4})
    tol = 1e-5
    g = pixel_boundaries(m, (-1, 1), (0, 1), edge_samples=3, tol=tol)
    ny, nx1, ns = g.vedge.shape
    I = np.broadcast_to(np.arange(-1, 2)[None, :, None], g.vedge.shape)
    yy = np.broadcast_to(g.fractions[None, None, :] - 0.5, g.vedge.shape)
    assert np.abs(g.vedge - (I - 0.5)).max() > 1e-3  # the aggressor moved them
    i_lo, _ = _land(m, g.vedge - 3 * tol, yy)
    i_hi, _ = _land(m, g.vedge + 3 * tol, yy)
    assert np.all(i_lo == I - 1) and np.all(i_hi == I)
    J = np.broadcast_to(np.arange(0, 2)[:, None, None], g.hedge.shape)
    xx = np.broadcast_to(np.arange(-1, 1)[None, :, None] - 0.5 + g.fractions, g.hedge.shape)
    _, j_lo = _land(m, xx, g.hedge - 3 * tol)
    _, j_hi = _land(m, xx, g.hedge + 3 * tol)
    assert np.all(j_lo == J - 1) and np.all(j_hi == J)

def test_unreachable_boundary_raises():
    m = SensorModel(SensorParameters.paper())
    with pytest.raises(RuntimeError, match="no boundary found"):
        bisect_boundary(m, [0.0], 0.5, "x", 5, tol=1e-3, max_half_width=1.0)


def test_corner_separates_four_pixels():
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 3e4})
    cx, cy = locate_corners(m, [0.5, -0.5], [0.5, 0.5], [0, -1], [0, 0], tol=1e-4)
    assert np.all(np.abs(cx - np.array([0.5, -0.5])) > 1e-3)
    # The corner lies on both boundaries: independent 1-d bisections at the
    # corner's own coordinates return it (to the tolerance).
    assert_allclose(bisect_boundary(m, cy, cx, "x", [0, -1], tol=1e-5), cx, atol=2e-4)
    assert_allclose(bisect_boundary(m, cx, cy, "y", [0, 0], tol=1e-5), cy, atol=2e-4)



def test_compiled_bisection_takes_the_steps_of_lines_traced_batch_by_batch():
    """CONSISTENCY: the compiled bisection loop equals the same steps written
    with :func:`drift_lines` (bracket halved by the landing pixel), bit for bit."""
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 3e4})
    along = np.array([-0.45, -0.2, 0.05, 0.3])
    for axis, index in (("x", 0), ("y", -1)):
        guess = 0.5 if axis == "x" else -0.5
        got = bisect_boundary(m, along, guess, axis, index, tol=1e-5)
        lo, hi = np.full(along.size, guess - 0.45), np.full(along.size, guess + 0.45)
        for _ in range(int(np.ceil(np.log2(0.9 / 1e-5)))):
            mid = 0.5 * (lo + hi)
            start = ((mid + 0.5) * P, (along + 0.5) * P)
            res = drift_lines(m, *(start if axis == "x" else start[::-1]), engine="compiled")
            lower = np.floor((res.x if axis == "x" else res.y) / P) <= index
            lo, hi = np.where(lower, mid, lo), np.where(lower, hi, mid)
        assert_allclose(got, 0.5 * (lo + hi), rtol=0, atol=0)
        assert np.all(np.abs(got - guess) > 1e-3)  # the aggressor moved these edges


def test_corners_next_to_an_aggressor_at_a_tight_tolerance():
    """CORRECTNESS (fixed point): corners of the 3 x 3 pixels around a 1e4 e
    aggressor (the bundled template's sensor, at the charge calibrate uses)
    at tol 2e-6 px, where the boundaries bend sharply and the readings either
    side of a corner differ by ~5e-4 px: independent readings with full
    brackets at each corner's own coordinates return it to within 2 tol
    (column) and 3 tol (row)."""
    from lsst_bfdrift.calibration.fit_model import default_start

    m = SensorModel(default_start()).with_charge({(0, 0): 1e4})
    tol, delta = 2e-6, 4e-6
    jj, ii = np.mgrid[0:3, 0:3]
    ci, ri = (ii - 1).ravel(), (jj - 1).ravel()
    x, y = locate_corners(m, ii - 0.5, jj - 0.5, ii - 1, jj - 1, tol=tol)
    assert np.abs(x - (ii - 0.5).ravel()).max() > 1e-3  # the aggressor moved them

    def reading(axis, along, across, index):
        return 0.5 * sum(bisect_boundary(m, along + s, across, axis, index, tol=tol)
                         for s in (-delta, delta))

    assert_allclose(reading("x", y, x, ci), x, rtol=0, atol=2 * tol)
    assert_allclose(reading("y", x, y, ri), y, rtol=0, atol=3 * tol)


def test_corners_converge_read_farther_out_where_a_boundary_jumps():
    """CORRECTNESS (symmetry): around a 1e4 e aggressor at tol 5e-7 px the
    row boundary jumps at the aggressor's corners (by ~5e-4 px), readings
    2 tol either side straddle the jump in turn and the alternation cycles
    (this raised before); read farther out, the corners converge, and the
    mirror-symmetric model gives mirror-image corners, each located on its
    own: in x to 4 tol, in y (along the jump) to within the jump, 1e-3 px
    against the corners' 3.9e-3 px move. Where a boundary jumps, a corner
    is defined to that size only."""
    from lsst_bfdrift.calibration.fit_model import default_start

    m = SensorModel(default_start()).with_charge({(0, 0): 1e4})
    jj, ii = np.mgrid[0:3, 0:3]
    x, y = locate_corners(m, ii - 0.5, jj - 0.5, ii - 1, jj - 1, tol=5e-7)
    x, y = x.reshape(3, 3), y.reshape(3, 3)
    assert abs(y[0, 0] + 0.5) > 3e-3  # moved by the aggressor
    assert_allclose(x[:2, 0], -x[:2, 1], rtol=0, atol=2e-6)  # mirror in x
    assert_allclose(y[0, :2], -y[1, :2], rtol=0, atol=1e-3)  # mirror in y

def test_workers_do_not_change_result():
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 1e4})
    a = pixel_boundaries(m, (0, 2), (0, 1), edge_samples=2, tol=1e-3, workers=1)
    b = pixel_boundaries(m, (0, 2), (0, 1), edge_samples=2, tol=1e-3, workers=2)
    for x, y in zip(a.displacements(), b.displacements()):
        assert_allclose(x, y, atol=0)


def test_bad_arguments():
    with pytest.raises(ValueError, match="empty pixel range"):
        pixel_boundaries(SensorModel(SensorParameters.paper()), (2, 2), (0, 1))
    with pytest.raises(ValueError, match="tol"):
        pixel_boundaries(SensorModel(SensorParameters.paper()), (0, 1), (0, 1), tol=0.5)
    with pytest.raises(ValueError, match="positive integer"):
        uniform_fractions(0)


@pytest.mark.parametrize("spacing", ["uniform", "tan"])
def test_centred_boundaries_of_a_symmetric_model_equal_the_whole_trace(spacing):
    """Correctness (against tracing every pixel, the direct computation): the
    quadrant traced and mirrored gives the boundaries of the whole block, to
    the bit for this model (the bisection is itself symmetric) and in any case
    within the bisection's tolerance; the charge moves them by far more."""
    model = SensorModel(SensorParameters()).with_charge({(0, 0): 2e4})
    assert model.mirror_symmetric
    kw = dict(edge_samples=4, tol=1e-4, spacing=spacing)
    whole = pixel_boundaries(model, (-2, 3), (-2, 3), **kw)
    mirrored = centred_boundaries(model, 2, **kw)
    assert (mirrored.i0, mirrored.j0, mirrored.shape) == (-2, -2, (5, 5))
    for name in ("corners", "vedge", "hedge"):
        assert_allclose(getattr(mirrored, name), getattr(whole, name), rtol=0, atol=1e-4)
    assert max(np.abs(d).max() for d in whole.displacements()) > 20 * 1e-4


def test_centred_boundaries_trace_an_asymmetric_model_whole():
    """Consistency: a bloom stop, a sensor edge, an override or charge beside
    the aggressor breaks the mirror symmetry, and such a model is traced whole
    (the same grid as pixel_boundaries, not a mirrored quadrant)."""
    P = SensorParameters
    for params, charge in ((P(bloom_stop=1.0), {(0, 0): 2e4}), (P(edge=-1.5), {(0, 0): 2e4}),
                           (P(column_overrides=((1, 0.5),)), {(0, 0): 2e4}),
                           (P(), {(0, 0): 2e4, (1, 0): 1e4})):
        assert not SensorModel(params).with_charge(charge).mirror_symmetric
    model = SensorModel(P(bloom_stop=1.0)).with_charge({(0, 0): 2e4})
    kw = dict(edge_samples=3, tol=1e-4)
    whole = pixel_boundaries(model, (-1, 2), (-1, 2), **kw)
    got = centred_boundaries(model, 1, **kw)
    assert_allclose(got.hedge, whole.hedge, rtol=0, atol=0)
    # the bloom stop at row boundary 1 moves the top edges unlike the bottom ones
    assert np.abs(whole.hedge[3] + whole.hedge[0][:, ::-1]).max() > 1e-3
