"""Forward models of the effects library against independent references."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.simulation.effects import (CTI, EFFECT_NAMES, ChargeCloud, GainNonlinearity, StaticArea,
                                  WellFilling, cti_filter_covariance, effect_library, full_lags,
                                  quadrant)


def test_vocabulary_and_library():
    assert tuple(e.name for e in effect_library()) == EFFECT_NAMES
    with pytest.raises(ValueError, match="unknown effects"):
        effect_library(["tree_rings"])
    with pytest.raises(ValueError, match="serial"):
        CTI("diagonal")
    for e in effect_library():
        for kind in ("table", "ptc", "flats"):
            ok, why = e.identifiable(kind)
            assert isinstance(ok, bool) and why
    assert not any(e.identifiable(k)[0] for e in effect_library(["diffusion"])
                   for k in ("table", "ptc", "flats"))


def test_full_lags_roundtrip():
    q = np.arange(16.0).reshape(4, 4)
    f = full_lags(q)
    assert f.shape == (7, 7)
    for i in range(-3, 4):
        for j in range(-3, 4):
            assert f[3 + i, 3 + j] == q[abs(i), abs(j)]
    assert_allclose(quadrant(f), q)


def test_charge_cloud_against_gaussian_average():
    """Cloud average of a smooth response, by numerical integration."""
    def a(x, y):
        return np.exp(-x**2 / 8.0 - y**2 / 18.0) - 0.3 * np.exp(-(x**2 + y**2) / 50.0)

    L = 6
    i, j = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    base = a(i, j)
    vs, vp = 0.04, 0.09
    out = ChargeCloud().apply_a(base, (vs, vp), None)
    # Gauss-Hermite average over the Gaussian cloud (30 x 30 nodes)
    x, w = np.polynomial.hermite_e.hermegauss(30)
    w = w / w.sum()
    u = x[:, None] * np.sqrt(vs)
    v = x[None, :] * np.sqrt(vp)
    ref = np.array([[np.sum(w[:, None] * w[None, :] * a(ii - u, jj - v))
                     for jj in range(L + 1)] for ii in range(L + 1)])
    # the change agrees to the accuracy of the second-order expansion (inside the
    # window: beyond lag L the model takes the pattern as zero)
    d, dref = (out - base)[:L, :L], (ref - base)[:L, :L]
    assert_allclose(d, dref, atol=0.06 * np.abs(dref).max())
    # zero cloud leaves the pattern unchanged; the sum over signed lags is conserved
    assert_allclose(ChargeCloud().apply_a(base, (0.0, 0.0), None), base)
    big = np.exp(-(i**2 + j**2) / 2.0)
    assert_allclose(full_lags(ChargeCloud().apply_a(big, (0.1, 0.2), None)).sum(),
                    full_lags(big).sum(), rtol=1e-6)


def test_cti_covariance_against_direct_filter():
    """Poisson image read out with deferral eps: measured vs formula."""
    rng = np.random.default_rng(3)
    mu, eps = 1000.0, 0.05
    n = rng.poisson(mu, (512, 512)).astype(float)
    for axis, img_axis in ((0, 1), (1, 0)):
        out = (1 - eps) * n + eps * np.roll(n, 1, axis=img_axis)
        d = out - out.mean()
        var = np.mean(d * d)
        c1 = np.mean(d * np.roll(d, 1, axis=img_axis))
        c1_other = np.mean(d * np.roll(d, 1, axis=1 - img_axis))
        white = np.zeros((3, 3))
        white[0, 0] = mu
        model = cti_filter_covariance(white, eps, axis)
        err = mu / 512.0  # sample-covariance error ~ var / sqrt(N)
        assert abs(var - model[0, 0]) < 4 * np.sqrt(2) * err
        lag1 = model[1, 0] if axis == 0 else model[0, 1]
        other = model[0, 1] if axis == 0 else model[1, 0]
        assert abs(c1 - lag1) < 4 * err
        assert abs(c1_other - other) < 4 * err
        assert_allclose(lag1, eps * (1 - eps) * mu)
    e = CTI("parallel")
    assert_allclose(e.apply_cov(white[None], (eps,))[0], cti_filter_covariance(white, eps, 1))


def test_gain_nonlinearity_against_monte_carlo():
    rng = np.random.default_rng(4)
    nu = 2e-6
    mu = np.array([1e4, 5e4, 9e4])
    e = GainNonlinearity()
    for m in mu:
        s = rng.normal(m, np.sqrt(m), 400000)
        S = s * (1 + nu * s)
        lin, fac = e.measured_signal(np.array([S.mean()]), (nu,))
        assert_allclose(lin[0], m, rtol=2e-3)
        assert_allclose(S.var() / s.var(), fac[0], rtol=1e-2)
    # tiny nu: no cancellation, M -> mu
    lin, fac = e.measured_signal(np.array([5e4]), (1e-16,))
    assert_allclose(lin, 5e4, rtol=1e-9)


def test_well_filling_b_term():
    class Basis:
        def dlog_depth(self, L):
            return np.full((L + 1, L + 1), 2e-7)

    a = np.array([[-1e-6, 1e-7], [5e-8, 0.0]])
    b = WellFilling().b_term(a, (3e-6,), Basis())
    # a * b = beta D where a != 0; zero where a == 0
    assert_allclose((a * b)[a != 0], 3e-6 * 2e-7)
    assert b[1, 1] == 0.0


def test_static_area_model():
    e = StaticArea(max_lag=1)
    assert len(e.param_names) == 4
    s = e.static(np.array([10.0, 20.0]), 1, (1e-4, 2e-5, 3e-5, 1e-5))
    assert_allclose(s[1], 4 * s[0])
    assert_allclose(s[0, 0, 1], 100 * 2e-5)
    with pytest.raises(ValueError, match="lags <= 1"):
        e.static(np.array([1.0]), 2, (0.0,) * 9)
