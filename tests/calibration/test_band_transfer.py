"""Tests of lsst_bfdrift.calibration.band_transfer: one calibration carried to every band."""

import dataclasses

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.calibration.band_transfer import band_a00_table, calibrated_band_templates
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.bands import build_band_templates
from lsst_bfdrift.templates.refine import draw_templates, template_alpha
from lsst_bfdrift.templates.template import DistortionTemplate, TemplateSettings, build_template

NODES = 3


@pytest.fixture(scope="module")
def calibrated():
    """A tiny 'calibrated' template: built at the paper's sensor (entrance window), its
    displacements 5 % larger (what a refinement to the data would do), calibration meta."""
    params = SensorParameters.paper()
    settings = TemplateSettings(size=3, edge_samples=2, tol=1e-2, workers=1)
    t = build_template(params, settings)
    k = 1.05
    meta = dict(t.meta, calibration={
        "max_lag": 1, "names": ["channel_depth"],
        "uncertainty": {"kind": "data", "sigma": [[2e-8, 1e-8], [1e-8, 5e-9]]}})
    return DistortionTemplate(t.corner_d * k, t.vedge_d * k, t.hedge_d * k, t.fractions,
                              t.charge, meta=meta)


@pytest.fixture(scope="module")
def transferred(calibrated):
    return calibrated_band_templates(calibrated, "r_57", bands=("u", "r", "y"), nodes=NODES)


def test_flats_band_keeps_the_calibrated_template(calibrated, transferred):
    """CONSISTENCY: band B's template is the calibrated one, with its band recorded."""
    for name in ("corner_d", "vedge_d", "hedge_d"):
        assert_allclose(getattr(transferred["r"], name), getattr(calibrated, name), rtol=0)
    info = transferred["r"].meta["calibration"]["band"]
    assert info["flats"] == "r" and info["ratio"][0][0] == 1.0
    assert transferred.meta["calibration_band"] == "r"


def test_other_bands_add_the_model_change(calibrated, transferred):
    """CONSISTENCY: T_X - T_B equals the model's M_X - M_B (built separately here), and the
    chromatic change goes the physical way (u distorts more than r, y less)."""
    params = SensorParameters.from_dict(calibrated.meta["params"])
    settings = TemplateSettings.from_dict(calibrated.meta["settings"])
    model = build_band_templates(params, ("u", "r", "y"), settings=settings, nodes=NODES)
    for x in ("u", "y"):
        assert_allclose(transferred[x].corner_d - calibrated.corner_d,
                        model[x].corner_d - model["r"].corner_d, atol=1e-12)
    a = {x: template_alpha(transferred[x])[1, 1] for x in ("u", "r", "y")}
    assert a["u"] < a["r"] < a["y"] < 0  # a00 < 0; |a00| smallest in y


def test_uncertainty_scaled_by_the_band_ratio(transferred):
    """CORRECTNESS: the stored a00 error is |r00| x the calibration's, and templates drawn
    from it (draw_templates, an independent code path) scatter a00 by that error."""
    rows = band_a00_table(transferred)
    for x in ("u", "r", "y"):
        r00 = rows[x]["ratio_a00"]
        assert_allclose(rows[x]["a00_err"], abs(r00) * 2e-8, rtol=1e-12)
    assert rows["y"]["ratio_a00"] < 1.0 < rows["u"]["ratio_a00"]
    draws = draw_templates(transferred["y"], 60, seed=5)
    a00 = np.array([template_alpha(t)[1, 1] for t in draws])
    assert_allclose(a00.std(ddof=1), rows["y"]["a00_err"], rtol=0.3)


def test_parameter_modes_scaled_by_the_a00_ratio(calibrated):
    """CONSISTENCY: a band's stored parameter modes are the calibration's times |r00|."""
    modes = {"size": 3, "corner_d": np.ones((1, 4, 4, 2)).tolist(),
             "vedge_d": np.full((1, 3, 4), 2e-4).tolist(),
             "hedge_d": np.full((1, 4, 3), -1e-4).tolist()}
    meta = dict(calibrated.meta, calibration={
        **calibrated.meta["calibration"],
        "uncertainty": {**calibrated.meta["calibration"]["uncertainty"],
                        "parameter_modes": modes}})
    t = DistortionTemplate(calibrated.corner_d, calibrated.vedge_d, calibrated.hedge_d,
                           calibrated.fractions, calibrated.charge, meta=meta)
    mb = calibrated_band_templates(t, "r_57", bands=("u", "r"), nodes=NODES)
    r00 = band_a00_table(mb)["u"]["ratio_a00"]
    got = mb["u"].meta["calibration"]["uncertainty"]["parameter_modes"]
    assert_allclose(got["vedge_d"], 2e-4 * abs(r00) * np.ones((1, 3, 4)), rtol=1e-12)
    assert_allclose(got["hedge_d"], -1e-4 * abs(r00) * np.ones((1, 4, 3)), rtol=1e-12)
    assert abs(r00) != 1.0 and modes["vedge_d"][0][0][0] == 2e-4  # the input is kept


def test_parameter_uncertainty(calibrated):
    """CORRECTNESS: kind 'parameters': a00 error = |r00| sqrt(J C J^T) at lag 0."""
    jac = np.array([[[3e-7], [1e-7]], [[1e-7], [2e-8]]])
    cov = np.array([[0.04]])
    meta = dict(calibrated.meta, calibration={
        "max_lag": 1, "uncertainty": {"kind": "parameters", "jacobian": jac.tolist(),
                                      "covariance": cov.tolist(), "names": ["channel_depth"]}})
    t = DistortionTemplate(calibrated.corner_d, calibrated.vedge_d, calibrated.hedge_d,
                           calibrated.fractions, calibrated.charge, meta=meta)
    mb = calibrated_band_templates(t, "g", bands=("g", "z"), nodes=NODES)
    row = band_a00_table(mb)["z"]
    ref = abs(row["ratio_a00"]) * 3e-7 * 0.2
    assert_allclose(row["a00_err_params"], ref, rtol=1e-12)
    assert_allclose(row["a00_err"], ref, rtol=1e-12)


def test_refusals(calibrated):
    bare = DistortionTemplate(calibrated.corner_d, calibrated.vedge_d, calibrated.hedge_d,
                              calibrated.fractions, calibrated.charge,
                              meta={k: v for k, v in calibrated.meta.items()
                                    if k != "calibration"})
    with pytest.raises(ValueError, match="lacks calibration in its metadata"):
        calibrated_band_templates(bare, "r")
    with pytest.raises(ValueError, match="unknown band 'q'"):
        calibrated_band_templates(calibrated, "q")
    with pytest.raises(TypeError, match="template must be a DistortionTemplate"):
        calibrated_band_templates("cal.fits", "r")
    other = dataclasses.replace(TemplateSettings.from_dict(calibrated.meta["settings"]), size=5)
    meta = dict(calibrated.meta, settings=other.to_dict())
    wrong = DistortionTemplate(calibrated.corner_d, calibrated.vedge_d, calibrated.hedge_d,
                               calibrated.fractions, calibrated.charge, meta=meta)
    with pytest.raises(ValueError, match="do not match the calibrated template"):
        calibrated_band_templates(wrong, "r", bands=("r",), nodes=NODES)
