"""Tests of the fit engine against closed forms and scipy (independent references)."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.optimize import curve_fit

from lsst_bfdrift.calibration.fitting import FitError, fit_parameters


def _linear_problem(rng):
    x = np.linspace(0.0, 3.0, 40)
    X = np.stack([np.ones_like(x), x, x**2], axis=1)
    truth = np.array([1.5, -0.7, 0.25])
    sigma = 0.05 + 0.02 * x
    y = X @ truth + rng.normal(0, sigma)
    return X, y, sigma


def test_linear_model_equals_weighted_least_squares(rng):
    """A model linear in its parameters: the fit is the closed-form WLS
    solution, and the covariance is (X^T W X)^-1."""
    X, y, sigma = _linear_problem(rng)
    W = np.diag(1 / sigma**2)
    cov = np.linalg.inv(X.T @ W @ X)
    best = cov @ X.T @ W @ y

    def model(v):
        return X @ np.array([v["c0"], v["c1"], v["c2"]])

    fit = fit_parameters(model, y, sigma, {"c0": 1.0, "c1": 0.0, "c2": 0.0},
                         {"c0": (-10, 10), "c1": (-10, 10), "c2": (-10, 10)})
    err = np.sqrt(np.diag(cov))
    assert np.all(np.abs([fit.values[k] for k in ("c0", "c1", "c2")] - best) < 0.03 * err)
    assert_allclose(fit.covariance, cov, rtol=1e-4)
    chi2 = np.sum(((X @ best - y) / sigma) ** 2)
    assert chi2 <= fit.chi2 < chi2 + 1e-3
    assert fit.dof == 37 and fit.converged
    assert_allclose(np.diag(fit.correlation), 1.0)


def test_nonlinear_model_matches_curve_fit(rng):
    """An exponential decay: same optimum and errors as scipy's curve_fit
    (absolute_sigma), with a Jacobian given at the start (the engine's
    Broyden path) or computed by finite differences."""
    t = np.linspace(0, 4, 30)
    sigma = np.full(t.size, 0.02)
    y = 2.0 * np.exp(-t / 1.3) + rng.normal(0, sigma)

    def f(tt, amp, tau):
        return amp * np.exp(-tt / tau)

    popt, pcov = curve_fit(f, t, y, p0=(1.5, 1.0), sigma=sigma, absolute_sigma=True)
    start = {"amp": 1.5, "tau": 1.0}
    bounds = {"amp": (0.1, 10.0), "tau": (0.1, 10.0)}

    def model(v):
        return f(t, v["amp"], v["tau"])

    jac0 = np.stack([np.exp(-t / 1.0), 1.5 * t / 1.0**2 * np.exp(-t / 1.0)], axis=-1)
    for kw in ({}, {"jacobian0": jac0}, {"central": True}):
        fit = fit_parameters(model, y, sigma, start, bounds, **kw)
        assert np.all(np.abs([fit.values["amp"], fit.values["tau"]] - popt)
                      < 0.03 * np.sqrt(np.diag(pcov)))
        assert_allclose(fit.covariance, pcov, rtol=0.02)
    assert fit.n_evaluations < 40


def test_mask_and_worst_points(rng):
    X, y, sigma = _linear_problem(rng)
    y = y.copy()
    y[7] += 40 * sigma[7]  # an outlier

    def model(v):
        return X @ np.array([v["c0"], v["c1"], v["c2"]])

    start = {"c0": 1.0, "c1": 0.0, "c2": 0.0}
    bounds = {k: (-10, 10) for k in start}
    fit = fit_parameters(model, y, sigma, start, bounds)
    assert fit.worst(1)[0][0] == (7,)
    assert fit.p_value < 1e-10
    mask = np.ones(y.size, bool)
    mask[7] = False
    clean = fit_parameters(model, y, sigma, start, bounds, mask=mask)
    assert clean.dof == 36 and np.isnan(clean.pulls[7])
    assert clean.p_value > 1e-3


def test_bounds_are_respected():
    def model(v):
        return np.array([v["a"], v["a"]])

    fit = fit_parameters(model, np.array([5.0, 5.0]), 1.0, {"a": 0.5}, {"a": (0.0, 1.0)})
    assert 0.99 < fit.values["a"] < 1.0
    assert fit.at_bound == ["a"]


@pytest.mark.parametrize("update", ["broyden", "exact"])
def test_correlated_parameters_reach_the_bounded_optimum(update):
    """Strongly correlated parameters, one of which ends on a bound: the others
    must take up what the bounded one cannot do (reference: scipy's bounded
    linear least squares)."""
    from scipy.optimize import lsq_linear

    x = np.linspace(0.0, 1.0, 30)
    X = np.stack([np.ones_like(x), x + 0.02 * x**2, x + 0.04 * x**3, x**2], axis=1)
    y = X @ np.array([0.2, 3.0, -1.0, 0.3]) + 0.01 * np.sin(7 * x)
    sigma = np.full(x.size, 0.01)
    names = ["c", "b1", "b2", "q"]
    lo, hi = np.array([0.0, -2.0, -0.5, -1.0]), np.array([1.0, 1.5, 2.0, 1.0])
    ref = lsq_linear(X / sigma[:, None], y / sigma, bounds=(lo, hi), tol=1e-12)
    assert list(ref.active_mask) == [0, 0, 1, 0]
    fit = fit_parameters(lambda v: X @ np.array([v[k] for k in names]), y, sigma,
                         {"c": 0.5, "b1": 0.0, "b2": 0.5, "q": 0.0},
                         {k: (a, b) for k, a, b in zip(names, lo, hi)}, update=update,
                         max_evaluations=200, tol=1e-6)
    chi2_ref = float(np.sum(((X @ ref.x - y) / sigma) ** 2))
    assert fit.chi2 < chi2_ref + 1e-4
    assert fit.at_bound == ["b2"]
    assert_allclose([fit.values[k] for k in names], ref.x, atol=1e-4)


@pytest.mark.parametrize("kwargs, match", [
    ({"start": {"a": 2.0}}, "outside its bounds"),
    ({"start": {}}, "no free parameters"),
    ({"sigma": np.array([1.0, 0.0, 1.0])}, "finite and positive"),
    ({"data": np.array([1.0, np.nan, 1.0])}, "NaN or inf"),
    ({"mask": np.array([True, False])}, "mask shape"),
    ({"bounds": {}}, "no bounds"),
])
def test_bad_input(kwargs, match):
    args = {"model": lambda v: np.full(3, v.get("a", 0.0)), "data": np.ones(3),
            "sigma": np.ones(3), "start": {"a": 0.5}, "bounds": {"a": (0.0, 1.0)}}
    args.update(kwargs)
    with pytest.raises(FitError, match=match):
        fit_parameters(args.pop("model"), args.pop("data"), args.pop("sigma"),
                       args.pop("start"), args.pop("bounds"), **args)


def test_model_of_wrong_shape():
    with pytest.raises(FitError, match="model returned shape"):
        fit_parameters(lambda v: np.zeros(2), np.ones(3), 1.0, {"a": 0.5}, {"a": (0, 1)})
