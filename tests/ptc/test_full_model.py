"""Tests of lsst_bfdrift.ptc.full_model: the Astier et al. 2019 full covariance model
(eq. 20), its lag operators, its exact Jacobian and its fit."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.ptc.covariances import ptc_exponential_model
from lsst_bfdrift.ptc.full_model import (convolve_lags, covariance_model,
                                         covariance_model_jacobian, fit_covariance_model,
                                         lag_operator)
from lsst_bfdrift.utils.errors import InputError


def _random_params(rng, L):
    """a_ij, b_ij (1/e) and n_ij (e^2) of a plausible sensor, randomised."""
    a = rng.normal(0.0, 1e-7, (L + 1, L + 1))
    a[0, 0] = -2.5e-6
    b = rng.normal(0.0, 3e-7, (L + 1, L + 1))
    noise = rng.normal(0.0, 2.0, (L + 1, L + 1))
    noise[0, 0] = 30.0
    return a, b, noise


def _signed(q, p, r):
    """A quadrant array's value at the signed lag (p, r); zero beyond its lags."""
    L = q.shape[0] - 1
    return q[abs(p), abs(r)] if abs(p) <= L and abs(r) <= L else 0.0


def _direct_conv(x, y):
    """(x * y)(i, j) = sum over signed lags (p, r) of x(p, r) y(i - p, j - r), for
    0 <= i, j <= L: explicit loops, no array trick."""
    L = x.shape[0] - 1
    out = np.zeros_like(x)
    for i in range(L + 1):
        for j in range(L + 1):
            out[i, j] = sum(_signed(x, p, r) * _signed(y, i - p, j - r)
                            for p in range(-L, L + 1) for r in range(-L, L + 1))
    return out


def test_full_model_equals_explicit_series_of_eq20(rng):
    """CORRECTNESS: eq. 20 of Astier et al. 2019 written out term by term with
    explicit convolution loops over signed lags, at every lag and signal, against
    the package's lag-operator evaluation."""
    L = 3
    a, b, noise = _random_params(rng, L)
    mu = np.array([2e3, 3e4, 9e4])
    g = 1.3
    aa = _direct_conv(a, a)
    ab = a * b
    aaa = _direct_conv(aa, a)
    a_ab = _direct_conv(a, ab)
    ref = np.empty((mu.size, L + 1, L + 1))
    for k, m in enumerate(mu):
        x = m * g
        bracket = (a * x + 2.0 / 3.0 * (aa + ab) * x**2
                   + (2.0 * aaa + 5.0 * a_ab) * x**3 / 6.0)
        bracket[0, 0] += 1.0
        ref[k] = m / g * bracket + noise / g**2
    assert_allclose(covariance_model(mu, g, a, b, noise), ref, rtol=1e-12, atol=1e-12)


def test_lag_operator_equals_direct_convolution(rng):
    """CORRECTNESS: M(y) x against scipy's convolve2d of the signed-lag arrays, and
    against explicit loops, for random arrays (any numbers, not only a_ij)."""
    for L in (0, 1, 4):
        x = rng.normal(size=(L + 1, L + 1))
        y = rng.normal(size=(L + 1, L + 1))
        got = (lag_operator(y) @ x.ravel()).reshape(x.shape)
        assert_allclose(got, convolve_lags(x, y), rtol=1e-13, atol=1e-13)
        assert_allclose(got, _direct_conv(x, y), rtol=1e-13, atol=1e-13)


def test_full_model_reduces_to_exponential_series():
    """CORRECTNESS: with only a00 and b = 0 the full model's C00 is the exponential
    model's third-order Taylor series: (e^{2x} - 1) / 2x = 1 + x + 2x^2/3 + x^3/3 + ..."""
    L = 3
    a = np.zeros((L + 1, L + 1))
    a[0, 0] = -2e-6
    mu = np.array([1e3, 1e4, 3e4])
    g = 0.8
    c = covariance_model(mu, g, a, np.zeros_like(a), np.zeros_like(a))
    x = a[0, 0] * mu * g
    assert_allclose(c[:, 0, 0], mu / g * (1 + x + 2 * x**2 / 3 + x**3 / 3), rtol=1e-12)
    assert_allclose(c[:, 0, 0], ptc_exponential_model(mu, g, a[0, 0], 0.0), rtol=1e-6)
    assert_allclose(c[:, 1:, :], 0.0, atol=1e-30)


def test_full_model_convolution_terms():
    """CORRECTNESS: a*a at lag (1, 0) equals 2 a00 a10 + 2 a10 a20 + ... (direct sum)."""
    a = np.zeros((3, 3))
    a[0, 0], a[1, 0], a[0, 1], a[1, 1] = -1.0, 0.2, 0.3, 0.05
    aa = convolve_lags(a, a)

    def full(i, j):
        i, j = abs(i), abs(j)
        return a[i, j] if i < 3 and j < 3 else 0.0
    ref = sum(full(p, q) * full(1 - p, 0 - q) for p in range(-3, 4) for q in range(-3, 4))
    assert aa[1, 0] == pytest.approx(ref)


def test_full_model_broadcasts_one_noise_value():
    """CONSISTENCY: a 1 x 1 noise (and b) array stands for every lag, as before."""
    a = np.array([[-2e-6, 3e-7], [1e-7, 2e-8]])
    mu = np.array([1e3, 5e4])
    one = covariance_model(mu, 0.9, a, np.zeros((1, 1)), [[20.0]])
    full = covariance_model(mu, 0.9, a, np.zeros_like(a), np.full_like(a, 20.0))
    assert_allclose(one, full, rtol=1e-15)


def test_jacobian_equals_central_differences(rng):
    """CORRECTNESS: the exact Jacobian against central finite differences of the
    model, parameter by parameter (the model is a cubic polynomial in a and b:
    the differences' truncation error is h^2/6 times the third derivative)."""
    L = 2
    a, b, noise = _random_params(rng, L)
    mu = np.array([5e3, 4e4, 9e4])
    g = 1.2
    n1 = (L + 1) ** 2
    p0 = np.concatenate([[g], a.ravel(), b.ravel(), noise.ravel()])
    step = np.concatenate([[1e-5], np.full(2 * n1, 1e-9), np.full(n1, 1e-2)])

    def model(p):
        return covariance_model(mu, p[0], p[1:1 + n1].reshape(a.shape),
                                p[1 + n1:1 + 2 * n1].reshape(a.shape),
                                p[1 + 2 * n1:].reshape(a.shape)).reshape(mu.size, n1)

    jac = covariance_model_jacobian(mu, g, a, b, noise)
    assert jac.shape == (mu.size, n1, 1 + 3 * n1)
    for k in range(p0.size):
        dp = np.zeros_like(p0)
        dp[k] = step[k]
        num = (model(p0 + dp) - model(p0 - dp)) / (2.0 * step[k])
        scale = np.abs(num).max()
        assert scale > 0, k  # every parameter moves some covariance
        assert_allclose(jac[:, :, k], num, rtol=0, atol=1e-6 * scale, err_msg=f"parameter {k}")


def _synthetic(rng, L=2, n_levels=8):
    a = np.array([[-2e-6, 3e-7, 5e-8], [1.2e-7, 4e-8, 1e-8], [2e-8, 1e-8, 5e-9]])[:L + 1, :L + 1]
    noise = np.zeros_like(a)
    noise[0, 0] = 25.0
    g = 0.8
    mu = np.geomspace(500, 9e4, n_levels)
    c = covariance_model(mu, g, a, np.zeros_like(a), noise)
    err = np.sqrt(2.0 / 1e6) * (mu / g)[:, None, None] * np.ones_like(c)
    return mu, c + rng.normal(0, 1, c.shape) * err, err, a, g


def test_exact_jacobian_fit_equals_finite_difference_fit(rng):
    """CONSISTENCY: the fit with the exact Jacobian lands where the former
    finite-difference fit lands (b_ij fixed: a well-posed minimum), with far fewer
    model evaluations. Both stop where the cost changes by less than 1e-8
    relative (scipy's ftol), not at one point: a00 and gain agree within 1e-6
    relative, the small a_ij within 1 % of their errors, chi2 within 1e-7 (the
    exact Jacobian's lower)."""
    mu, c, err, _, _ = _synthetic(rng)
    counts = {}
    fits = {}
    for jac in ("exact", "2-point"):
        n = [0]

        def count():
            n[0] += 1
        fits[jac] = fit_covariance_model(mu, c, sigma=err, fit_b=False, jac=jac,
                                         progress=count)
        counts[jac] = n[0]
    ex, fd = fits["exact"], fits["2-point"]
    assert ex["a"][0, 0] == pytest.approx(fd["a"][0, 0], rel=1e-6)
    assert ex["gain"] == pytest.approx(fd["gain"], rel=1e-6)
    assert np.all(np.abs(ex["a"] - fd["a"]) < 0.01 * fd["a_err"])
    assert ex["chi2"] == pytest.approx(fd["chi2"], rel=1e-7)
    assert ex["chi2"] <= fd["chi2"] * (1 + 1e-12)  # the exact Jacobian gets closer
    assert_allclose(ex["a_err"], fd["a_err"], rtol=1e-3)
    assert counts["exact"] < counts["2-point"] / 5


def test_full_fit_recovers_synthetic(rng):
    """CORRECTNESS: a_ij and gain drawn into noisy covariances are recovered within
    4 sigma."""
    mu, c_noisy, err, a, g = _synthetic(rng, n_levels=30)
    r = fit_covariance_model(mu, c_noisy, sigma=err, fit_b=False)
    assert r["gain"] == pytest.approx(g, abs=4 * r["gain_err"])
    assert np.all(np.abs(r["a"] - a) < 4 * r["a_err"] + 1e-12)
    assert r["chi2"] / r["dof"] < 1.5


def test_full_fit_with_known_gain_and_no_noise(rng):
    """CORRECTNESS: gain held at its true value and n_ij at zero: fewer parameters,
    smaller errors on a_ij, still unbiased; a wrong fixed gain is detected by chi2."""
    a = np.array([[-2e-6, 3e-7], [1.2e-7, 4e-8]])
    g = 0.8
    mu = np.geomspace(500, 9e4, 30)
    c = covariance_model(mu, g, a, np.zeros_like(a), np.zeros_like(a))
    err = np.sqrt(2.0 / 1e6) * (mu / g)[:, None, None] * np.ones_like(c)
    c_noisy = c + rng.normal(0, 1, c.shape) * err
    free = fit_covariance_model(mu, c_noisy, sigma=err, fit_b=False)
    fixed = fit_covariance_model(mu, c_noisy, sigma=err, fit_b=False, gain=g, fit_noise=False)
    assert fixed["gain"] == g and fixed["gain_err"] == 0.0
    assert np.all(fixed["noise"] == 0) and np.all(fixed["noise_err"] == 0)
    assert np.all(np.abs(fixed["a"] - a) < 4 * fixed["a_err"])
    assert fixed["a_err"][0, 0] < 0.8 * free["a_err"][0, 0]
    assert fixed["chi2"] / fixed["dof"] < 1.5
    wrong = fit_covariance_model(mu, c_noisy, sigma=err, fit_b=False, gain=1.02 * g,
                                 fit_noise=False)
    assert wrong["chi2"] / wrong["dof"] > 5
    with pytest.raises(ValueError, match="gain"):
        fit_covariance_model(mu, c_noisy, sigma=err, gain=-1.0)


def test_unknown_jacobian_option_is_refused(rng):
    mu, c, err, _, _ = _synthetic(rng)
    with pytest.raises(InputError, match="jac must be 'exact' or '2-point'"):
        fit_covariance_model(mu, c, sigma=err, fit_b=False, jac="3-point")
