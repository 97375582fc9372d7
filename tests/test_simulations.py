"""Tests of lsst_bfdrift.simulations: periodic areas and flat-field statistics."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.simulations import PeriodicAreas, simulate_flats
from lsst_bfdrift.superpose import moment_maps


def test_periodic_areas_equal_moment_maps_of_wrapped_images(small_template, rng):
    t = small_template
    q = rng.poisson(4e4, (3, 6, 7)).astype(float)
    a = PeriodicAreas(t, (6, 7)).areas(q)
    pad = 2 * t.center + 2
    for k in range(3):
        big = np.pad(q[k], pad, mode="wrap")
        ref = moment_maps(t, big).area[pad:-pad, pad:-pad]
        assert_allclose(a[k], ref, atol=1e-13)
        assert abs(a[k].sum() - 42) < 1e-12  # the torus is tiled


def test_poisson_without_bf(small_template):
    """A template with negligible responsivity gives Poisson statistics."""
    weak = small_template.scaled(1e9)  # same displacements for 1e9 x the charge
    tab = simulate_flats(weak, n_images=256, shape=(12, 12), step=2000, n_steps=3, seed=5,
                         max_lag=2)
    sig = 1.0 / np.sqrt(256 * 144)
    last = tab[-1]
    assert last["paper"][0, 0] == pytest.approx(1.0, abs=5 * sig * np.sqrt(2))
    assert np.all(np.abs(last["paper"].ravel()[1:]) < 5 * sig)
    assert last["pairs"][0, 0] / last["mu"] == pytest.approx(1.0, abs=0.05)


def test_bf_covariances_follow_the_template(small_template):
    """To first order C_ij / mu = a_ij mu with a_ij = dlnA_ij / dQ (template)."""
    t = small_template
    tab = simulate_flats(t, n_images=512, shape=(16, 16), step=3000, n_steps=5, seed=11,
                         max_lag=1)
    mu = tab["mu"][-1]
    c = t.center
    a = np.log(t.moments().area) / t.charge  # per electron
    sig = 1.0 / np.sqrt(512 * 256)
    got = tab["paper"][-1]
    assert got[0, 0] < 1 - 0.5 * abs(a[c, c]) * mu  # variance deficit
    for (di, dj) in ((1, 0), (0, 1), (1, 1)):
        assert got[di, dj] == pytest.approx(a[c + dj, c + di] * mu, abs=4 * sig)


@pytest.mark.parametrize("kw, match", [
    ({"n_images": 5}, "n_images"),
    ({"step": -1.0}, "step"),
    ({"n_steps": 0}, "n_steps"),
    ({"shape": (8, 8), "max_lag": 4}, "max_lag"),
])
def test_bad_arguments(small_template, kw, match):
    with pytest.raises(ValueError, match=match):
        simulate_flats(small_template, **kw)
