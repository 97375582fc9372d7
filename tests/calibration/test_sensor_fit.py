"""Tests of lsst_bfdrift.calibration.sensor_fit: the fitting routine offered to users."""

import pytest

from lsst_bfdrift.calibration.sensor_fit import fit_sensor_parameters, template_numbers
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import TemplateSettings

FAST = TemplateSettings(size=3, edge_samples=2, tol=3e-4, workers=1)


def test_recovers_channel_depth_of_known_model():
    """Closure: targets made by a model with d_ch = 2.6 um, fit from 2.3 um."""
    truth = SensorParameters.paper(channel_depth=2.6)
    s = template_numbers(truth, FAST)
    targets = {"A00": (s["A00"], 5e-4), "A01": (s["A01"], 2e-4)}
    res = fit_sensor_parameters(targets, SensorParameters.paper(channel_depth=2.3),
                                {"channel_depth": (0.5, 8.0)}, settings=FAST, max_nfev=4)
    assert res.values["channel_depth"] == pytest.approx(2.6, abs=3 * res.errors["channel_depth"]
                                                        + 0.02)
    assert res.errors["channel_depth"] > 0 and res.chi2 < 4.0
    assert [r[0] for r in res.table()] == ["A00", "A01"]


@pytest.mark.parametrize("kw, match", [
    (dict(targets={}), "no targets"),
    (dict(targets={"A00": (0.9, 0.0)}), "sigma"),
    (dict(targets={"A00": (0.9, 1e-3)}, free={}), "no free"),
    (dict(targets={"A00": (0.9, 1e-3)}, free={"channel_depth": (3.0, 8.0)}), "outside"),
])
def test_bad_arguments(kw, match):
    args = dict(targets=None, params0=SensorParameters.paper(), free={"channel_depth": (0.5, 8.0)})
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        fit_sensor_parameters(args.pop("targets"), args.pop("params0"), args.pop("free"))


def test_template_numbers_name_every_lag_serial_then_parallel():
    from lsst_bfdrift.templates.template import build_template
    st = TemplateSettings(size=5, edge_samples=2, tol=3e-4, workers=1)
    s = template_numbers(SensorParameters.paper(), st)
    ref = build_template(SensorParameters.paper(), st).summary()
    # the generic lag keys (written over the summary's) agree with the
    # summary's own nearest neighbours (A01 parallel, A10 serial)
    for k in ("A00", "A01", "A10", "A11"):
        assert s[k] == pytest.approx(ref[k], abs=1e-12)
    assert s["A01"] > s["A10"] > 1.0
    assert {"A02", "A20", "A22", "A12", "A21"} <= set(s) and "A03" not in s


# Measured area coefficients of an LSST ITL sensor (per e; i serial, j
# parallel): shared/data/measured/itl_covariances_21oct19.txt, lags (0, 1),
# (1, 0), (1, 1), (0, 2), (2, 0): mean and standard deviation.
ITL_MEASURED = {(0, 1): (1.761e-07, 1.206e-08), (1, 0): (7.245e-08, 1.061e-08),
                (1, 1): (4.347e-08, 8.110e-09), (0, 2): (2.216e-08, 6.027e-09),
                (2, 0): (2.264e-08, 1.079e-08)}


def test_default_template_is_calibrated_to_the_measured_itl_sensor():
    """The bundled default template against measured data (not its own numbers)."""
    import json
    import math

    from lsst_bfdrift.cli.main import read_config
    from lsst_bfdrift.templates.template import default_template_path, load_default_template
    t = load_default_template()
    a = t.moments().area
    c = t.center
    for (i, j), (mean, sig) in ITL_MEASURED.items():
        model = math.log(a[c + j, c + i]) / t.charge
        assert abs(model - mean) < 2 * sig, (i, j, model, mean)
    # a00 (-1.044e-6 +- 1.5e-8, its sum-rule value) is in the fit
    assert abs(math.log(a[c, c]) / t.charge + 1.044e-6) < 3 * 1.5e-8
    # >= 16 samples per edge (8 leave 6e-4 on A00)
    assert t.edge_samples >= 16
    # the configuration that documents it holds the parameters it was built
    # with, and its provenance names the fitted values
    cfg_path = default_template_path().replace(".fits", "_config.json")
    params, settings = read_config(cfg_path)
    # (as parameters: the template predates charge_variance_parallel, default 0)
    assert SensorParameters.from_dict(t.meta["params"]) == params
    with open(cfg_path) as fh:
        prov = json.load(fh)["provenance"]
    for k, v in prov["values"].items():
        assert getattr(params, k) == pytest.approx(v, rel=1e-3)
    assert prov["chi2"] >= 0 and set(prov["errors"]) == set(prov["values"])
    # one source of defaults: SensorParameters.paper() is the bundled template's sensor
    assert SensorParameters() == params
    assert t.meta["calibration"]["a00_in_fit"]
