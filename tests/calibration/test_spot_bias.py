"""Tests of lsst_bfdrift.calibration.spot_bias (the correction's own slopes on a spot design).

Kinds:

* exact: with a template that moves no boundary, the simulated spots and
  their square-pixel twins are the same image and the correction does
  nothing, so every slope is 0 (the pairing and the measurement are right);
* consistency (the package's photon simulation against its own correction,
  both with the bundled template): on spots of sigma 1 px the drift
  correction over-corrects the fixed-weight size growth by a few %, on
  2 px it leaves under 1 % (the finding of
  ``benchmarks/calibration/spots_truth.py``, where GalSim's file on GalSim's
  spots shows the same difference between the sizes);
* wiring: a SpotField subtracts a stated bias from the slopes a correction
  leaves (not from the measured ones) and adds its error in quadrature;
  bad input is refused with a clear message.
"""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from tests.calibration._spot_series import forward_spot_images
from lsst_bfdrift.calibration.spot_bias import spot_correction_bias
from lsst_bfdrift.calibration.spot_fit import SpotField
from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.templates.template import DistortionTemplate, load_default_template
from lsst_bfdrift.utils.errors import InputError

LEVELS = np.geomspace(5e4, 4e5, 3)


def _series(sigma, levels=LEVELS):
    t = load_default_template()
    images, times = forward_spot_images(t, grid=3, pitch=40, levels=levels, sigma=sigma,
                                        margin=30)
    return SpotSeries(images, exptimes=times)


def _flat_template(t):
    """The bundled template with no boundary moved."""
    z = np.zeros_like
    return DistortionTemplate(z(t.corner_d), z(t.vedge_d), z(t.hedge_d), t.fractions, t.charge)


def test_a_template_that_moves_nothing_leaves_exactly_nothing():
    series = _series(1.5)
    b = spot_correction_bias(series, _flat_template(load_default_template()), centres=2)
    for q in ("size", "e1", "e2"):
        assert b[q] == (0.0, 0.0)
    assert b["n_spots"] == 4 and b["levels"].size == 3
    # the drawn spots are the series' own: its faint-limit covariance, round, ~1.5 px
    assert_allclose(np.sqrt(np.diag(b["covariance"])), 1.5, rtol=0.05)
    assert abs(b["covariance"][0, 1]) < 0.02


def test_undersampled_spots_are_over_corrected_and_wide_ones_not():
    t = load_default_template()
    small, wide = _series(1.0), _series(2.0, levels=np.geomspace(2e5, 8e5, 3))
    before_small = small.slopes(None)["size"][0]
    before_wide = wide.slopes(None)["size"][0]
    b1 = spot_correction_bias(small, t, centres=3, seed=5)
    b2 = spot_correction_bias(wide, t, centres=2, seed=5)
    f1, e1 = 100 * b1["size"][0] / before_small, 100 * b1["size"][1] / before_small
    f2, e2 = 100 * b2["size"][0] / before_wide, 100 * b2["size"][1] / before_wide
    print(f"size left by the correction: sigma 1 px {f1:+.2f} +- {e1:.2f} %, "
          f"sigma 2 px {f2:+.2f} +- {e2:.2f} %")
    assert -5.0 < f1 < -0.5 and f1 + 3 * e1 < 0
    assert abs(f2) < 1.0
    assert f2 - f1 > 1.0


def test_spot_field_subtracts_a_stated_bias_from_corrected_slopes_only():
    series = _series(1.5)
    t = load_default_template()
    plain = SpotField(series)
    biased = SpotField(series, bias={"size": (1e-4, 3e-5), "e1": (-2e-5, 0.0)})
    rows = plain.usable
    assert biased.slopes(None, rows) == plain.slopes(None, rows)
    p, b = plain.slopes(t, rows), biased.slopes(t, rows)
    assert_allclose(b["size"][0], p["size"][0] - 1e-4, rtol=0, atol=1e-15)
    assert_allclose(b["size"][1], np.hypot(p["size"][1], 3e-5), rtol=1e-12)
    assert_allclose(b["e1"], (p["e1"][0] + 2e-5, p["e1"][1]), rtol=0, atol=1e-15)
    assert b["e2"] == p["e2"]


def test_bad_input_is_refused():
    series = _series(1.5)
    with pytest.raises(InputError, match="centres must be a positive integer"):
        spot_correction_bias(series, load_default_template(), centres=0)
    with pytest.raises(InputError, match=r"bias must map 'size', 'e1', 'e2' to \(slope, error\)"):
        SpotField(series, bias={"size": 1e-4})
    with pytest.raises(InputError, match="bias slopes must be finite with errors >= 0"):
        SpotField(series, bias={"size": (np.nan, 1e-5)})
    with pytest.raises(InputError, match="bias slopes must be finite with errors >= 0"):
        SpotField(series, bias={"size": (1e-4, -1e-5)})
