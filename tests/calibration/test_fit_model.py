"""Tests of lsst_bfdrift.calibration.fit_model: the model the calibration fits."""

import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.calibration import fit_model


def test_shipped_start_jacobian_equals_a_fresh_computation():
    """Consistency (package against itself): the package-data start Jacobian
    equals a fresh forward difference at the default start (lags <= 2, two
    candidates), and is used only where it applies."""
    start = fit_model.default_start()
    cands = {n: fit_model.CANDIDATES[n] for n in ("xi0", "channel_depth")}
    m0, J, src = fit_model.start_jacobian(start, cands, 2)
    assert src == "package data" and m0.shape == (3, 3) and J.shape == (3, 3, 2)
    calls = []

    def model(values):
        calls.append(values)
        return fit_model.model_acoeffs(start.replace(**values), 2)

    fresh = fit_model._compute_jacobian(model, {n: float(getattr(start, n)) for n in cands}, cands)
    assert len(calls) == 3
    assert_allclose(m0, fresh[0], rtol=1e-12, atol=0)
    assert_allclose(J, fresh[1], rtol=1e-12, atol=1e-25)
    # another start, other bounds, or lags beyond the file: computed
    ms = fit_model.MODEL_SETTINGS
    assert fit_model._shipped(start.replace(xi0=start.xi0 * 1.01), cands, 2, ms) is None
    assert fit_model._shipped(start, {"xi0": (1.0, 2e4)}, 2, ms) is None
    assert fit_model._shipped(start, cands, fit_model.START_JACOBIAN_MAX_LAG + 1, ms) is None
    assert fit_model._shipped(start, cands, 2, fit_model.CONVERGED_MODEL_SETTINGS) is None
    with pytest.raises(ValueError, match="model settings must be a dict"):
        fit_model.model_acoeffs(start, 2, settings={"near_samples": 32})
