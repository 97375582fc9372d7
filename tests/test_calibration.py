"""Tests of lsst_bfdrift.calibration: the fitting routine offered to users."""

import pytest

from lsst_bfdrift.calibration import fit_sensor_parameters, template_numbers
from lsst_bfdrift.sensor import SensorParameters
from lsst_bfdrift.template import TemplateSettings

FAST = TemplateSettings(size=3, edge_samples=2, tol=3e-4, workers=1)


def test_recovers_channel_depth_of_known_model():
    """Closure: targets made by a model with d_ch = 2.6 um, fit from 2.3 um."""
    truth = SensorParameters(channel_depth=2.6)
    s = template_numbers(truth, FAST)
    targets = {"A00": (s["A00"], 5e-4), "A01": (s["A01"], 2e-4)}
    res = fit_sensor_parameters(targets, SensorParameters(channel_depth=2.3),
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
    args = dict(targets=None, params0=SensorParameters(), free={"channel_depth": (0.5, 8.0)})
    args.update(kw)
    with pytest.raises(ValueError, match=match):
        fit_sensor_parameters(args.pop("targets"), args.pop("params0"), args.pop("free"))
