"""Tests of lsst_bfdrift.simulation.galsim_twins (paired SiliconSensor images, in-sensor sky)."""

import galsim
import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.simulation.galsim_twins import accumulate_twins, shoot_stamp_photons, sky_box
from lsst_bfdrift.simulation.skysim import simulate_star_field

SENSOR = "lsst_itl_50_8"


def _ring_means(img, inner):
    """Mean of the box's outermost pixel ring and of the ring just outside it."""
    a, b = inner.start, inner.stop
    box = np.zeros(img.shape, bool)
    box[a:b, a:b] = True
    shrunk = np.zeros(img.shape, bool)
    shrunk[a + 1:b - 1, a + 1:b - 1] = True
    grown = np.zeros(img.shape, bool)
    grown[a - 1:b + 1, a - 1:b + 1] = True
    return img[box & ~shrunk].mean(), img[grown & ~box].mean(), (box & ~shrunk).sum()


def test_sky_box_geometry():
    lo, hi, inner = sky_box(41, 8)
    assert (lo, hi) == (21 - 8 - 0.5 - 3, 21 + 8 + 0.5 + 3)
    assert (inner.start, inner.stop) == (21 - 1 - 8 - 3, 21 + 8 + 3)
    assert inner.stop - inner.start == hi - lo  # one index per pixel of the box
    lo, hi, inner = sky_box(25, None)
    assert (inner.start, inner.stop) == (0, 28)  # clipped at 0: the whole stamp
    with pytest.raises(ValueError, match="sky_radius"):
        sky_box(25, -1)


def test_fed_box_has_uniform_sky_up_to_its_edge():
    """Sky photons only (no star): the sky collected through the sensor is the
    input level everywhere in the box with feed; without feed diffusion
    empties the box's edge pixels (the ring the feed removes)."""
    sky, stamp = 1500.0, 21
    lo, hi, inner = sky_box(stamp, 3)
    empty = np.empty(0)
    kw = dict(sensor=SENSOR, seed=5, stamp=stamp, pixel_scale=0.2, sky=sky, box=(lo, hi))
    (fed,), n_fed = accumulate_twins(empty, empty, empty, (1e-9,), feed=3,
                                     rng=np.random.default_rng(1), **kw)
    (bare,), n_bare = accumulate_twins(empty, empty, empty, (1e-9,),
                                       rng=np.random.default_rng(1), **kw)
    edge, out, n_edge = _ring_means(fed, inner)
    assert abs(edge - sky) < 5 * np.sqrt(sky / n_edge)  # Poisson error of the mean
    assert out == 0.0  # photons landing outside the box are dropped with feed
    n_box = (hi - lo) ** 2
    assert abs(fed.sum() - sky * n_box) < 5 * np.sqrt(sky * n_box)
    edge_bare, out_bare, _ = _ring_means(bare, inner)
    assert edge_bare < sky - 20 * np.sqrt(sky / n_edge)  # diffusion loss, unbalanced
    assert out_bare > 20 * np.sqrt(sky / n_edge)  # ... landing just outside
    assert n_fed > n_bare  # the feed photons


@pytest.mark.slow
def test_twins_share_photons_and_differ_only_by_bf():
    """Both strengths get the same photons: equal totals; the BF twin moved charge."""
    prof = galsim.Moffat(beta=3.5, fwhm=0.8).withFlux(3e5)
    x, y, f = shoot_stamp_photons(prof, 21, pixel_scale=0.2, seed=4)
    assert_allclose(f.sum(), 3e5, rtol=5e-3)
    assert_allclose([x.mean(), y.mean()], [11.0, 11.0], atol=0.02)  # true centre of 21 px
    lo, hi, inner = sky_box(21, 4)
    for feed in (0, 3):
        (bf, truth), n_sky = accumulate_twins(
            x, y, f, (1.0, 1e-9), sensor=SENSOR, seed=9, stamp=21, pixel_scale=0.2, sky=200.0,
            box=(lo, hi), feed=feed, rng=np.random.default_rng(2))
        assert n_sky > 0
        assert_allclose(bf.sum(), truth.sum(), rtol=1e-4)  # only off-stamp losses differ
        assert np.abs(bf - truth).max() > 20  # BF moved charge near the core
        c = 10  # central pixel: BF pushes charge out of it
        assert bf[c, c] < truth[c, c]


def test_sky_mask_drops_already_collected_sky():
    empty = np.empty(0)
    lo, hi, inner = sky_box(15, 2)
    mask = np.ones((15, 15), bool)
    mask[:, :7] = False  # left half collected already
    (img,), n_sky = accumulate_twins(empty, empty, empty, (1e-9,), sensor=SENSOR, seed=1,
                                     stamp=15, pixel_scale=0.2, sky=400.0, box=(lo, hi),
                                     sky_mask=mask, rng=np.random.default_rng(3))
    width = hi - lo
    kept = width * (hi - 7.5)  # box area right of pixel index 7's left edge (x > 7.5)
    assert abs(n_sky - 400.0 * kept) < 5 * np.sqrt(400.0 * kept)
    assert img[:, :5].sum() < 0.01 * img.sum()  # only diffusion reaches two pixels in


def test_bad_input_is_rejected():
    e = np.empty(0)
    kw = dict(sensor=SENSOR, seed=1, stamp=11, pixel_scale=0.2, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="strengths must be positive"):
        accumulate_twins(e, e, e, (1.0, 0.0), **kw)
    with pytest.raises(ValueError, match="box"):
        accumulate_twins(e, e, e, (1.0,), sky=10.0, **kw)
    with pytest.raises(ValueError, match="1-d arrays"):
        accumulate_twins(np.zeros(3), np.zeros(2), np.zeros(3), (1.0,), **kw)
    with pytest.raises(ValueError, match="rng"):
        accumulate_twins(e, e, e, (1.0,), sensor=SENSOR, seed=1, stamp=11, pixel_scale=0.2)
    with pytest.raises(ValueError, match="feed"):
        accumulate_twins(e, e, e, (1.0,), feed=2, **kw)
    with pytest.raises(ValueError, match="sky_mask"):
        accumulate_twins(e, e, e, (1.0,), sky=10.0, box=(2.5, 8.5), sky_mask=np.ones((3, 3)),
                         **kw)
    with pytest.raises(ValueError, match="stamp must be odd"):
        simulate_star_field((64, 64), 1, stamp=30)


@pytest.mark.slow
def test_field_sky_is_level_across_the_boxes_and_stars_do_not_depend_on_it():
    """In a field the sky is the input level inside and just outside each
    star's box (no diffusion ring), and the stars (positions, fluxes) are the
    same with the sky added afterwards."""
    sky = 800.0
    kw = dict(strength=1.0, flux=(1e4, 2e4), sky=sky, read_noise=0.0, seed=6, sky_radius=4,
              updates=100, min_nrecalc=1e4)
    a = simulate_star_field((96, 96), 2, **kw)
    b = simulate_star_field((96, 96), 2, sky_through_sensor=False, **kw)
    for k in ("x", "y", "flux"):
        assert_allclose(a["stars"][k].value, b["stars"][k].value)
    assert not np.array_equal(a["image"], b["image"])
    lo, hi, inner = sky_box(31, 4)
    for x, y in zip(a["stars"]["x"].value, a["stars"]["y"].value):
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        cut = a["image"][iy - 15:iy + 16, ix - 15:ix + 16]
        edge, out, n_edge = _ring_means(cut, inner)
        # Poisson error of the ring means, plus up to ~15 e of the faint star's wings
        # 7-8 px out; the diffusion ring without feed is ~ +-160 e (20 % of the sky)
        for v in (edge, out):
            assert abs(v - sky) < 5 * np.sqrt(sky / n_edge) + 15.0


def test_galsim_acoeffs_is_the_linear_response():
    """GalSim's a-matrix: the sum rule holds inside GalSim's stamp (its
    outer boundary does not move; the quadrant sum is exact to the stamp's
    small asymmetry, 0.3 % of a00), the parallel neighbour is the stronger,
    and the two-charge formula equals a small-charge finite difference."""
    import galsim

    from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs

    a = galsim_acoeffs("lsst_itl_50_8", 5)
    mult = np.ones_like(a)
    mult[1:] *= 2
    mult[:, 1:] *= 2
    assert abs((a * mult).sum()) < 5e-3 * abs(a[0, 0])
    assert a[0, 0] < 0 and a[0, 1] > a[1, 0] > 0
    sim = galsim.SiliconSensor("lsst_itl_50_8", diffusion_factor=0.0)
    img = galsim.ImageD(31, 31, scale=0.2)
    img.setCenter(0, 0)
    img[0, 0] = 10.0
    small = (sim.calculate_pixel_areas(img).array[15, 15:18] - 1) / 10.0
    np.testing.assert_allclose(a[:3, 0], small, rtol=1e-4)
    with pytest.raises(ValueError, match="max_lag"):
        galsim_acoeffs("lsst_itl_50_8", -1)


def test_one_openmp_thread_during_the_draw_and_restored_after(monkeypatch):
    """The accumulation runs on one OpenMP thread (GalSim's threads spin on a
    busy machine) and leaves the caller's thread count as it was, after an
    error too. Consistency: the same photons give images equal to 1e-9 e
    whatever the caller's thread count (only the pixel sums' rounding may
    differ), holding the star's flux."""
    x, y, f = shoot_stamp_photons(galsim.Gaussian(sigma=0.3, flux=2e4), 15, pixel_scale=0.2,
                                  seed=4)
    kw = dict(sensor=SENSOR, seed=2, stamp=15, pixel_scale=0.2, updates=50)
    seen = []
    accumulate = galsim.SiliconSensor.accumulate

    def spy(self, *args, **kwargs):
        seen.append(galsim.utilities.get_omp_threads())
        return accumulate(self, *args, **kwargs)

    monkeypatch.setattr(galsim.SiliconSensor, "accumulate", spy)
    before = galsim.utilities.get_omp_threads()
    try:
        images = []
        for n in (2, 1):
            expect = galsim.utilities.set_omp_threads(n)  # what OpenMP grants
            (img,), _ = accumulate_twins(x, y, f, (1.0,), rng=np.random.default_rng(5), **kw)
            assert galsim.utilities.get_omp_threads() == expect
            images.append(img)
        assert seen == [1, 1]  # GalSim accumulated on one thread both times
        assert_allclose(images[0], images[1], rtol=0, atol=1e-9)
        assert images[0].sum() == pytest.approx(2e4, rel=0.05)
        expect = galsim.utilities.set_omp_threads(2)
        with pytest.raises(OSError, match="no_such_sensor_file"):
            accumulate_twins(x, y, f, (1.0,), rng=np.random.default_rng(5),
                             **{**kw, "sensor": "no_such_sensor_file"})
        assert galsim.utilities.get_omp_threads() == expect
    finally:
        galsim.utilities.set_omp_threads(before)
