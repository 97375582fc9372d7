"""Tests of lsst_bfdrift.validation on stars drawn by galsim.SiliconSensor."""

import pytest

from lsst_bfdrift.template import DistortionTemplate
from lsst_bfdrift.validation import _slope, draw_star_pairs, validate_stars


def test_slope_through_origin():
    s, e = _slope([1.0, 2.0, 3.0], [2.0, 4.0, 6.0])
    assert s == pytest.approx(2.0) and e == pytest.approx(0.0, abs=1e-12)


def test_corrections_remove_most_of_the_galsim_bf_slope():
    pairs = draw_star_pairs(30, flux=(3e5, 1.5e6), seed=7)
    assert all(p["bf"].shape == (41, 41) for p in pairs)
    res = validate_stars(pairs, DistortionTemplate.from_galsim("lsst_itl_50_8"))
    unc = res["uncorrected"]["size_slope"]
    # the BF effect of lsst_itl_50_8 is clearly detected (MODEL_NOTES: ~1e-3 per 1e5 e)
    assert unc > 10 * res["uncorrected"]["size_slope_err"] and 2e-4 < unc < 3e-3
    for m in ("coulton18", "astier23", "drift"):
        assert abs(res[m]["size_slope"]) < 0.15 * unc  # >= 85 % removed
    assert res["drift"]["n_stars"] >= 25


def test_needs_stars():
    with pytest.raises(ValueError, match="n_stars"):
        draw_star_pairs(0)
