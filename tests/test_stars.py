"""Tests of lsst_bfdrift.stars: photon assignment and star accumulation."""

import galsim
import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.geometry import points_in_polygons, pixel_polygons
from lsst_bfdrift.stars import StarSimulation, image_moments, shoot_photons, simulate_star
from lsst_bfdrift.superpose import superpose_boundaries


def test_image_moments_of_a_gaussian():
    jj, ii = np.mgrid[:41, :41]
    img = np.exp(-0.5 * (((ii - 20.3) / 2.0) ** 2 + ((jj - 19.6) / 1.5) ** 2))
    m = image_moments(img)
    assert_allclose([m["x"], m["y"], m["ixx"], m["iyy"]], [20.3, 19.6, 4.0, 2.25], rtol=1e-6)
    assert m["e1"] == pytest.approx((4 - 2.25) / 6.25, rel=1e-6)


def test_shoot_photons_matches_psf_width():
    x, y = shoot_photons(galsim.Gaussian(sigma=0.4), 200000, pixel_scale=0.2, seed=3)
    assert np.std(x) == pytest.approx(2.0, rel=0.01)
    assert np.std(y) == pytest.approx(2.0, rel=0.01)


def test_assignment_agrees_with_polygons(small_template, rng):
    sim = StarSimulation(small_template, stamp_size=9, update_every=100000)
    q = np.zeros((9, 9))
    q[4, 4] = 3e5  # strong distortion, polygons visibly moved
    sim.image[:] = q
    sim._refresh()
    px, py = rng.uniform(-0.4, 8.4, 20000), rng.uniform(-0.4, 8.4, 20000)
    ii, jj = sim._assign(px, py)
    g = superpose_boundaries(small_template, q)
    x, y = pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions)
    ok = ii >= 0
    assert ok.mean() > 0.99
    assert points_in_polygons(px[ok], py[ok], x[jj[ok], ii[ok]], y[jj[ok], ii[ok]]).all()
    moved = ok & ((ii != np.floor(px + 0.5)) | (jj != np.floor(py + 0.5)))
    assert moved.sum() > 50  # the test exercises moved boundaries


def test_conservation_and_paired_bf(small_template):
    psf = galsim.Gaussian(fwhm=0.6)
    hist, final = simulate_star(small_template, psf, 50000, stamp_size=25, seed=4,
                                update_every=1000)
    assert final["image"].sum() + final["lost"] == 50000
    assert final["nominal_image"].sum() == pytest.approx(final["image"].sum(), abs=50)
    # brighter-fatter: the recorded star grows with counts relative to its twin
    growth = hist["T"] / hist["T_nominal"] - 1
    assert growth[-1] > 0 and growth[-1] > growth[0]
    assert final["image"][12, 12] < final["nominal_image"][12, 12]
    assert final["maps"].area[12, 12] < 1.0


@pytest.mark.parametrize("kw, match", [
    ({"stamp_size": 2}, "stamp_size"),
    ({"update_every": 0}, "update_every"),
])
def test_bad_arguments(small_template, kw, match):
    with pytest.raises(ValueError, match=match):
        StarSimulation(small_template, **kw)
