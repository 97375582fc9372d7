"""Tests of lsst_bfdrift.catalogs.slopes on synthetic catalogs
(independent reference: the slope put in, and the N(0, 1) pulls of noise-only
catalogs)."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.catalogs.slopes import birge_scale, fit_flux_slope, shape_flux_relations


def _synthetic(rng, n, slope, outliers=0):
    """Stars with a quadratic PSF-size field, a flux slope and 1/SNR + floor noise."""
    x = rng.uniform(0, 1000, n)
    y = rng.uniform(0, 1000, n)
    flux = np.exp(rng.uniform(np.log(1e4), np.log(1.5e6), n))
    snr = flux / np.sqrt(flux + 3e4)
    sigma = np.hypot(1.0 / snr, 2e-3)
    q = 1.8 + 0.2 * (x / 1000) ** 2 - 0.1 * x * y / 1e6 + slope * flux / 1e5
    q = q + rng.normal(0, sigma)
    if outliers:
        bad = rng.choice(n, outliers, replace=False)
        q[bad] += rng.choice([-1, 1], outliers) * 0.05
    return x, y, flux / 1e5, q, snr, sigma


def test_slope_recovered_with_outliers():
    rng = np.random.default_rng(1)
    x, y, g, q, snr, sigma = _synthetic(rng, 150, 1e-3, outliers=12)
    r = fit_flux_slope(x, y, g, q, snr, n_boot=100)
    # independent reference: weighted least squares on the clean stars with the true errors
    assert abs(r["slope"] - 1e-3) < 3 * r["slope_err"]
    assert r["n_downweighted"] >= 10
    assert r["z"] > 5


def test_null_slopes_are_not_detected_and_errors_are_calibrated():
    # 300 noise-only catalogs: the pull z = slope / err must be ~ N(0, 1)
    rng = np.random.default_rng(2)
    z = []
    for _ in range(300):
        x, y, g, q, snr, _ = _synthetic(rng, 60, 0.0)
        z.append(fit_flux_slope(x, y, g, q, snr, n_boot=0)["z"])
    z = np.array(z)
    assert np.mean(np.abs(z) > 3) < 0.02          # false detections at 3 sigma
    assert 0.8 < np.std(z) < 1.25 and abs(np.mean(z)) < 0.2


def test_too_few_stars_get_clear_messages():
    rng = np.random.default_rng(3)
    x, y, g, q, snr, _ = _synthetic(rng, 5, 0.0)
    with pytest.raises(ValueError, match="only 5 usable stars"):
        fit_flux_slope(x, y, g, q, snr)


def test_source_noise_term_weights_bright_stars_right():
    # stars whose size noise has a source term b / sqrt(F) beside 1 / SNR (as
    # adaptive moments of bright stars do): with the fluxes given, the fit
    # recovers b, its pulls stay N(0, 1), and the slope error is smaller than
    # the SNR-only model's (which must take the source term as a floor tau)
    rng = np.random.default_rng(4)
    b = 1.5
    z_flux, err_flux, err_snr, betas = [], [], [], []
    for _ in range(150):
        x = rng.uniform(0, 1000, 200)
        y = rng.uniform(0, 1000, 200)
        flux = np.exp(rng.uniform(np.log(1e4), np.log(1.5e6), 200))
        snr = flux / np.sqrt(flux + 3e4)
        sigma = np.sqrt(1.0 / snr ** 2 + b ** 2 / flux)
        q = 1.8 + 0.1 * x / 1000 + rng.normal(0, sigma)
        # no noise-bias terms in either fit: the weights alone are compared
        r = fit_flux_slope(x, y, flux / 1e5, q, snr, flux=flux, n_boot=0, noise_term=False)
        z_flux.append(r["z"])
        err_flux.append(r["slope_err"])
        betas.append(r["beta"])
        err_snr.append(fit_flux_slope(x, y, flux / 1e5, q, snr, n_boot=0,
                                      noise_term=False)["slope_err"])
    z_flux = np.array(z_flux)
    assert 0.8 < np.std(z_flux) < 1.2 and abs(np.mean(z_flux)) < 0.25
    assert_allclose(np.median(betas), b, rtol=0.2)
    assert np.median(np.array(err_flux) / np.array(err_snr)) < 0.9


def test_two_noise_bias_terms_remove_a_source_noise_bias():
    # adaptive moments are biased by the sky's noise and by the star's own
    # photon noise with coefficients of their own: q = ... + b / SNR^2 + c / F
    # with c != b. The 1/SNR^2 term alone leaves part of c / F in the slope;
    # with the fluxes given both terms are fitted and the slope is unbiased
    # (independent reference: the zero slope put in)
    rng = np.random.default_rng(5)
    one, two = [], []
    for _ in range(60):
        x = rng.uniform(0, 1000, 700)
        y = rng.uniform(0, 1000, 700)
        flux = np.exp(rng.uniform(np.log(1e4), np.log(1.5e6), 700))
        snr = flux / np.sqrt(flux + 5e4)
        q = 1.8 + 0.1 * x / 1000 + 2.0 / snr ** 2 + 150.0 / flux \
            + rng.normal(0, np.sqrt(1.0 / snr ** 2 + 1.5 ** 2 / flux))
        one.append(fit_flux_slope(x, y, flux / 1e5, q, snr, n_boot=0))
        two.append(fit_flux_slope(x, y, flux / 1e5, q, snr, flux=flux, n_boot=0))
    z1 = np.array([r["z"] for r in one])
    z2 = np.array([r["z"] for r in two])
    assert abs(np.mean(z2)) < 0.35 and 0.7 < np.std(z2) < 1.3
    assert abs(np.mean(z1)) > 1.0  # the single term leaves a bias
    assert_allclose(np.median([r["source_bias"] for r in two]), 150.0 / 1e5, rtol=0.3)
    assert all(r["source_bias"] is None for r in one)


def test_birge_scale_against_direct_sum_and_true_scatter():
    """The Birge ratio: the direct sum sqrt(chi2 / (n - p)) when above 1, 1 otherwise;
    on residuals drawn 1.5 times wider than their errors (seeded) it finds 1.5."""
    rng = np.random.default_rng(11)
    e = rng.uniform(0.5, 2.0, 400)
    r = rng.normal(0.0, 1.5 * e)
    assert_allclose(birge_scale(r, e, 2.0), np.sqrt(np.sum((r / e) ** 2) / 398.0), rtol=1e-12)
    assert_allclose(birge_scale(r, e, 2.0), 1.5, rtol=0.08)
    # only ever inflates
    assert birge_scale(0.5 * e * rng.normal(size=400), e, 2.0) == 1.0
    # unweighted points (infinite errors) are not counted
    e2 = np.r_[e[:10], np.full(5, np.inf)]
    r2 = np.r_[r[:10], np.full(5, 1e9)]
    assert_allclose(birge_scale(r2, e2, 1.0),
                    max(1.0, np.sqrt(np.sum((r[:10] / e[:10]) ** 2) / 9.0)), rtol=1e-12)
    # too few points or no degree of freedom left: no estimate
    assert birge_scale(10 * e[:5], e[:5], 0.0) == 1.0
    assert birge_scale(10 * e[:8], e[:8], 7.5) == 1.0
    assert birge_scale(10 * e[:8], e[:8], 6.5) > 1.0
