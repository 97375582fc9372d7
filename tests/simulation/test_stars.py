"""Tests of lsst_bfdrift.simulation.stars: photon assignment and star accumulation."""

import galsim
import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.physics.polygons import points_in_polygons, pixel_polygons
from lsst_bfdrift.simulation._star_kernels import NEIGHBOUR_ORDER
from lsst_bfdrift.simulation.stars import StarSimulation, image_moments, shoot_photons, simulate_star
from lsst_bfdrift.geometry.superpose import superpose_boundaries


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


@pytest.fixture(scope="module")
def itl_template():
    """GalSim's lsst_itl_50_8 (9 x 9, 8 tan-spaced samples, tangential shifts)."""
    return import_galsim_sensor("lsst_itl_50_8")


def _reference_assignment(px, py, grid):
    """First pixel, in NEIGHBOUR_ORDER, whose polygon contains the point by the
    numpy crossing test on polygons built by pixel_polygons."""
    x, y = pixel_polygons(grid.corners, grid.vedge, grid.hedge, grid.fractions,
                          vedge_t=grid.vedge_t, hedge_t=grid.hedge_t)
    ny, nx = x.shape[:2]
    ii = np.full(px.size, -1)
    jj = np.full(px.size, -1)
    hits = np.zeros(px.size, int)
    ci, cj = np.floor(px + 0.5).astype(int), np.floor(py + 0.5).astype(int)
    for di, dj in NEIGHBOUR_ORDER[::-1]:  # reversed: the first in order is written last
        ti, tj = ci + di, cj + dj
        ok = (ti >= 0) & (ti < nx) & (tj >= 0) & (tj < ny)
        inside = np.zeros(px.size, bool)
        inside[ok] = points_in_polygons(px[ok], py[ok], x[tj[ok], ti[ok]], y[tj[ok], ti[ok]])
        ii[inside], jj[inside] = ti[inside], tj[inside]
        hits += inside
    return ii, jj, hits


def _points_near_edges(grid, rng, n):
    """Points within 1e-12..1e-6 px of random polygon edges, on both sides."""
    x, y = pixel_polygons(grid.corners, grid.vedge, grid.hedge, grid.fractions,
                          vedge_t=grid.vedge_t, hedge_t=grid.hedge_t)
    ny, nx, nv = x.shape
    j, i, a = rng.integers(0, ny, n), rng.integers(0, nx, n), rng.integers(0, nv, n)
    b = (a + 1) % nv
    xa, ya, xb, yb = x[j, i, a], y[j, i, a], x[j, i, b], y[j, i, b]
    t = rng.uniform(0, 1, n)
    length = np.hypot(xb - xa, yb - ya)
    off = rng.choice([-1, 1], n) * 10.0 ** rng.uniform(-12, -6, n)
    return (xa + t * (xb - xa) - off * (yb - ya) / length,
            ya + t * (yb - ya) + off * (xb - xa) / length)


@pytest.mark.parametrize("which", ["small", "itl"])
def test_assignment_matches_polygon_reference(which, small_template, itl_template, rng):
    tpl = small_template if which == "small" else itl_template
    n = 15
    sim = StarSimulation(tpl, stamp_size=n)
    q = np.zeros((n, n))
    q[7, 7], q[5, 9], q[10, 4] = np.array([3.0, 1.5, 0.8]) * tpl.charge  # strong, not folded
    sim.reset(q)
    grid = superpose_boundaries(tpl, q)
    ex, ey = _points_near_edges(grid, rng, 20000)
    px = np.concatenate([rng.uniform(-1.0, n, 40000), ex])
    py = np.concatenate([rng.uniform(-1.0, n, 40000), ey])
    ii, jj = sim.assign(px, py)
    ri, rj, hits = _reference_assignment(px, py, grid)
    assert_array_equal(ii, ri)
    assert_array_equal(jj, rj)
    assert (hits <= 1).mean() > 0.9999  # shared boundaries tile: overlaps only at rounding
    assert ((ii >= 0) & (ii != np.floor(px + 0.5))).sum() > 100  # moved boundaries exercised
    assert (ii < 0).sum() > 100  # points outside the stamp exercised


@pytest.mark.parametrize("which", ["small", "itl"])
def test_incremental_boundaries_equal_fft_superposition(which, small_template, itl_template):
    tpl = small_template if which == "small" else itl_template
    n = 21
    sim = StarSimulation(tpl, stamp_size=n, update_every=700)
    for seed in range(3):  # several add() calls, batches straddling the calls
        px, py = shoot_photons(galsim.Gaussian(fwhm=0.7), 60000, seed=seed)
        sim.add(px + 10.25 + seed, py + 9.75)
    assert sim.image.sum() + sim.lost == 180000
    assert sim.image.sum() > 170000
    g = sim.boundaries()
    ref = superpose_boundaries(tpl, sim.image)
    nom = ref.nominal()
    assert np.abs(ref.corners - nom.corners).max() > 1e-3  # boundaries really moved
    assert_allclose(g.corners, ref.corners, rtol=0, atol=1e-10)
    assert_allclose(g.vedge, ref.vedge, rtol=0, atol=1e-10)
    assert_allclose(g.hedge, ref.hedge, rtol=0, atol=1e-10)
    if which == "itl":
        assert_allclose(g.vedge_t, ref.vedge_t, rtol=0, atol=1e-10)
        assert_allclose(g.hedge_t, ref.hedge_t, rtol=0, atol=1e-10)
    # the inner boxes used by the fast path followed the moving boundaries
    rng = np.random.default_rng(11)
    ex, ey = _points_near_edges(g, rng, 5000)
    px = np.concatenate([rng.uniform(5, 16, 20000), ex])
    py = np.concatenate([rng.uniform(5, 16, 20000), ey])
    ii, jj = sim.assign(px, py)
    ri, rj, _ = _reference_assignment(px, py, g)
    assert_array_equal(ii, ri)
    assert_array_equal(jj, rj)


def test_accumulation_assigns_with_current_boundaries(itl_template):
    """One photon per batch: each lands where the boundaries of all earlier
    photons put it (replayed with a full FFT superposition per photon)."""
    n = 9
    sim = StarSimulation(itl_template, stamp_size=n, update_every=1)
    rng = np.random.default_rng(5)
    sim.reset(np.where(np.hypot(*np.mgrid[-4:5, -4:5]) < 2, 2e5, 0.0))
    q = sim.image.copy()
    px, py = rng.uniform(2.5, 5.5, 300), rng.uniform(2.5, 5.5, 300)
    sim.add(px, py)
    for k in range(px.size):
        g = superpose_boundaries(itl_template, q)
        ri, rj, _ = _reference_assignment(px[k:k + 1], py[k:k + 1], g)
        q[rj[0], ri[0]] += 1.0
    assert_allclose(sim.image, q, rtol=0, atol=0)


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


def test_bad_photons_and_charge(small_template):
    sim = StarSimulation(small_template, stamp_size=5)
    with pytest.raises(ValueError, match="finite"):
        sim.add([1.0, np.nan], [1.0, 2.0])
    with pytest.raises(ValueError, match="same size"):
        sim.assign([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="shape"):
        sim.reset(np.zeros((4, 4)))


@pytest.mark.parametrize("qdist", [3, 4])
def test_galsim_layout_areas_equal_galsim(itl_template, qdist):
    """The 'galsim' layout rebuilds GalSim's own pixel polygons: its areas
    equal galsim.SiliconSensor.calculate_pixel_areas (GalSim stores float32)."""
    from lsst_bfdrift.templates.galsim_rules import layout_areas
    n = 21
    jj, ii = np.mgrid[:n, :n]
    q = np.round(2e5 * np.exp(-0.5 * ((ii - 10.3) ** 2 + (jj - 9.8) ** 2) / 1.5 ** 2))
    ref = galsim.SiliconSensor("lsst_itl_50_8", qdist=qdist).calculate_pixel_areas(
        galsim.ImageD(q.copy())).array
    sim = StarSimulation(itl_template, stamp_size=n, layout="galsim", qdist=qdist)
    sim.reset(q)
    a = layout_areas(sim._V, sim._H)
    assert_allclose(a, ref, rtol=0, atol=1e-7)
    assert np.abs(ref - 1).max() > 0.05  # strongly distorted
    # the shared (tiling) layout differs from GalSim's at the 1e-4..1e-3 level
    assert np.abs(sim.geometry().area - ref).max() > 1e-4


@pytest.mark.slow
def test_galsim_layout_reproduces_galsim_photon_by_photon():
    """Same photons, same update cadence: the 'galsim' layout with GalSim's
    box rule lands all but a few conversions where galsim.SiliconSensor does;
    the exact polygon rule (galsim_box=False) lands measurably more elsewhere."""
    raw = import_galsim_sensor("lsst_itl_50_8", match="none")
    rng = np.random.default_rng(8)
    img = galsim.ImageD(31, 31, scale=0.2)
    galsim.Gaussian(fwhm=0.7).withFlux(3e5).drawImage(
        img, method="phot", save_photons=True, rng=galsim.BaseDeviate(9),
        offset=tuple(rng.uniform(-0.5, 0.5, 2)))
    x = np.asarray(img.photons.x) + img.true_center.x
    y = np.asarray(img.photons.y) + img.true_center.y
    p = galsim.PhotonArray(x.size)
    p.x, p.y, p.flux = x, y, np.ones(x.size)
    ref = galsim.ImageD(31, 31)
    threads = galsim.utilities.get_omp_threads()
    galsim.utilities.set_omp_threads(1)  # OpenMP on busy shared cores is very slow
    try:
        galsim.SiliconSensor("lsst_itl_50_8", diffusion_factor=0.0, nrecalc=1000,
                             rng=galsim.BaseDeviate(3)).accumulate(p, ref)
    finally:
        galsim.utilities.set_omp_threads(threads)
    moved = {}
    for box in (True, False):
        sim = StarSimulation(raw, stamp_size=31, update_every=1000, layout="galsim", qdist=3,
                             galsim_box=box, seed=1)
        sim.add(x - 1.0, y - 1.0)  # GalSim's pixel i is centred on x = i, ours on i - 1
        moved[box] = np.abs(sim.image - ref.array).sum() / 2
    bf = np.abs(sim.image - sim.nominal_image).sum() / 2
    assert bf > 200  # the brighter-fatter effect moved many conversions
    assert moved[True] <= 5
    assert moved[False] > moved[True] + 4
