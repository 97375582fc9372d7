"""Tests of the steps of calibrate_with_stars, one function at a time.

Kinds:

* hand-computed small cases: the direction step rule, the progress count,
  the fold combination, the chi2, tension, information, coefficient and
  lag-change tables, the Birge scaling (closed forms of the chi2 survival
  function for 1, 2 and 4 degrees of freedom, not scipy);
* the linearised solve against a direct weighted least-squares solution
  (numpy lstsq on the stacked, weighted rows; hat matrix for the leverage);
* the fit with Gauss-Newton steps against the exact minimum of the same
  chi2 found by scipy's scalar minimiser (a star slope quadratic in the
  step, so the linear solve alone is off);
* wiring with stand-in fields: the row order of the star vector, which
  half is measured with which fold's template, which step each direction
  is evaluated at, and the errors raised;
* the a-matrix rows against direct indexing of the template's area response.
"""

import math
import types

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.optimize import minimize_scalar

from tests.calibration.test_star_fit import _calibration
from tests.validation._galsim_fields import paired_fields
from lsst_bfdrift.calibration.star_basis import (STAR_JACOBIAN_STEP, AmatrixRows, DirectionBasis,
                                                 amatrix_jacobian, direction_basis,
                                                 evaluate_directions, evaluated_basis,
                                                 model_direction_step)
from lsst_bfdrift.calibration.star_fit import (StarField, fields_summary, fitted_star_slopes,
                                               holdout_fields, progress_steps, read_star_fields,
                                               split_fields)
from lsst_bfdrift.calibration.star_result import joint_template
from lsst_bfdrift.calibration.star_report import (direction_coefficients, fit_chi2, lag_changes,
                                                  slope_precision, star_information,
                                                  tension_test)
from lsst_bfdrift.calibration.star_solve import (PRIOR_STEPS, combine_folds, cross_validate,
                                                 fit_joint, fit_with_error_scale,
                                                 held_out_validation, solve_joint,
                                                 star_jacobian, star_vector)
from lsst_bfdrift.calibration.tuning import CalibrationError
from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.templates.refine import (combine_templates, template_alpha,
                                          template_difference)
from lsst_bfdrift.templates.template import build_template
from lsst_bfdrift.utils.errors import InputError

_ARRAYS = ("corner_d", "vedge_d", "hedge_d", "vedge_t", "hedge_t")


def _scale_delta(template, factor=1.0):
    """The direction 'scale' (the template's own displacements), times ``factor``."""
    return {k: None if getattr(template, k) is None else factor * getattr(template, k)
            for k in _ARRAYS}


def _strength(template, base):
    """k with template = k x base, from the vertical edges (exact for the scale family)."""
    return float(np.sum(template.vedge_d * base.vedge_d) / np.sum(base.vedge_d ** 2))


class _Field:
    """A stand-in star field: ``slopes`` from a function of the template and the subset."""

    kind = "stars"

    def __init__(self, name, fn, *, n=10, fails=None):
        self.name, self.fn, self.fails = name, fn, fails
        self.calls = []
        self.usable = np.ones(n, bool)
        self.fit_stars = self.usable.copy()
        self.held_out = self.usable.copy()
        self.half_a = np.arange(n) % 2 == 0
        self.half_b = ~self.half_a

    def slopes(self, template, subset, *, n_boot=0, seed=20151):
        self.calls.append((template, np.asarray(subset).copy(), n_boot, seed))
        if self.fails is not None and self.fails(template):
            raise InputError("cannot correct")
        return self.fn(template, np.asarray(subset)) | {"n_stars": int(np.sum(subset))}

    def corrected_catalog(self, template):
        if self.fails is not None and self.fails(template):
            raise InputError("cannot correct")
        return None


# --------------------------------------------------------------------------- star_basis

def test_model_direction_step_rule():
    # a tenth of the value, or of 1 % of the range when the value is small
    assert model_direction_step(2.0, 0.0, 10.0) == pytest.approx(0.2)
    assert model_direction_step(0.0, -1.0, 1.0) == pytest.approx(0.002)
    # past the upper bound: the step goes down
    assert model_direction_step(9.95, 0.0, 10.0) == pytest.approx(-0.995)
    # no room either way: no direction
    assert model_direction_step(1.0, 0.95, 1.05) is None


def test_amatrix_rows_index_the_template_response():
    """Row k of the a-matrix rows is lag (i, j) of its label a{i}{j}: table.a[i, j],
    and the template's area response at pixel (c + j, c + i) (rows y, columns x)."""
    res = _calibration()
    ta = res.template
    a, sigma = res.table.a, res.table.sigma
    table = AcoeffTable(a, sigma, source="a00 not fitted", exclude_a00=True)
    rows = AmatrixRows(table, ta)
    c, L = ta.center, rows.max_lag
    assert L == min(table.max_lag, c - 1)
    alpha = template_alpha(ta)
    labels = rows.labels()
    assert len(labels) == rows.size == int(table.mask()[:L + 1, :L + 1].sum())
    assert "a00" not in labels and "a21" in labels and "a12" in labels
    for k, lab in enumerate(labels):
        i, j = int(lab[1]), int(lab[2])
        assert rows.measured[k] == a[i, j] and rows.sigma[k] == sigma[i, j]
        assert rows.start[k] == alpha[c + j, c + i]
    assert np.isnan(rows.sigma_lags[0, 0]) and rows.sigma_lags[1, 2] == sigma[1, 2]
    # the a-matrix is linear in the displacements: the 'scale' column is T_a's own a_ij
    jac = amatrix_jacobian(rows, ta, [_scale_delta(ta), _scale_delta(ta, -2.0)])
    assert_allclose(jac[:, 0], rows.start, rtol=1e-9)
    assert_allclose(jac[:, 1], -2.0 * rows.start, rtol=1e-9)


def test_direction_basis_model_directions_and_curl():
    """With the model's directions: 'scale' (T_a), each candidate with room (the
    built template's change for its step) and 'curl'; a candidate without room
    is left out; with lag directions, only 'curl' and those."""
    res = _calibration()
    x0 = float(res.params.xi0)
    cands = {"xi0": (300.0, 3e4), "channel_depth": (res.params.channel_depth * 0.99,
                                                   res.params.channel_depth * 1.01)}
    r = type(res)(**{**res.__dict__, "candidates": cands})
    ticks = []
    names, steps, deltas, lag_names, warns = direction_basis(r, {}, bar=ticks.append)
    assert names == ["scale", "xi0", "curl"] and lag_names == set() and warns == []
    assert len(ticks) == 3  # one per candidate and one for curl
    assert steps["scale"] == steps["curl"] == 1.0
    assert steps["xi0"] == pytest.approx(0.1 * x0)
    for k in _ARRAYS:
        if getattr(res.template, k) is not None:
            assert_allclose(deltas[0][k], getattr(res.template, k))
    direct = template_difference(build_template(res.params.replace(xi0=x0 + steps["xi0"]),
                                                res.settings), res.built_template)
    for k in _ARRAYS:
        if direct[k] is not None:
            assert_allclose(deltas[1][k], direct[k], rtol=0, atol=1e-12)
    lag = {"mode0": {"delta": _scale_delta(res.template, 0.01)}}
    names, steps, deltas, lag_names, warns = direction_basis(r, lag)
    assert names == ["curl", "mode0"] and lag_names == {"mode0"} and steps["mode0"] == 1.0


def test_evaluate_directions_steps_back_and_drops():
    """A lag direction the fields cannot take a whole step of is evaluated at a
    quarter step; a model direction that fails at its quarter step is dropped
    with a warning; the basis keeps the rest, with the a-matrix Jacobian."""
    res = _calibration()
    ta = res.template
    # the fields fail on templates more than 1.5 times T_a
    fields = [_Field(n, None, fails=lambda t: t is not None and _strength(t, ta) > 1.5)
              for n in ("f0", "f1")]
    names = ["big", "curl", "mode0"]
    deltas = [_scale_delta(ta, 4.0), _scale_delta(ta, 0.0), _scale_delta(ta, 1.0)]
    keep, templates, eps, warns = evaluate_directions(ta, names, deltas, {"mode0"}, fields)
    assert keep == [1, 2]
    assert eps == [STAR_JACOBIAN_STEP, STAR_JACOBIAN_STEP]  # mode0: 1.0 fails, 0.25 does not
    assert _strength(templates[1], ta) == pytest.approx(1.25)
    assert len(warns) == 1 and warns[0].startswith("direction big skipped")
    rows = AmatrixRows(res.table, ta)
    basis, warns = evaluated_basis(ta, rows, names, {}, deltas, {"mode0"}, fields)
    assert basis.names == ["curl", "mode0"] and list(basis.is_lag) == [False, True]
    assert basis.n_lag == 1
    assert_allclose(basis.jacobian[:, 1], rows.start, rtol=1e-9)
    with pytest.raises(CalibrationError, match="no direction of the template family"):
        evaluated_basis(ta, rows, ["big"], {}, deltas[:1], set(), fields)


# --------------------------------------------------------------------------- star_solve

def test_star_vector_order_and_jacobian():
    """Rows: each field's size, e1, e2 in turn; the Jacobian: finite differences
    over each direction's step."""
    def fn(off):
        return lambda t, sub: {"size": (off + t + sub.sum(), 0.1), "e1": (off + 2 * t, 0.2),
                               "e2": (off + 3 * t, 0.3)}
    fields = [_Field("a", fn(0.0)), _Field("b", fn(100.0))]
    subsets = {"a": np.ones(10, bool), "b": np.arange(10) < 4}
    v, e = star_vector(fields, subsets, 1.0, n_boot=7, seed=5)
    assert_allclose(v, [11.0, 2.0, 3.0, 105.0, 102.0, 103.0])
    assert_allclose(e, [0.1, 0.2, 0.3] * 2)
    assert fields[0].calls[-1][2:] == (7, 5)
    basis = types.SimpleNamespace(templates=[1.5, 3.0], eps=[0.5, 2.0])
    J = star_jacobian(fields, subsets, basis, v, seed=5)
    assert_allclose(J, np.tile([[1.0], [2.0], [3.0]], (2, 2)))


def _weighted_system(Ja, Js, r_s, a_sig, s_sig, cols, prior_cols):
    """Rows sqrt(W) J and -sqrt(W) r of the data and of the priors of ``prior_cols``."""
    J = np.vstack([Ja[:, cols], Js[:, cols]])
    r = np.concatenate([np.zeros(Ja.shape[0]), r_s])
    s = np.concatenate([a_sig, s_sig])
    ok = np.isfinite(s)
    A, b = J[ok] / s[ok, None], -r[ok] / s[ok]
    prior = np.array([[1.0 if c == p else 0.0 for c in cols] for p in prior_cols]) / PRIOR_STEPS
    return np.vstack([A, prior.reshape(-1, len(cols))]), np.concatenate([b,
                                                                         np.zeros(len(prior))])


def test_solve_joint_against_direct_least_squares():
    """Two lag directions (no prior), a model direction the stars need ('m') and
    one nothing sees ('z'): 'm' is chosen, 'z' not; steps, covariances and the
    stars' leverage against the weighted least-squares solution and its hat
    matrix; an unfitted star row (error inf) weighs only in cov_all."""
    Ja = np.array([[1.0, 0.0, 0.2, 0.0], [0.0, 1.0, 0.1, 0.0], [0.3, 0.2, 0.0, 0.0]])
    Js = np.array([[0.5, 0.2, 2.0, 0.0], [0.1, 0.3, 1.0, 0.0], [0.4, 0.1, 1.5, 0.0]])
    r_s = np.array([4.0, 2.0, 3.0])
    a_sig = np.array([1.0, 2.0, 0.5])
    s_sig = np.array([0.1, 0.2, np.inf])
    s_all = np.array([0.1, 0.2, 0.3])
    is_lag = np.array([True, True, False, False])
    sol = solve_joint(Ja, Js, r_s, a_sig, s_sig, is_lag, ["l0", "l1", "m", "z"],
                      max_directions=3, star_sigma_all=s_all)
    assert sol["chosen"] == ["m"] and sol["cols"] == [0, 1, 2]
    assert [s["parameter"] for s in sol["selection"]] == [None, "m"]
    A, b = _weighted_system(Ja, Js, r_s, a_sig, s_sig, [0, 1, 2], [2])
    assert_allclose(sol["coef"], np.linalg.lstsq(A, b, rcond=None)[0], rtol=1e-9)
    cov = np.linalg.inv(A.T @ A)
    assert_allclose(sol["cov"], cov, rtol=1e-9)
    # the a-matrix rows and the prior alone (rows 0-2 and the last one of A)
    no_star = np.r_[0:3, A.shape[0] - 1]
    assert_allclose(sol["cov_flats"], np.linalg.inv(A[no_star].T @ A[no_star]), rtol=1e-9)
    # the trace of the hat matrix over the two fitted star rows (rows 3 and 4 of A)
    H = A @ cov @ A.T
    assert sol["star_leverage"] == pytest.approx(H[3, 3] + H[4, 4], rel=1e-9)
    A_all, _ = _weighted_system(Ja, Js, r_s, a_sig, s_all, [0, 1, 2], [2])
    assert_allclose(sol["cov_all"], np.linalg.inv(A_all.T @ A_all), rtol=1e-9)
    # without room for a model direction: the lags alone, and no cov_all asked
    sol0 = solve_joint(Ja, Js, r_s, a_sig, s_sig, is_lag, ["l0", "l1", "m", "z"],
                       max_directions=0)
    assert sol0["chosen"] == [] and sol0["cols"] == [0, 1] and sol0["cov_all"] is None
    A0, b0 = _weighted_system(Ja, Js, r_s, a_sig, s_sig, [0, 1], [])
    assert_allclose(sol0["coef"], np.linalg.lstsq(A0, b0, rcond=None)[0], rtol=1e-9)


def test_fit_joint_reaches_the_exact_minimum():
    """One direction, 'scale' (T(c) = (1 + c) T_a), a star field whose size slope
    is (1 + c)^2 - 1.44 (not linear in c: the finite-difference Jacobian is 2.25,
    the derivative at 0 is 2): the Gauss-Newton steps end at the minimum of
    the same chi2 (a-matrix, star and prior terms) found by scipy's scalar
    minimiser, and the reported a_ij change and residuals are the exact ones."""
    res = _calibration()
    ta = res.template
    table = AcoeffTable(res.table.a, 20.0 * res.table.sigma, source="loose")
    rows = AmatrixRows(table, ta)
    d = _scale_delta(ta)
    basis = DirectionBasis(["scale"], {"scale": 1.0}, [d], np.array([False]),
                           [combine_templates(ta, [d], [STAR_JACOBIAN_STEP])],
                           [STAR_JACOBIAN_STEP], amatrix_jacobian(rows, ta, [d]))
    err = 0.05

    def slopes(t, sub):
        k = 1.0 if t is None else _strength(t, ta)
        return {"size": (k ** 2 - 1.44, err), "e1": (0.3 * k, 1.0), "e2": (0.0, 1.0)}
    field = _Field("f", slopes)
    out = fit_joint({"f": field.usable}, [field], ta, basis, rows, max_directions=1,
                    iterations=6, n_boot=0)
    assert out["chosen"] == ["scale"]

    def chi2(c):  # the a-matrix rows measure the change from T_a: c alpha(T_a)
        return (np.sum((c * rows.start / rows.sigma) ** 2)
                + (((1 + c) ** 2 - 1.44) / err) ** 2 + (c / PRIOR_STEPS) ** 2)
    best = minimize_scalar(chi2, bounds=(-0.5, 1.0), method="bounded",
                           options={"xatol": 1e-10}).x
    sigma_c = math.sqrt(out["cov"][0, 0])
    assert abs(out["coef"][0] - best) < 0.05 * sigma_c
    # the linear solve alone (no Gauss-Newton step) is off by more
    linear = fit_joint({"f": field.usable}, [field], ta, basis, rows, max_directions=1,
                       iterations=0, n_boot=0)
    assert abs(linear["coef"][0] - best) > 0.2 * sigma_c
    k = _strength(out["t"], ta)
    assert k == pytest.approx(1 + out["coef"][0], rel=1e-12)
    assert_allclose(out["a_change"], out["coef"][0] * rows.start, rtol=1e-9,
                    atol=1e-9 * np.abs(rows.start).max())
    assert_allclose(out["r_fin"][rows.size:], [k ** 2 - 1.44, 0.3 * k, 0.0], rtol=1e-12)
    # e1 and e2 measured, not fitted
    assert np.isinf(out["sig_s"][1:]).all() and out["sig_u"][0] == err
    # a joint template the field cannot be corrected with (T_a and the direction's
    # template can): the error names the steps
    bad = _Field("f", slopes, fails=lambda t: t is not None and 1.1 < _strength(t, ta) < 1.24)
    with pytest.raises(CalibrationError, match=r"scale \+0\.\d+ steps\) cannot correct"):
        fit_joint({"f": bad.usable}, [bad], ta, basis, rows, max_directions=1, n_boot=0)


def _birge_fit(residuals, errors, leverage, calls):
    def fit(subsets, star_scale=1.0):
        calls.append(star_scale)
        return {"r_fin": np.concatenate([[9.0, 9.0], residuals]),
                "sig_s": np.asarray(errors) * star_scale, "star_leverage": leverage,
                "id": len(calls)}
    return fit


def test_fit_with_error_scale_birge_ratio():
    """Six fitted slopes scattering twice their errors, one parameter taken:
    refitted with sqrt(chi2 / (6 - 1)); within their errors, or asked not to: one fit."""
    r = np.array([2.0, -2.0, 2.0, -2.0, 2.0, -2.0])
    e = np.ones(6)
    calls = []
    final, scale, warns = fit_with_error_scale(_birge_fit(r, e, 1.0, calls), {}, n_amatrix=2)
    assert scale == pytest.approx(math.sqrt(24.0 / 5.0))
    assert calls == [1.0, scale] and final["id"] == 2
    assert warns == [f"the 6 fitted star slopes scatter {scale:.2f} times their bootstrap "
                     "errors after the fit; their errors were scaled by it"]
    calls = []
    final, scale, warns = fit_with_error_scale(_birge_fit(0.5 * e, e, 1.0, calls), {},
                                               n_amatrix=2)
    assert (scale, calls, warns, final["id"]) == (1.0, [1.0], [], 1)
    calls = []
    final, scale, warns = fit_with_error_scale(_birge_fit(r, e, 1.0, calls), {}, n_amatrix=2,
                                               scale_errors=False)
    assert (scale, calls, warns) == (1.0, [1.0], [])


def test_combine_folds_inverse_variance():
    def row(n, size, e1):
        s = {"size": size, "e1": e1, "e2": (0.0, 1.0), "n_stars": n}
        return {"before": s, "flats_only": s, "joint": s, "n_stars": n}
    out = combine_folds([row(5, (1.0, 0.1), (3.0, 1.0)), row(7, (2.0, 0.2), (1.0, 1.0))])
    assert out["n_stars"] == 12 and out["joint"]["n_stars"] == 12 and len(out["folds"]) == 2
    # size: weights 100 and 25
    assert out["joint"]["size"][0] == pytest.approx((100 * 1.0 + 25 * 2.0) / 125)
    assert out["joint"]["size"][1] == pytest.approx(1 / math.sqrt(125))
    assert out["before"]["e1"] == pytest.approx((2.0, 1 / math.sqrt(2)))


def test_cross_validate_measures_each_half_with_the_other_halfs_template():
    """Fold A is fitted on the A halves and measures the B halves with its template,
    and the other way round; the bootstrap uses seed + 1."""
    fits = []

    def fit(subsets):
        half = "A" if np.array_equal(subsets["f"], np.arange(10) % 2 == 0) else "B"
        fits.append(half)
        return {"t": f"T{half}", "chosen": [f"dir{half}"]}
    # size slope: which template and how many stars (the A half has 5, as the B half:
    # the first star of each half tells them apart)
    values = {None: 0.0, "Ta": 10.0, "TA": 20.0, "TB": 30.0}

    def slopes(t, sub):
        first = int(np.flatnonzero(sub)[0])
        return {"size": (values[t] + first, 1.0), "e1": (0.0, 1.0), "e2": (0.0, 1.0)}
    field = _Field("f", slopes)
    held = cross_validate([field], fit, "Ta", n_boot=3, seed=40)
    assert fits == ["A", "B"]
    folds = held["f"]["folds"]
    assert [f["fitted_on"] for f in folds] == ["half A", "half B"]
    assert [f["directions"] for f in folds] == [["dirA"], ["dirB"]]
    # fold A measures the B half (first star 1) with TA; fold B the A half with TB
    assert folds[0]["joint"]["size"][0] == 21.0 and folds[1]["joint"]["size"][0] == 30.0
    assert folds[0]["flats_only"]["size"][0] == 11.0 and folds[1]["before"]["size"][0] == 0.0
    assert held["f"]["joint"]["size"] == pytest.approx((25.5, 1 / math.sqrt(2)))
    assert {c[3] for c in field.calls} == {41} and {c[2] for c in field.calls} == {3}
    # one fit's held-out stars ('split', 'last')
    field.held_out = np.arange(10) >= 7
    out = held_out_validation([field], "Ta", "TB", n_boot=3, seed=40)
    assert out["f"]["joint"]["size"] == (37.0, 1.0) and out["f"]["n_stars"] == 3


# --------------------------------------------------------------------------- star_report

def _rows(sigma, labels=None):
    sigma = np.asarray(sigma, float)
    labels = labels or [f"a{k}0" for k in range(sigma.size)]
    return types.SimpleNamespace(size=sigma.size, sigma=sigma, labels=lambda: labels,
                                 start=np.zeros(sigma.size), measured=np.zeros(sigma.size))


def test_fit_chi2_and_tension_hand_case():
    """Two fields, size fitted: dof 2, p = exp(-x / 2); the four unfitted slopes:
    p = exp(-x / 2) (1 + x / 2); the worst pulls named."""
    rows = _rows([0.5, 1.0])
    rows.start, rows.measured = np.array([0.1, 0.0]), np.array([0.0, 0.3])
    fields = [types.SimpleNamespace(name="f0"), types.SimpleNamespace(name="f1")]
    sig_u = np.array([0.1, 0.2, 0.3, 0.1, 0.2, 0.3])
    scale = 2.0
    final = {"r_s0": np.array([0.4, 0.1, 0.2, 0.3, 0.0, 0.1]),
             "r_fin": np.array([0.2, -0.1, 0.05, 0.1, 0.2, 0.4, 0.1, 0.3]),
             "a_change": np.array([0.5, -0.2]), "sig_u": sig_u,
             "sig_s": np.where([1, 0, 0, 1, 0, 0], sig_u * scale, np.inf)}
    chi2, sig_s = fit_chi2(final, rows, scale)
    assert chi2["flats_only"]["amatrix"] == pytest.approx((0.1 / 0.5) ** 2 + 0.3 ** 2)
    assert chi2["flats_only"]["stars"] == pytest.approx(16.0 + 9.0)
    assert chi2["joint"]["amatrix"] == pytest.approx(0.16 + 0.01)
    assert chi2["joint"]["stars"] == pytest.approx(0.25 + 16.0)
    assert (chi2["n_amatrix"], chi2["n_stars"]) == (2, 2)
    tension, warns = tension_test(final, rows, sig_s, fields)
    rise = 1.0 + 0.04 + 0.25 + 16.0
    assert tension["chi2_rise"] == pytest.approx(rise) and tension["dof"] == 2
    assert tension["p_value"] == pytest.approx(math.exp(-rise / 2))
    x = (0.1 / 0.2) ** 2 + (0.2 / 0.3) ** 2 + (0.1 / 0.2) ** 2 + (0.3 / 0.3) ** 2
    u = tension["unfitted"]
    assert u["slopes"] == ["e1", "e2"] and u["dof"] == 4 and u["chi2"] == pytest.approx(x)
    assert u["p_value"] == pytest.approx(math.exp(-x / 2) * (1 + x / 2))
    # p = 1.8e-4 < 1e-3: the three largest pulls, f1:size (+4) first
    assert [w["what"] for w in tension["worst"]] == ["f1:size", "f0:size", "a00"]
    assert tension["worst"][0]["pull"] == pytest.approx(4.0)
    assert len(warns) == 1 and "worst: f1:size pull +4.0" in warns[0]
    # every slope fitted (one field): no unfitted entry; p = erfc(sqrt(x / 2)) for dof 1
    final1 = {"r_fin": np.array([0.0, 0.0, 0.1, 0.0, 0.0]), "a_change": np.zeros(2),
              "sig_u": np.ones(3), "sig_s": np.array([0.1, np.inf, np.inf])}
    t1, w1 = tension_test(final1, rows, final1["sig_s"], fields[:1],
                          fitted_slopes=("size", "e1", "e2"))
    assert "unfitted" not in t1 and "worst" not in t1 and w1 == []
    assert t1["p_value"] == pytest.approx(math.erfc(math.sqrt(0.5)))


def test_information_coefficients_and_lag_changes():
    rows = types.SimpleNamespace(sigma=np.array([1.0, 2.0]), lag_mask=np.array(
        [[True, True] + [False] * 9, [False, True] + [False] * 9] + [[False] * 11] * 8
        + [[True] + [False] * 10]), sigma_lags=None)
    rows.sigma_lags = np.where(rows.lag_mask, 0.5, np.nan)
    basis = types.SimpleNamespace(jacobian=np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 4.0]]),
                                  n_lag=2, steps={"m": 0.5})
    final = {"cols": [0, 1, 2], "chosen": ["m"], "Js": np.array([[0.0, 0.0, 3.0]]),
             "coef": np.array([0.1, 0.2, -1.5]), "cov": np.diag([1.0, 1.0, 0.04])}
    info = star_information(final, basis, rows, np.array([2.0]), star_scale=1.5)
    fa, fs = 2.0 ** 2 / 1.0 + 4.0 ** 2 / 4.0, 3.0 ** 2 / 3.0 ** 2
    assert info == {"m": pytest.approx(fs / (fa + fs))}
    coef = direction_coefficients(final, basis)
    assert coef == {"m": {"steps": -1.5, "steps_err": pytest.approx(0.2),
                          "parameter_change": -0.75, "parameter_change_err": pytest.approx(0.1),
                          "step": 0.5}}
    # rows in lag_mask order: (0, 0), (0, 1), (1, 1), (10, 0)
    pulls = lag_changes(np.array([0.1, -0.2, 0.3, 0.05]), rows)
    assert pulls == {"a00": (0.1, pytest.approx(0.2)), "a01": (-0.2, pytest.approx(-0.4)),
                     "a11": (0.3, pytest.approx(0.6)), "a10,0": (0.05, pytest.approx(0.1))}


def test_slope_precision_propagates_the_covariances():
    """sigma = sqrt(g C g) per field, g the slope's row of the star Jacobian; in %
    of the uncorrected size slope and of the e1 slope the flats template removes."""
    def slopes(t, sub):
        return {"size": (4.0 if t is None else 1.0, 0.1),
                "e1": (0.5 if t is None else 0.3, 0.1), "e2": (0.0, 0.1)}
    fields = [_Field("f", slopes)]
    final = {"cols": [1], "Js": np.array([[9.0, 2.0], [9.0, 0.5], [9.0, 0.0]]),
             "cov": np.array([[0.25]]), "cov_flats": np.array([[1.0]]),
             "cov_all": np.array([[0.01]])}
    size, e1 = slope_precision(final, fields, "Ta", n_boot=4, seed=9)
    assert size["f"] == {"flats": 2.0, "joint": 1.0, "flats_percent": 50.0,
                         "joint_percent": 25.0}
    assert e1["f"]["removed"] == pytest.approx(0.2)
    assert e1["f"]["joint"] == 0.25 and e1["f"]["joint_percent"] == pytest.approx(125.0)
    assert e1["f"]["all_fitted"] == pytest.approx(0.05)
    assert e1["f"]["all_fitted_percent"] == pytest.approx(25.0)
    assert {c[2:] for c in fields[0].calls} == {(4, 9)}


# --------------------------------------------------------------------------- star_fit

def test_read_and_split_fields():
    img = paired_fields()["images"][2]
    fields = read_star_fields([img, img.copy()])
    assert [f.name for f in fields] == ["field0", "field1"]
    given = [StarField(img, name="x"), StarField(img, name="x")]
    named = read_star_fields(given)
    assert [f.name for f in named] == ["x#0", "x#1"]
    assert [f.name for f in given] == ["x", "x"]  # copies renamed, the caller's kept
    with pytest.raises(CalibrationError, match="no star fields"):
        read_star_fields([])
    with pytest.raises(CalibrationError, match="star field field0: "):
        read_star_fields([np.random.default_rng(1).normal(800, 28, (128, 128))])
    f = fields[0]
    usable = f.usable.copy()
    assert all(w.endswith("excluded") for w in split_fields([f], "split", seed=3, min_stars=1))
    assert not np.any(f.fit_stars & f.held_out)
    assert np.array_equal(f.fit_stars | f.held_out, usable)
    # paired in flux: one star of each consecutive pair held out
    order = np.flatnonzero(usable)[np.argsort(np.asarray(f.catalog["flux"].value)[usable])]
    for k in range(0, order.size - 1, 2):
        assert f.held_out[order[k:k + 2]].sum() == 1
    split_fields([f], "cross", seed=3, min_stars=1)
    assert np.array_equal(f.fit_stars, usable) and np.array_equal(f.held_out, usable)
    assert not np.any(f.half_a & f.half_b) and np.array_equal(f.half_a | f.half_b, usable)
    n_half = int(min(f.half_a.sum(), f.half_b.sum()))
    with pytest.raises(CalibrationError, match=f"{n_half} usable stars to fit"):
        split_fields([f], "cross", seed=3, min_stars=n_half + 1)


def test_holdout_fields_and_progress_count():
    fields = ["a", "b", "c"]
    assert holdout_fields(fields, "auto") == ("cross", fields, fields)
    assert holdout_fields(fields, "last") == ("last", ["a", "b"], ["c"])
    with pytest.raises(InputError, match="holdout must be"):
        holdout_fields(fields, "half")
    with pytest.raises(CalibrationError, match="two or more"):
        holdout_fields(["a"], "last")
    # lag directions, one field, cross: 2 + (1 + 15 + 3 x 3) + 3 x 2
    assert progress_steps(0, 15, 1, 1, "cross", 2) == 33
    # model directions (8 candidates and 'scale'), two fitted fields, one held out
    assert progress_steps(9, 0, 2, 1, "last", 1) == 9 + 2 + 2 * (9 + 1 + 2) + 3


def test_result_assembly():
    res = _calibration()
    ta = res.template
    ta_meta = dict(ta.meta)
    t = joint_template(ta, ta, {"holdout": "cross"})
    assert t is not ta and ta.meta == ta_meta  # a copy; the input is not modified
    assert t.meta["calibration"]["stars"] == {"holdout": "cross"}
    for k, v in ta.meta.get("calibration", {}).items():
        if k == "uncertainty":  # the flats' parameter modes are not carried
            assert "parameter_modes" not in t.meta["calibration"][k]
            v = {n: u for n, u in v.items() if n != "parameter_modes"}
        assert t.meta["calibration"][k] == v
    for k in _ARRAYS:
        if getattr(ta, k) is not None:
            assert np.array_equal(getattr(t, k), getattr(ta, k))
    other = combine_templates(ta, [_scale_delta(ta)], [0.1])
    assert joint_template(other, ta, {}) is other
    # the flats' parameter modes leave the uncertainty; the input keeps them
    unc = {"kind": "data", "sigma": [[1e-8]], "parameter_modes": {"size": 3}}
    moded = combine_templates(ta, [], [], meta={**ta.meta, "calibration": {"uncertainty": unc}})
    t = joint_template(moded, moded, {"holdout": "cross"})
    assert t.meta["calibration"]["uncertainty"] == {"kind": "data", "sigma": [[1e-8]]}
    assert moded.meta["calibration"]["uncertainty"] is unc and "parameter_modes" in unc

    def slopes(tmp, sub):
        return {"size": ({None: 1.0, "Ta": 2.0, "Tj": 3.0}[tmp], 0.1), "e1": (0.0, 0.1),
                "e2": (0.0, 0.1)}
    f0, f1 = _Field("f0", slopes), _Field("f1", slopes)
    f1.fit_stars = np.arange(10) < 6
    f0.held_out = np.arange(10) < 3
    f0.n_detections, f1.n_detections = 12, 10
    f0.flag_counts = f1.flag_counts = {"saturated": 1}
    table = fitted_star_slopes([f1], "Ta", "Tj", n_boot=2, seed=8)
    assert [table["f1"][k]["size"][0] for k in ("before", "flats_only", "joint")] == [1, 2, 3]
    assert table["f1"]["joint"]["n_stars"] == 6 and {c[2:] for c in f1.calls} == {(2, 8)}
    info = fields_summary([f0, f1], [f1], [f0])
    assert info == [{"name": "f0", "kind": "stars", "n_detections": 12, "n_usable": 10,
                     "n_fit": 0, "n_held_out": 3, "flagged": {"saturated": 1}},
                    {"name": "f1", "kind": "stars", "n_detections": 10, "n_usable": 10,
                     "n_fit": 6, "n_held_out": 0, "flagged": {"saturated": 1}}]
