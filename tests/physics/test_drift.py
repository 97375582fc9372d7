"""Tests of lsst_bfdrift.physics.drift against independent integrators and limits."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.integrate import solve_ivp

from lsst_bfdrift.physics.absorption import absorption_length
from lsst_bfdrift.physics.drift import conversion_height, drift_lines, landing_pixels
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters


def _reference_endpoint(model, x, y, z0, z_stop):
    """Drift line by scipy's DOP853 at tight tolerance, ended by an event."""
    def rhs(s, r):
        e = np.array(model.field(r[0], r[1], r[2]), float).ravel()
        return -e / np.linalg.norm(e)

    def hit(s, r):
        return r[2] - z_stop
    hit.terminal, hit.direction = True, -1
    sol = solve_ivp(rhs, (0, 1000), [x, y, z0], rtol=1e-11, atol=1e-11, events=hit,
                    method="DOP853")
    return sol.y_events[0][0]


def test_backdrop_only_lines_are_straight(rng):
    m = SensorModel(SensorParameters.paper(xi_cs=0.0, xi_ck=0.0))
    x, y = rng.uniform(-30, 30, 40), rng.uniform(-30, 30, 40)
    res = drift_lines(m, x, y)
    assert_allclose(res.x, x, atol=1e-12)
    assert_allclose(res.y, y, atol=1e-12)
    assert_allclose(res.z, m.params.z_collect)
    assert res.finished.all()


def test_matches_dop853_with_aggressor():
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 1e4})
    starts = [(0.3, 5.0), (-0.2, 3.0), (9.7, 9.9), (10.02, -0.03), (4.0, 4.5), (15.0, 2.0)]
    res = drift_lines(m, [s[0] for s in starts], [s[1] for s in starts])
    for k, (x, y) in enumerate(starts):
        xe, ye, _ = _reference_endpoint(m, x, y, 100.0, m.params.z_collect)
        # 1e-4 um = 1e-5 px, ten times below the default bisection tolerance
        assert_allclose([res.x[k], res.y[k]], [xe, ye], atol=1e-4)


def test_conversion_height_below_window():
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 1e4})
    xe, ye, _ = _reference_endpoint(m, 2.0, 7.0, 60.0, m.params.z_collect)
    res = drift_lines(m, 2.0, 7.0, 60.0)
    assert_allclose([res.x, res.y], [xe, ye], atol=1e-4)


def test_lines_avoid_barriers_and_aggressor():
    m = SensorModel(SensorParameters.paper()).with_charge({(0, 0): 1e4})
    # lines starting just inside the aggressor pixel near its left edge are
    # pushed out of it by the collected charge
    i, j = landing_pixels(m, [0.05, 9.95], [5.0, 5.0])
    assert list(i) == [-1, 1] and list(j) == [0, 0]
    # without the charge the same lines are held by the channel stops
    i, j = landing_pixels(SensorModel(SensorParameters.paper()), [0.05, 9.95], [5.0, 5.0])
    assert list(i) == [0, 0]


def test_shape_is_kept():
    m = SensorModel(SensorParameters.paper())
    res = drift_lines(m, np.full((3, 4), 2.0), np.linspace(1, 9, 4))
    assert res.x.shape == (3, 4) and res.steps.shape == (3, 4)


@pytest.mark.parametrize("kw, match", [
    (dict(x0=np.nan, y0=1.0), "finite"),
    (dict(x0=1.0, y0=1.0, z0=150.0), "conversion heights"),
    (dict(x0=1.0, y0=1.0, z0=0.5), "conversion heights"),
])
def test_bad_starts(kw, match):
    with pytest.raises(ValueError, match=match):
        drift_lines(SensorModel(SensorParameters.paper()), **kw)


def test_max_steps_flags_unfinished():
    res = drift_lines(SensorModel(SensorParameters.paper()), [1.0, 2.0], [1.0, 2.0], max_steps=3)
    assert not res.finished.any()
    assert (res.z > SensorModel(SensorParameters.paper()).params.z_collect).all()


def test_absorption_length_from_galsim_table():
    import os

    import galsim
    table = np.loadtxt(os.path.join(galsim.meta_data.share_dir, "sensors", "abs_length.dat"),
                       skiprows=1)
    k = len(table) // 2
    assert_allclose(absorption_length(table[k, 0]), table[k, 1])
    assert absorption_length(900.0) > absorption_length(400.0)
    with pytest.raises(ValueError, match="wavelength"):
        absorption_length(5000.0)


def test_conversion_height(rng):
    L = absorption_length(700.0)
    assert_allclose(conversion_height(700.0, 100.0), 100.0 - L)
    z = conversion_height(700.0, 100.0, rng=rng, size=20000, z_stop=2.0)
    assert z.min() >= 2.0 and z.max() <= 100.0
    assert_allclose(100.0 - z.mean(), L, rtol=0.05)


def test_compiled_engine_equals_numpy_engine(rng):
    """Same algorithm, compiled line by line: identical to rounding, every term kind."""
    from lsst_bfdrift.physics.drift import compile_model
    m = SensorModel(SensorParameters.paper(bloom_stop=2, edge=-3, xi_guard=2.0,
                                     truncations=[(1, 0.5, 1, 3.0)], row_overrides=[(1, 1.0)],
                                     row_shifts=[(2, 0.5)]),
                    charge={(0, 0): 1e4, (1, 2): 5e3})
    assert compile_model(m) is not None
    x, y = rng.uniform(-20, 30, 200), rng.uniform(-20, 30, 200)
    a = drift_lines(m, x, y, engine="numpy")
    b = drift_lines(m, x, y, engine="compiled")
    assert_allclose(b.x, a.x, atol=1e-10)
    assert_allclose(b.y, a.y, atol=1e-10)
    assert np.array_equal(a.steps, b.steps) and np.array_equal(a.stalled, b.stalled)


def test_unknown_terms_fall_back_to_numpy():
    from lsst_bfdrift.physics.drift import compile_model
    from lsst_bfdrift.physics.fields import FieldTerm

    class Zero(FieldTerm):
        def field(self, x, y, z):
            z0 = np.zeros(np.broadcast(x, y, z).shape)
            return z0, z0.copy(), z0.copy()
    m = SensorModel(terms=[Zero()])
    assert compile_model(m) is None
    res = drift_lines(m, [3.0], [4.0])  # auto -> numpy
    assert res.finished.all()
    with pytest.raises(ValueError, match="compiled engine"):
        drift_lines(m, [3.0], [4.0], engine="compiled")
    with pytest.raises(ValueError, match="engine"):
        drift_lines(m, [3.0], [4.0], engine="gpu")
