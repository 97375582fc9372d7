"""Tests of lsst_bfdrift.superpose: linear superposition, tiling, moment maps."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.geometry import pixel_polygons, polygon_moments
from lsst_bfdrift.superpose import check_charge_image, moment_maps, superpose_boundaries


def _direct_displacements(t, charge):
    """Reference: loop over aggressors and add each shifted, scaled template."""
    ny, nx = charge.shape
    c = t.center
    corner = np.zeros((ny + 1, nx + 1, 2))
    v = np.zeros((ny, nx + 1, t.edge_samples))
    h = np.zeros((ny + 1, nx, t.edge_samples))
    for ja, ia in zip(*np.nonzero(charge)):
        f = charge[ja, ia] / t.charge
        for J in range(ny + 1):
            for I in range(nx + 1):
                a, b = J - ja + c, I - ia + c
                if 0 <= a <= 2 * c + 1 and 0 <= b <= 2 * c + 1:
                    corner[J, I] += f * t.corner_d[a, b]
                if J < ny and 0 <= a <= 2 * c and 0 <= b <= 2 * c + 1:
                    v[J, I] += f * t.vedge_d[a, b]
                if I < nx and 0 <= a <= 2 * c + 1 and 0 <= b <= 2 * c:
                    h[J, I] += f * t.hedge_d[a, b]
    return corner, v, h


def test_fft_superposition_equals_direct_sum(small_template, rng):
    charge = np.zeros((9, 11))
    for _ in range(6):
        charge[rng.integers(0, 9), rng.integers(0, 11)] += rng.uniform(-2e4, 5e4)
    g = superpose_boundaries(small_template, charge)
    nom = g.nominal()
    corner, v, h = _direct_displacements(small_template, charge)
    assert_allclose(g.corners - nom.corners, corner, atol=1e-12)
    assert_allclose(g.vedge - nom.vedge, v, atol=1e-12)
    assert_allclose(g.hedge - nom.hedge, h, atol=1e-12)


def test_polygons_tile_the_plane(small_template, rng):
    c = small_template.center
    charge = np.zeros((40, 50))
    charge[c + 1:-c - 1, c + 1:-c - 1] = rng.poisson(4e4, (40 - 2 * c - 2, 50 - 2 * c - 2))
    maps = moment_maps(small_template, charge, strip=7)
    # outer boundary untouched (charge too far from it): areas sum to the count
    assert abs(maps.area.sum() - charge.size) < 1e-9
    assert maps.area.min() < 0.99


def test_isolated_aggressor_reproduces_template(small_template):
    t = small_template
    charge = np.zeros((15, 15))
    charge[7, 7] = t.charge
    maps = moment_maps(t, charge)
    m = t.moments()
    c = t.center
    sl = slice(7 - c, 7 + c + 1)
    assert_allclose(maps.area[sl, sl], m.area, rtol=1e-12)
    jj, ii = np.mgrid[-c:c + 1, -c:c + 1]
    assert_allclose(maps.dx[sl, sl], m.x - ii, atol=1e-12)
    assert_allclose(maps.e1[sl, sl], m.e1, atol=1e-10)


def test_moment_maps_equal_polygon_moments_for_any_strip(small_template, rng):
    charge = rng.uniform(0, 8e4, (23, 17))
    g = superpose_boundaries(small_template, charge)
    x, y = pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions)
    ref = polygon_moments(x, y)
    jj, ii = np.mgrid[0:23, 0:17]
    for strip in (1, 5, 64):
        maps = moment_maps(small_template, charge, strip=strip)
        assert_allclose(maps.area, ref.area, rtol=1e-12)
        assert_allclose(maps.dx, ref.x - ii, atol=1e-11)
        assert_allclose(maps.dy, ref.y - jj, atol=1e-11)
        assert_allclose(maps.ixx, ref.ixx, rtol=1e-9)
        assert_allclose(maps.e2, ref.e2, atol=1e-9)


def test_undistorted_for_zero_charge(small_template):
    maps = moment_maps(small_template, np.zeros((6, 7)))
    assert_allclose(maps.area, 1.0, rtol=1e-14)
    assert_allclose(maps.ixx, 1.0 / 12.0, rtol=1e-12)
    assert_allclose([maps.dx, maps.dy, maps.e1, maps.e2], 0.0, atol=1e-14)


def test_input_is_not_modified_and_mask_removes_aggressors(small_template):
    charge = np.zeros((12, 12))
    charge[5, 5] = 3e4
    charge[2, 9] = np.nan
    mask = np.isnan(charge)
    before = charge.copy()
    maps = moment_maps(small_template, charge, mask=mask)
    assert np.array_equal(np.isnan(charge), np.isnan(before))
    assert np.array_equal(charge[~mask], before[~mask])
    ref = moment_maps(small_template, np.where(mask, 0.0, charge))
    assert_allclose(maps.area, ref.area, rtol=0, atol=0)


@pytest.mark.parametrize("charge, kw, match", [
    (np.full((4, 4), np.nan), {}, "non-finite"),
    (np.zeros(5), {}, "2-d"),
    (np.zeros((0, 3)), {}, "empty"),
    (np.zeros((4, 4)), {"mask": np.zeros((3, 3), bool)}, "mask shape"),
])
def test_bad_images(charge, kw, match):
    with pytest.raises(ValueError, match=match):
        check_charge_image(charge, **kw)


def test_compiled_moments_with_tangential_displacements(rng):
    """The GalSim import carries tangential displacements: kernel vs numpy."""
    from lsst_bfdrift.template import DistortionTemplate
    t = DistortionTemplate.from_galsim("lsst_itl_50_8")
    charge = rng.uniform(0, 2e5, (14, 12))
    g = superpose_boundaries(t, charge)
    assert g.vedge_t is not None
    x, y = pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions, vedge_t=g.vedge_t,
                          hedge_t=g.hedge_t)
    ref = polygon_moments(x, y)
    maps = moment_maps(t, charge, strip=5)
    jj, ii = np.mgrid[0:14, 0:12]
    assert_allclose(maps.area, ref.area, rtol=1e-12)
    assert_allclose(maps.dx, ref.x - ii, atol=1e-11)
    assert_allclose(maps.ixy, ref.ixy, atol=1e-11)
