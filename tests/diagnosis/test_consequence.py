"""Tests of what an added effect changes in the calibration and for stars
(lsst_bfdrift.diagnosis.consequence).

star_consequence is checked against the linear response of the correction
to the template's strength (the package's own forward model on both sides:
a consistency test); template_change against its own inputs (the basis'
a_ij) and the real calibrate."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.calibration.acoeff_model import load_default_basis
from lsst_bfdrift.diagnosis.consequence import base_acoeffs, star_consequence, template_change
from lsst_bfdrift.diagnosis.report import diagnosis_markdown, template_change_lines
from lsst_bfdrift.simulation.skysim import scale_template
from lsst_bfdrift.templates.template import load_default_template


@pytest.fixture(scope="module")
def template():
    return load_default_template()


@pytest.mark.parametrize("strength", [0.8, 1.0, 1.25])
def test_star_consequence_follows_the_template_strength(template, strength):
    """Correcting with s x the true template leaves 1 - s of both slopes (to
    first order in the BF strength; the stars' a mu stays below 0.1)."""
    r = star_consequence(template, scale_template(template, strength))
    assert_allclose(r["size_left"], 1.0 - strength, atol=0.01)
    assert_allclose(r["e1_left"], 1.0 - strength, atol=0.01)
    assert r["size_slope"]["uncorrected"] > 0  # BF makes bright stars larger


def test_star_consequence_bad_input(template):
    with pytest.raises(ValueError, match="fluxes"):
        star_consequence(template, template, fluxes=[1e4])
    with pytest.raises(ValueError, match="fwhm"):
        star_consequence(template, template, fwhm=0.0)


def _diag(basis, shift):
    """A diagnosis dictionary whose final base parameters are moved by
    ``shift`` x each parameter's error."""
    x0 = dict(basis.x0)
    err = dict(basis.errors)
    moved = {n: v + shift * err[n] for n, v in x0.items()}
    step = lambda p: {"base_params": p, "base_errors": err}  # noqa: E731
    return {"kind": "table", "steps": [step(x0), step(moved)], "effects_added": ["x"]}


def test_base_acoeffs_propagate_the_basis(template):
    basis = load_default_basis()
    d = _diag(basis, 2.0)
    a, s = base_acoeffs(d["steps"][1], basis, 2)
    x = [d["steps"][1]["base_params"][n] for n in basis.names]
    assert_allclose(a, basis.a(x, 2), rtol=1e-12)
    e = np.array([basis.errors[n] for n in basis.names])
    assert_allclose(s[0, 1], np.sqrt(np.sum((basis.jacobian[0, 1] * e) ** 2)), rtol=1e-12)
    # with the fit's covariance (correlated parameters): against the scatter of
    # a_ij over parameters drawn from it (independent Monte Carlo reference)
    n = len(basis.names)
    corr = np.full((n, n), -0.6 / (n - 1)) + np.eye(n) * (1 + 0.6 / (n - 1))
    cov = corr * np.outer(e, e)
    step = dict(d["steps"][1], base_covariance=cov.tolist())
    _, s_cov = base_acoeffs(step, basis, 2)
    draws = np.random.default_rng(11).multivariate_normal(x, cov, 20000)
    mc = np.std([basis.a(v, 2) for v in draws], axis=0)
    assert_allclose(s_cov, mc, rtol=0.03)
    assert not np.allclose(s_cov, s, rtol=0.03)  # the correlations matter


def test_template_change_below_threshold_calibrates_nothing():
    basis = load_default_basis()
    tc = template_change(_diag(basis, 0.1), basis, max_lag=2)
    assert tc["available"] and not tc["changed"] and "templates" not in tc
    assert abs(tc["largest_shift"]) < 1.0
    assert "does not change" in "\n".join(template_change_lines(tc))
    assert not template_change({"kind": "ptc", "steps": []}, None)["available"]
    one = _diag(basis, 2.0)
    one["steps"] = one["steps"][:1]
    assert template_change(one, basis)["reason"] == "no effect was added"


def test_template_change_calibrates_both_sides(template, monkeypatch):
    """A shift of 3 errors in every parameter: both sides are calibrated from
    their base a_ij, and the stars are drawn with the side with the effects
    and corrected with the other. calibrate (tested in test_tuning.py, about
    a minute a side) is replaced by templates of known strength: 0.9 x the
    bundled one without the effects, the bundled one with them, so 10 % of
    both slopes must be left."""
    from types import SimpleNamespace

    from lsst_bfdrift.calibration import tuning

    basis = load_default_basis()
    d = _diag(basis, 3.0)
    seen = {}

    def fake(table, **kw):
        side = "with" if table.source.endswith("with effects") else "without"
        seen[side] = table.a.copy()
        t = template if side == "with" else scale_template(template, 0.9)
        return SimpleNamespace(template=t, template_acoeffs=table.a,
                               fit=SimpleNamespace(chi2_dof=1.0))

    monkeypatch.setattr(tuning, "calibrate", fake)
    tc = template_change(d, basis, max_lag=2)
    assert tc["changed"] and set(tc["templates"]) == {"without effects", "with effects"}
    for side, step in (("without", 0), ("with", 1)):
        assert_allclose(seen[side], base_acoeffs(d["steps"][step], basis, 2)[0], rtol=1e-12)
    assert_allclose(tc["stars"]["size_left"], 0.1, atol=0.01)
    assert_allclose(tc["stars"]["e1_left"], 0.1, atol=0.01)
    d["template_change"] = tc
    d.update(n_points=1, note="", candidates=[], not_identifiable={}, verdict="v")
    d["steps"] = [dict(s, label=f"s{k}", chi2_dof=1.0, chi2=1.0, dof=1, rms_pull=1.0,
                       rms_residual=0.0, largest_residuals=[],
                       effects=[{"name": "x", "params": {}, "errors": {}}][:k])
                  for k, s in enumerate(d["steps"])]
    md = diagnosis_markdown(d)
    assert "What the added effects change" in md and "+10.0 % of the size-flux slope" in md
