"""Tests of lsst_bfdrift.catalogs.spots, spot_slopes and spot_series.

Each test says whether it checks against an independent reference (an
analytic Gaussian's known moments, a slope put into the images, the scatter
of noise realisations) or the package's consistency with itself (the drift
forward model on both sides).
"""

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose

from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.catalogs.spot_slopes import (compare_slopes, fit_spot_slope,
                                               predict_spot_slopes, spot_slopes)
from lsst_bfdrift.catalogs.spots import (deweight_moments, find_spots, fixed_weight_moments,
                                         measure_spots, read_spot_images, spot_flag_counts)
from lsst_bfdrift.correction.solvers import recorded_image
from lsst_bfdrift.templates.swept import SweptAreas
from lsst_bfdrift.templates.template import load_default_template


def _gaussian(shape, x0, y0, cov, flux):
    """A Gaussian sampled at pixel centres (its moments are exactly ``cov``)."""
    ny, nx = shape
    jj, ii = np.mgrid[:ny, :nx]
    ci = np.linalg.inv(cov)
    dx, dy = ii - x0, jj - y0
    q = ci[0, 0] * dx * dx + 2 * ci[0, 1] * dx * dy + ci[1, 1] * dy * dy
    return flux * np.exp(-0.5 * q) / (2 * np.pi * np.sqrt(np.linalg.det(cov)))


def _series(seed, *, n_images=5, grid=3, pitch=34, s0=(1.5, 1.4), slope=(0.02, 0.01),
            read_noise=5.0, sky=20.0, fluxes=(2e4, 1e6), margin=17):
    """Spot images whose sigma_x, sigma_y grow linearly with flux (px per 1e5 e)."""
    rng = np.random.default_rng(seed)
    shape = (grid * pitch + 2 * margin,) * 2
    levels = np.geomspace(fluxes[0], fluxes[1], n_images)
    pos = [(margin + pitch * (i + 0.5) + rng.uniform(-.5, .5),
            margin + pitch * (j + 0.5) + rng.uniform(-.5, .5))
           for j in range(grid) for i in range(grid)]
    scale = 1 + 0.05 * rng.normal(size=len(pos))
    images = []
    for f in levels:
        im = np.zeros(shape)
        for (x, y), s in zip(pos, scale):
            sx, sy = s0[0] + slope[0] * f * s / 1e5, s0[1] + slope[1] * f * s / 1e5
            im += _gaussian(shape, x, y, np.diag([sx * sx, sy * sy]), f * s)
        im = rng.poisson(im + sky).astype(float) + rng.normal(0, read_noise, shape)
        images.append(im)
    return images, list(levels / 1e5), np.array(pos)


def _write(path, data, **cards):
    hdr = fits.Header()
    for k, v in cards.items():
        hdr[k] = v
    fits.PrimaryHDU(np.asarray(data, np.float32), header=hdr).writeto(path)
    return str(path)


@pytest.mark.parametrize("cov, weight", [(np.diag([1.5 ** 2, 1.5 ** 2]), 2.2),
                                         (np.array([[2.9, 0.4], [0.4, 1.7]]), 2.5),
                                         (np.array([[1.2, -0.3], [-0.3, 2.2]]), 4.0)])
def test_fixed_weight_moments_of_a_sampled_gaussian_are_exact(cov, weight):
    """Independent reference: a Gaussian sampled at pixel centres times the
    Gaussian weight is a Gaussian, so the deweighted moments are its
    covariance, e1 and e2 follow, and the centroid is its centre."""
    img = _gaussian((45, 45), 22.3, 21.8, cov, 1e5)
    m = fixed_weight_moments(img, weight_sigma=weight, radius=4 * weight + 1, center=(22, 22))
    assert_allclose(m["m"], [cov[0, 0], cov[1, 1], cov[0, 1]], rtol=1e-7, atol=1e-9)
    assert_allclose((m["x"], m["y"]), (22.3, 21.8), atol=1e-7)
    t = cov[0, 0] + cov[1, 1]
    assert_allclose((m["sigma_x"], m["e1"], m["e2"], m["size"]),
                    (np.sqrt(cov[0, 0]), (cov[0, 0] - cov[1, 1]) / t, 2 * cov[0, 1] / t,
                     np.log(t)), rtol=1e-7, atol=1e-9)
    assert_allclose(m["flux"], 1e5, rtol=1e-6)
    # the weighted moments are the product's: (C^-1 + I / w^2)^-1
    mw = np.linalg.inv(np.linalg.inv(cov) + np.eye(2) / weight ** 2)
    assert_allclose(m["mw"], [mw[0, 0], mw[1, 1], mw[0, 1]], rtol=1e-7, atol=1e-9)
    again, jac = deweight_moments(m["mw"], weight)
    assert_allclose(again, m["m"], rtol=1e-12)
    # the Jacobian is the derivative (finite differences)
    h = 1e-6
    for k in range(3):
        step = np.array(m["mw"], float)
        step[k] += h
        assert_allclose((deweight_moments(step, weight)[0] - again) / h, jac[:, k], rtol=1e-4,
                        atol=1e-6)


def test_propagated_errors_match_the_scatter_of_noise_realisations():
    """Independent reference: the standard deviation of each quantity over
    400 Poisson + read-noise realisations of one spot is the propagated error
    (within 15 %)."""
    rng = np.random.default_rng(5)
    cov = np.array([[2.4, 0.3], [0.3, 2.0]])
    truth = _gaussian((31, 31), 15.2, 14.9, cov, 3e4)
    vals, errs = [], []
    for _ in range(400):
        img = rng.poisson(truth + 30.0) - 30.0 + rng.normal(0, 5.0, truth.shape)
        m = fixed_weight_moments(img, weight_sigma=2.3, radius=9.2, center=(15, 15),
                                 variance=np.clip(img, 0, None) + 30.0 + 25.0)
        vals.append([m[k] for k in ("sigma_x", "sigma_y", "size", "e1", "e2", "flux")])
        errs.append([m[f"{k}_err"] for k in ("sigma_x", "sigma_y", "size", "e1", "e2", "flux")])
    assert_allclose(np.std(vals, axis=0), np.median(errs, axis=0), rtol=0.15)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_injected_linear_size_flux_slope_is_recovered_with_honest_errors(seed):
    """Independent reference: spots whose sigma_x and sigma_y grow by 0.02 and
    0.01 px per 1e5 e (sampled Gaussians, Poisson and read noise): the fitted
    slopes match within 3 errors, and e2 (0 by construction) too."""
    images, times, _ = _series(seed)
    ex = read_spot_images(images, exptimes=times)
    res = spot_slopes(measure_spots(ex, find_spots(ex)))
    for name, truth in (("sigma_x", 0.02), ("sigma_y", 0.01), ("e2", 0.0)):
        r = res[name]
        assert abs(r["slope"] - truth) < 3 * r["slope_err"], (name, r["slope"], r["slope_err"])
        assert r["slope_err"] == max(r["err_formal"], r["err_image"], r["err_spot"])
    assert res["sigma_x"]["z"] > 30 and res["n_spots"] == 9 and res["n_images"] == 5


@pytest.mark.parametrize("kind", ["image", "spot"])
def test_errors_see_the_image_to_image_and_spot_to_spot_scatter(kind):
    """Independent reference: a common size change per exposure (a focus
    drift: every spot of an image wider by one random amount, 20 times the
    row noise), or slopes that differ from spot to spot (30 % rms), are not
    averaged down by the number of spots or images: the pulls of 200
    realisations keep a standard deviation near 1, where the formal error
    alone gives several."""
    rng = np.random.default_rng(7)
    n_img, n_spot = 8, 30
    spot = np.repeat(np.arange(n_spot)[None], n_img, 0).ravel()
    image = np.repeat(np.arange(n_img), n_spot)
    flux = np.geomspace(1e4, 1e6, n_img)[image] * (1 + 0.05 * rng.normal(size=spot.size))
    q_err = np.full(spot.size, 1e-4)
    z, z_formal = [], []
    for _ in range(200):
        slope = 1e-3 + (rng.normal(0, 3e-4, n_spot)[spot] if kind == "spot" else 0.0)
        common = rng.normal(0, 2e-3, n_img)[image] if kind == "image" else 0.0
        q = 1.5 + 0.01 * spot / n_spot + slope * flux / 1e5 + common \
            + rng.normal(0, 1e-4, spot.size)
        r = fit_spot_slope(spot, image, flux, q, q_err)
        z.append((r["slope"] - 1e-3) / r["slope_err"])
        z_formal.append((r["slope"] - 1e-3) / r["err_formal"])
        assert r["slope_err"] == r[f"err_{kind}"]
    assert 0.8 < np.std(z) < 1.35 and np.mean(np.abs(z) > 3) < 0.05
    assert np.std(z_formal) > 2


def test_spots_are_found_once_and_matched_across_the_series():
    """Independent reference: the grid positions are the spots' true centres
    (within 0.05 px), and each spot's row in every image is the same spot."""
    images, times, pos = _series(11)
    ex = read_spot_images(images, exptimes=times)
    grid = find_spots(ex)
    assert len(grid) == 9 and not grid.crowded.any()
    d = np.hypot(grid.x[:, None] - pos[None, :, 0], grid.y[:, None] - pos[None, :, 1])
    assert np.all(d.min(axis=1) < 0.05)
    cat = measure_spots(ex, grid)
    for k in range(len(grid)):
        rows = np.asarray(cat["spot"]) == k
        assert np.ptp(cat["x"].value[rows]) < 0.05 and np.ptp(cat["y"].value[rows]) < 0.05
    # the default weight: 1.5 times the median adaptive sigma
    assert_allclose(grid.weight_sigma, 1.5 * grid.adaptive_sigma, rtol=0.01)


def test_prediction_of_the_drift_forward_model_is_self_consistent():
    """Consistency (the package's model on both sides): spots recorded through a
    template by the drift forward model are measured with the slopes that
    predict_spot_slopes gives for that template (within 2 % of the size slope;
    the BF-free model is rebuilt from the measured faint-limit moments), and
    corrected by the Task with that template they keep less than 3 % of it."""
    rng = np.random.default_rng(3)
    tpl = load_default_template()
    side = 31
    pitch, grid = 36, 3
    shape = (pitch * grid + 20,) * 2
    levels = np.geomspace(2e4, 1e6, 5)
    pos = [(10 + pitch * (i + 0.5) + rng.uniform(-.5, .5),
            10 + pitch * (j + 0.5) + rng.uniform(-.5, .5)) for j in range(grid)
           for i in range(grid)]
    swept = SweptAreas(tpl, (side, side))
    cov = np.array([[1.6, 0.1], [0.1, 1.4]])
    images = []
    for f in levels:
        im = np.zeros(shape)
        for x, y in pos:
            ix, iy = int(round(x)), int(round(y))
            unit = _gaussian((side, side), 15 + x - ix, 15 + y - iy, cov, 1.0)
            im[iy - 15:iy + 16, ix - 15:ix + 16] += recorded_image(f * unit, swept)
        images.append(im + rng.normal(0, 1.0, shape))
    series = SpotSeries(images, exptimes=list(levels / 1e5))
    measured = series.fit()
    assert measured["size"]["z"] > 8
    pred = predict_spot_slopes(series.catalog, tpl, measured=measured)
    cmp = compare_slopes(measured, pred)
    for name in ("sigma_x", "sigma_y", "size"):
        assert abs(cmp[name]["ratio"] - 1) < 0.02, (name, cmp[name])
    stamp = series.predict(tpl, model="stamp", measured=measured)
    assert abs(stamp["size"]["slope"] / pred["size"]["slope"] - 1) < 0.02
    # the joint fit's view: corrected with the same template, the same spots
    # (same grid, weight and rows) keep less than 3 % of their size slope
    after = series.slopes(tpl)
    before = series.slopes()
    assert set(after) == {"size", "e1", "e2", "n_stars"} and after["n_stars"] == 45
    assert abs(after["size"][0]) < 0.03 * before["size"][0], (after, before)
    assert abs(after["size"][0]) < 3 * after["size"][1] + 0.01 * before["size"][0]


def test_saturated_and_edge_spots_are_flagged_counted_and_left_out(tmp_path):
    """Bad input: spots at or above SATURATE are flagged saturated, a spot
    cut by the image edge is flagged edge; both are counted (in total and per
    image) and left out of the slopes, which the other spots still give."""
    images, times, pos = _series(21, fluxes=(2e4, 1.5e6))
    cut = [im[:, 28:] for im in images]  # the first column of spots: stamps leave the image
    paths = [_write(tmp_path / f"s{k}.fits", im, EXPTIME=t, BUNIT="electron", SATURATE=3e4)
             for k, (im, t) in enumerate(zip(cut, times))]
    series = SpotSeries(paths)
    counts = spot_flag_counts(series.catalog, per_image=True)
    assert counts["saturated"] > 0 and counts["edge"] == 3 * len(paths)
    assert [c["edge"] for c in counts["images"]] == [3] * len(paths)
    assert counts["images"][-1]["saturated"] == 6 and counts["images"][0]["saturated"] == 0
    cat = series.catalog
    assert not np.any(np.asarray(cat["use"]) & np.asarray(cat["flag_saturated"]))
    peak = cat["peak"].value
    assert np.all(np.asarray(cat["flag_saturated"])[np.isfinite(peak)]
                  == (peak[np.isfinite(peak)] >= 3e4))
    res = series.fit()
    assert res["excluded"]["saturated"] == counts["saturated"]
    assert res["n_spots"] == 6 and res["n_points"] == counts["used"]


def test_bad_inputs_are_clear_errors(tmp_path):
    """Bad input: a file in ADU without a gain (the message names BUNIT =
    'electron' and the gain option), no EXPTIME, images of different shapes,
    too few spots in the grid or in one image, too few images or exposure
    times; each a clear error with the count."""
    images, times, _ = _series(31, n_images=3)
    adu = [_write(tmp_path / f"a{k}.fits", im, EXPTIME=t)
           for k, (im, t) in enumerate(zip(images, times))]
    with pytest.raises(ValueError, match=r"--gain G.*BUNIT = 'electron'"):
        SpotSeries(adu, gain_name="--gain")
    # the gain given: ADU with that gain, fine
    assert len(SpotSeries(adu, gain=1.0).grid) == 9
    no_time = _write(tmp_path / "n.fits", images[0], BUNIT="electron")
    with pytest.raises(ValueError, match="no EXPTIME keyword"):
        read_spot_images([no_time])
    with pytest.raises(ValueError, match="not a positive exposure time"):
        read_spot_images(images[:1], exptimes=[0.0])
    with pytest.raises(ValueError, match=r"differ in shape: image0 is 136 x 136 px, image1 is "
                                         r"120 x 136 px"):
        read_spot_images([images[0], images[1][:, :120]], exptimes=[1, 2])
    few, ft, _ = _series(32, grid=2, n_images=3)
    with pytest.raises(ValueError, match="found 4 spots in the sum of the 3 images.*at least 5"):
        SpotSeries(few, exptimes=ft)
    dark = images[:2] + [np.random.default_rng(1).normal(0, 5.0, images[0].shape)]
    with pytest.raises(ValueError, match=r"image2: 0 of the grid's 9 spots detected.*at least 5"):
        SpotSeries(dark, exptimes=times)
    with pytest.raises(ValueError, match=r"at least 3 images at 2 or more exposure times "
                                         r"\(the same spots at several fluxes\); got 2 images"):
        SpotSeries(images[:2], exptimes=times[:2])
    with pytest.raises(ValueError, match="got 3 images at 1 exposure time"):
        SpotSeries(images, exptimes=[1.0] * 3)


def test_a_stated_bias_pedestal_is_subtracted_on_read(tmp_path):
    """Correctness (exact arithmetic): images whose header states BIASLVL are
    read less that pedestal (data and saturation level), the files are left
    as they were, and the series' rows and its drift-corrected rows equal
    those of the same images written without the pedestal; a BIASLVL that is
    not a number is refused."""
    images, times, _ = _series(41, n_images=3, fluxes=(2e4, 4e5))
    plain = [_write(tmp_path / f"p{k}.fits", im, EXPTIME=t, BUNIT="electron", SATURATE=9e4)
             for k, (im, t) in enumerate(zip(images, times))]
    biased = [_write(tmp_path / f"b{k}.fits", im + 1000.0, EXPTIME=t, BUNIT="electron",
                     SATURATE=9e4 + 1000.0, BIASLVL=1000.0)
              for k, (im, t) in enumerate(zip(images, times))]
    ex = read_spot_images(biased)
    ref = read_spot_images(plain)
    with fits.open(biased[0]) as hdul:
        on_disk = hdul[0].data.astype(float)
    assert_allclose(on_disk, np.asarray(images[0], np.float32) + 1000.0, rtol=0, atol=0.07)
    for a, b in zip(ex, ref):
        assert a.bias == 1000.0 and b.bias == 0.0
        assert_allclose(a.saturation, b.saturation)
        assert_allclose(a.data, b.data, rtol=0, atol=1e-3)  # float32 rounding of +1000
    s_b, s_p = SpotSeries(biased), SpotSeries(plain)
    for key in ("flux", "sigma_x", "sigma_y"):
        assert_allclose(s_b.catalog[key].value, s_p.catalog[key].value, rtol=1e-6)
    t = load_default_template()
    for key in ("sigma_x", "sigma_y", "e1"):
        assert_allclose(s_b.corrected_catalog(t)[key].value,
                        s_p.corrected_catalog(t)[key].value, rtol=1e-5, atol=1e-7)
    bad = _write(tmp_path / "x.fits", images[0], EXPTIME=1.0, BUNIT="electron", BIASLVL="high")
    with pytest.raises(ValueError, match=r"BIASLVL = 'high' is not a bias level"):
        read_spot_images([bad])


def test_too_few_usable_rows_name_the_exclusions():
    """Bad input: when saturation leaves too few rows, the slope fit says how
    many rows each flag took."""
    images, times, _ = _series(41, n_images=3, fluxes=(4e5, 1.5e6))
    series = SpotSeries(images, exptimes=times, saturation=2e4, weight_sigma=2.3)
    with pytest.raises(ValueError, match=r"0 of 27 rows usable; left out: 27 saturated"):
        series.fit()
