"""Tests of lsst_bfdrift.calibration.star_fit (joint a-matrix + star-field calibration).

Kinds:

* exactness of the linear family (direct recomputation of the area response
  of the combined template: a consistency check of the algebra);
* detections reused on the same image give the catalog of a fresh
  detection (consistency);
* the joint fit on a star field drawn by galsim.SiliconSensor (independent
  data): a flats template 40 % too weak is pulled back by the stars, by the
  model's directions or within the a-matrix's errors, and the held-out stars
  (two-fold cross-validation: each half measured with the template fitted to
  the other half) show it.
"""

import functools

import numpy as np
import pytest
from astropy.utils.exceptions import AstropyUserWarning
from numpy.testing import assert_allclose

from tests.validation._galsim_fields import STRENGTHS, paired_fields
from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.catalogs.catalog import detect_stars, measure_stars
from lsst_bfdrift.calibration.star_fit import StarField, calibrate_with_stars
from lsst_bfdrift.calibration.fit_model import CANDIDATES
from lsst_bfdrift.calibration.tuning import CalibrationError, CalibrationResult
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs
from lsst_bfdrift.simulation.skysim import scale_template
from lsst_bfdrift.templates.refine import (area_response_directions, combine_templates,
                                          curl_free_template, match_area_coefficients,
                                          template_alpha, template_difference)
from lsst_bfdrift.templates.template import TemplateSettings, build_template
from lsst_bfdrift.utils.errors import InputError

STRENGTH = STRENGTHS[2]


@functools.lru_cache(maxsize=None)
def _calibration():
    """A calibration result without the search (the bundled sensor's parameters,
    an 11 x 11 template with 8 samples per edge) whose template is refined to
    GalSim ITL's a-matrix at the field's BF strength."""
    a = STRENGTH * galsim_acoeffs("lsst_itl_50_8", 3)
    table = AcoeffTable(a, 0.05 * np.abs(a) + 1e-9, source="galsim lsst_itl_50_8 x10")
    settings = TemplateSettings(size=11, edge_samples=8, tol=1e-4, aggressor_charge=1e4)
    params = SensorParameters()
    built = build_template(params, settings)
    template = match_area_coefficients(built, table.a, max_lag=3)
    return CalibrationResult(params=params, table=table, template=template,
                             built_template=built, settings=settings,
                             candidates=dict(CANDIDATES))


def test_detections_reused_on_the_same_image_give_the_same_catalog():
    img = paired_fields()["images"][2]
    det = detect_stars(img)
    a = measure_stars(img)
    b = measure_stars(img, detections=det)
    assert len(a) == len(b) == len(det.centroids)
    for col in ("x", "y", "flux", "T", "e1", "e2", "flags"):
        assert_allclose(np.asarray(b[col]), np.asarray(a[col]))
    with pytest.raises(ValueError, match="differs from the detections"):
        measure_stars(img[:-1], detections=det)


def test_star_field_measured_on_given_detections():
    """A StarField given another field's detections (here its own) measures the
    same stars row by row as measure_stars does on them, and refuses a
    mismatched image."""
    img = paired_fields()["images"][2]
    own = StarField(img)
    again = StarField(img.copy(), detections=own.detections)
    assert again.detections is own.detections
    for col in ("x", "y", "flux", "T", "e1", "e2", "flags"):
        assert_allclose(np.asarray(again.catalog[col]), np.asarray(own.catalog[col]))
    assert np.array_equal(again.usable, own.usable)
    with pytest.raises(ValueError, match="differs from the detections"):
        StarField(img[:-1], detections=own.detections)


def test_stars_pull_a_weak_template_back_and_held_out_stars_show_it():
    res = _calibration()
    img = paired_fields()["images"][2]
    weak = scale_template(res.template, 0.5)
    # a weak flats template, and an a-matrix too noisy to say so: only the stars can (the
    # a-matrix rows measure the change from the flats template, its own estimate)
    loose = AcoeffTable(res.table.a, 50.0 * res.table.sigma, source="loose")
    res_weak = type(res)(**{**res.__dict__, "template": weak, "table": loose})
    # the model's directions alone (the flats' own uncertainty: the next test)
    joint = calibrate_with_stars(res_weak, [img], min_stars=8, seed=3, flats_uncertainty=False)
    assert joint.directions[0] == "scale"
    assert joint.uncertainty is None
    assert joint.star_information["scale"] > 0.5
    # the scale found restores the template within its error (0.5 -> 1: +1)
    sc = joint.coefficients["scale"]
    assert abs(sc["steps"] - (1 / 0.5 - 1)) < max(3 * sc["steps_err"], 0.25)
    held = joint.held_out["field0"]
    before, weak_s, fixed = (held[k]["size"] for k in ("before", "flats_only", "joint"))
    assert before[0] > 5 * before[1]                  # BF seen on the held-out stars
    assert weak_s[0] > 2 * weak_s[1]                  # the weak template leaves BF
    assert abs(fixed[0]) < 0.5 * weak_s[0]            # the stars' fit removes most of it
    assert abs(fixed[0]) < 3 * fixed[1]
    # two-fold cross-validation: the template fitted to every usable star, and each
    # star held out once, from the fold fitted to the other half (disjoint halves)
    info = joint.fields[0]
    assert info["n_fit"] == info["n_held_out"] == info["n_usable"]
    folds = held["folds"]
    assert [f["fitted_on"] for f in folds] == ["half A", "half B"]
    assert folds[0]["n_stars"] + folds[1]["n_stars"] == info["n_usable"]
    assert "two-fold cross-validation" in joint.held_out_table()
    # the figure of the held-out validation draws the three slopes with their errors
    from lsst_bfdrift.calibration.plots import plot_star_calibration
    fig = plot_star_calibration(joint)
    ax = fig.axes[0]
    drawn = [c for c in ax.containers if hasattr(c, "lines")]
    assert len(drawn) == 3
    assert_allclose(drawn[2].lines[0].get_ydata()[0], fixed[0])
    assert fig.axes[2].get_yticklabels()[0].get_text() == "scale"
    import matplotlib.pyplot as plt
    plt.close(fig)


@pytest.mark.parametrize("fitted", [("size",), ("size", "e1", "e2")])
def test_stars_undo_a_flats_error_within_the_a_matrix_errors(fitted):
    """A flats template off by 3 sigma of its a-matrix (a_ij known to 100 %
    per lag, sum rule kept), along the direction of those errors that the
    field's size slope sees most: the stars move it back within the
    a-matrix's errors (no model direction allowed), by about the Gaussian update's
    share k^2 / (1 + k^2) (k: the size slope's change per step over its
    error, about 1.3 here), and the held-out stars (two-fold
    cross-validation) show most of the size slope the error left removed. The
    reported a_ij change is the templates' exact polygon areas' and keeps the
    measured lags' area (sum rule); the field is drawn by galsim.SiliconSensor.
    Fitting the size slope alone (the default) or with e1 and e2 does it
    alike; the slopes not fitted are reported as a check."""
    res = _calibration()
    img = paired_fields()["images"][2]
    table = AcoeffTable(res.table.a, 20.0 * res.table.sigma, source="100 %")
    right = res.template
    modes = area_response_directions(right, table.sigma[:4, :4], max_lag=3)
    field = StarField(img)
    s0 = field.slopes(right, field.usable)
    moved = [field.slopes(combine_templates(right, [m["delta"]], [1.0]), field.usable)
             for m in modes.values()]
    g = np.array([s["size"][0] - s0["size"][0] for s in moved])
    g1 = np.array([s["e1"][0] - s0["e1"][0] for s in moved])
    g2 = np.array([s["e2"][0] - s0["e2"][0] for s in moved])
    u = g / np.linalg.norm(g)
    wrong = combine_templates(right, [m["delta"] for m in modes.values()], 3.0 * u)
    # the a-matrix's directions alone (max_directions=0: no model direction)
    joint = calibrate_with_stars(type(res)(**{**res.__dict__, "template": wrong,
                                              "table": table}), [img], min_stars=8, seed=3,
                                 max_directions=0, fitted_slopes=fitted)
    assert joint.directions == []
    assert joint.tension["dof"] == joint.chi2["n_stars"] == len(fitted)
    assert joint.star_error_scale == 1.0  # fewer than six fitted slopes: no estimate
    if len(fitted) == 1:
        unfit = joint.tension["unfitted"]
        assert unfit["slopes"] == ["e1", "e2"] and unfit["dof"] == 2
        assert 0 <= unfit["p_value"] <= 1
        assert "e1, e2 not fitted, after the fit chi2" in joint.tension_line()
    else:
        assert "unfitted" not in joint.tension
    unc = joint.uncertainty
    assert unc["n_directions"] == 15                  # 16 lags (a00 too) less the sum rule
    steps = np.array([unc["steps"][n] for n in modes])
    # back along the error, by a good part of its 3 sigma, and less elsewhere
    assert -3.5 < steps @ u < -1.0
    assert np.linalg.norm(steps - (steps @ u) * u) < abs(steps @ u)
    assert 1.0 < unc["chi2"] < 12.0
    held = joint.held_out["field0"]
    before, wrong_s, fixed = (held[k]["size"] for k in ("before", "flats_only", "joint"))
    right_s = field.slopes(right, field.usable)["size"]
    assert abs(wrong_s[0] - right_s[0]) > 2 * wrong_s[1]   # the flats error shows
    assert abs(fixed[0] - right_s[0]) < 0.6 * abs(wrong_s[0] - right_s[0])
    # the reported a_ij change, against the templates' exact polygon areas
    c = right.center
    change = (template_alpha(joint.template) - template_alpha(wrong))[c:c + 4, c:c + 4].T
    for lag, v in unc["a_change"].items():
        assert_allclose(change[int(lag[1]), int(lag[2])], v, rtol=1e-9,
                        atol=1e-9 * np.abs(change).max())
    assert_allclose(unc["chi2"], np.sum((change / table.sigma[:4, :4]) ** 2), rtol=1e-9)
    npix = np.array([[1, 2, 2, 2]] + [[2, 4, 4, 4]] * 3)
    assert abs(np.sum(npix * change)) < 0.02 * np.abs(npix * change).sum()
    assert "within the a-matrix's errors (15 directions)" in joint.uncertainty_line()
    # the size slope's uncertainty, against the direct computation: the steps are one
    # a-matrix error each (prior covariance I), so the flats leave sigma = |g|, and one
    # size slope of error e updates it as a scalar Gaussian: |g| e / sqrt(|g|^2 + e^2)
    ss = unc["size_slope_sigma"]["field0"]
    assert_allclose(ss["flats"], np.linalg.norm(g), rtol=0.2)  # g: at the right template
    if len(fitted) == 1:
        e = joint.fit_slopes["field0"]["flats_only"]["size"][1]
        assert_allclose(ss["joint"], ss["flats"] * e / np.hypot(ss["flats"], e), rtol=0.05)
    assert ss["joint"] < ss["flats"]
    assert_allclose(ss["flats_percent"],
                    100 * ss["flats"] / abs(joint.fit_slopes["field0"]["before"]["size"][0]))
    assert "with the stars" in joint.uncertainty_line()
    # the fields the 3 % goal would take, against the scalar Gaussian update of the
    # flats' precision by fields of this field's slope error (in % of its slope)
    goal = joint.uncertainty["fields_for_size_goal"]
    assert goal["goal_percent"] == 3.0
    if len(fitted) == 1:
        assert ss["joint_percent"] > 3.0  # one small field: short of the goal
        e_pct = 100 * e / abs(joint.fit_slopes["field0"]["before"]["size"][0])
        direct = e_pct ** 2 * (1 / 3.0 ** 2 - 1 / ss["flats_percent"] ** 2)
        assert abs(goal["fields"] - direct) <= 0.12 * direct + 1
        assert any(w.startswith(f"the corrected size slope is known to +- "
                                f"{ss['joint_percent']:.1f} %") and
                   f"about {goal['fields']} fields like these" in w for w in joint.warnings)
    # the e1 slope's, alike (|g1|), in % of the e1 slope the flats template removes
    s1 = unc["e1_slope_sigma"]["field0"]
    assert_allclose(s1["flats"], np.linalg.norm(g1), rtol=0.2)
    fs = joint.fit_slopes["field0"]
    assert_allclose(s1["removed"], fs["before"]["e1"][0] - fs["flats_only"]["e1"][0],
                    rtol=1e-12)
    assert_allclose(s1["flats_percent"], 100 * s1["flats"] / abs(s1["removed"]))
    assert s1["joint"] <= s1["flats"] * (1 + 1e-9)
    # with all three slopes fitted, the Gaussian update of a unit prior by the three rows
    # (the direct computation): what the fit gives when it fits them, and what it
    # states it would give when it fits size alone
    errs = [fs["flats_only"][k][1] for k in ("size", "e1", "e2")]
    post = np.linalg.inv(np.eye(g.size) + sum(np.outer(v, v) / e ** 2
                                              for v, e in zip((g, g1, g2), errs)))
    s1_all = np.sqrt(g1 @ post @ g1)
    if len(fitted) == 1:
        assert_allclose(s1["all_fitted"], s1_all, rtol=0.1)
        assert s1["all_fitted"] < s1["joint"]
        assert "with the e1 and e2 slopes fitted too" in joint.uncertainty_line()
    else:
        assert_allclose(s1["joint"], s1_all, rtol=0.1)
        assert "all_fitted" not in s1
    assert "the e1 slope to +- " in joint.uncertainty_line()
    # a-matrix errors of 100 % per lag leave the e1 correction unknown, and the report says so
    assert s1["joint_percent"] > 100
    assert any(w.startswith(f"the corrected e1 slope is uncertain by +- "
                            f"{s1['joint_percent']:.0f} %") for w in joint.warnings)


@pytest.mark.slow
def test_star_errors_scaled_by_the_fields_scatter_and_tension_kept():
    """Two galsim.SiliconSensor fields of different brighter-fatter strength (5 and
    10), size, e1 and e2 fitted (six slopes): no template nulls both, so they
    scatter about the fit beyond their bootstrap errors. The fit's errors are
    scaled by the Birge ratio (against the direct sum: the a-matrix, known to
    5 %, leaves the stars almost no parameter, so chi2 / 6), and the warning
    states it; the chi2 and the tension keep the bootstrap errors, so the
    disagreement is still reported, and the scaled stars pull the template
    less (a consistency check of the mechanism on independent fields)."""
    res = _calibration()
    imgs = paired_fields()["images"]
    kw = dict(min_stars=8, seed=3, max_directions=0, fitted_slopes=("size", "e1", "e2"))
    raw = calibrate_with_stars(res, [imgs[2], imgs[1]], scale_star_errors=False, **kw)
    scaled = calibrate_with_stars(res, [imgs[2], imgs[1]], **kw)
    assert raw.star_error_scale == 1.0
    s = scaled.star_error_scale
    assert_allclose(s ** 2, raw.chi2["joint"]["stars"] / 6.0, rtol=0.03)
    assert s > 1.5
    assert any(f"6 fitted star slopes scatter {s:.2f} times" in w for w in scaled.warnings)
    assert raw.tension["p_value"] < 1e-2 and scaled.tension["p_value"] < 1e-2
    assert_allclose(scaled.chi2["flats_only"]["stars"], raw.chi2["flats_only"]["stars"],
                    rtol=1e-12)
    assert scaled.chi2["joint"]["amatrix"] < 0.5 * raw.chi2["joint"]["amatrix"]
    assert scaled.summary()["star_error_scale"] == s
    # a-matrix errors of 5 % pin the e1 correction well enough: no e1 warning
    e1 = [v["joint_percent"] for v in scaled.uncertainty["e1_slope_sigma"].values()]
    assert np.mean(e1) < 100
    assert not any("e1 slope is uncertain" in w for w in scaled.warnings)


def test_bad_star_inputs_get_clear_errors():
    res = _calibration()
    img = paired_fields()["images"][2]
    with pytest.raises(CalibrationError, match=r"usable stars to fit .*need at least 30"):
        calibrate_with_stars(res, [img])
    with pytest.raises(CalibrationError, match="no star fields"):
        calibrate_with_stars(res, [])
    with pytest.raises(CalibrationError, match="two or more"):
        calibrate_with_stars(res, [img], holdout="last", min_stars=8)
    with pytest.raises(CalibrationError, match="no sources detected"):
        calibrate_with_stars(res, [np.random.default_rng(1).normal(800, 28, (128, 128))])
    nores = type(res)(**{**res.__dict__, "template": None})
    with pytest.raises(CalibrationError, match="template built"):
        calibrate_with_stars(nores, [img])
    with pytest.raises(InputError, match="fitted_slopes must be a non-empty subset"):
        calibrate_with_stars(res, [img], min_stars=8, fitted_slopes=("size", "e3"))
    with pytest.raises(InputError, match="size_goal must be a finite precision > 0"):
        calibrate_with_stars(res, [img], min_stars=8, size_goal=0.0)


def test_saturated_and_masked_stars_are_excluded_and_counted():
    """A field clipped below its brightest peaks (no saturation level given) and
    with a NaN on another star: the clipped stars are flagged saturated (the
    level taken from the flat top), the NaN one masked; the report counts
    both, and the input image is not modified."""
    res = _calibration()
    img = paired_fields()["images"][0].copy()
    level = 0.7 * img.max()  # below the two brightest stars' cores
    img = np.minimum(img, level)
    iy, ix = np.unravel_index(np.argsort(np.where(img < 0.3 * level, img, 0).ravel())[-1],
                              img.shape)
    img[iy, ix] = np.nan
    before = img.copy()
    with pytest.warns(AstropyUserWarning, match="flat top"):
        out = calibrate_with_stars(res, [img], min_stars=8)
    np.testing.assert_array_equal(img, before)
    sat = [w for w in out.warnings if "saturated stars excluded" in w]
    masked = [w for w in out.warnings if "masked or non-finite" in w]
    assert len(sat) == 1 and int(sat[0].split(": ")[1].split()[0]) >= 1
    assert len(masked) == 1 and masked[0].startswith("field0: 1 stars")


def test_curl_direction_moves_e1_and_not_the_a_matrix():
    """The 'curl' direction (the template minus the curl-free template with
    its areas) leaves every a_ij unchanged (exact polygon areas) and, on a
    galsim.SiliconSensor star field, moves the corrected stars' e1 slope (the
    serial/parallel partition of the boundary shifts), not e2 (the model is
    symmetric about both axes) nor, to 1 % of the BF slope, their size."""
    res = _calibration()
    ta = res.template
    c = ta.center
    d = template_difference(ta, curl_free_template(ta))
    field = StarField(paired_fields()["images"][2])
    a0 = template_alpha(ta)[c:c + 4, c:c + 4]
    s = {}
    for k in (-1.0, 1.0):
        t = combine_templates(ta, [d], [k])
        assert_allclose(template_alpha(t)[c:c + 4, c:c + 4], a0, rtol=0,
                        atol=1e-5 * abs(a0[0, 0]))
        s[k] = field.slopes(t, field.usable)
    before = field.slopes(None, field.usable)
    de1, de2, dsize = (s[1.0][n][0] - s[-1.0][n][0] for n in ("e1", "e2", "size"))
    assert abs(de1) > 20 * abs(de2)
    assert abs(dsize) < 0.01 * before["size"][0]
    assert abs(de1) > 1e-3 * before["size"][0]


def test_a_right_template_is_left_alone():
    # the flats template already corrects the field: no direction passes the ln N test
    res = _calibration()
    img = paired_fields()["images"][2]
    loose = AcoeffTable(res.table.a, 50.0 * res.table.sigma, source="loose")
    joint = calibrate_with_stars(type(res)(**{**res.__dict__, "table": loose}), [img],
                                 min_stars=8, seed=3, holdout="split", flats_uncertainty=False)
    assert joint.directions == []
    # one seeded half fitted, the other held out
    info = joint.fields[0]
    assert info["n_fit"] + info["n_held_out"] == info["n_usable"]
    held = joint.held_out["field0"]
    assert held["joint"]["size"] == held["flats_only"]["size"]
    assert abs(held["joint"]["size"][0]) < 3 * held["joint"]["size"][1]


def test_a_field_of_another_sensor_is_reported_as_tension():
    # flats of a sensor with BF strength 10 (a-matrix to 5 %), stars of one with
    # strength 5 (GalSim fields, same photons): no template satisfies both, and
    # the report names the size slope of the stars as the data that pull
    res = _calibration()
    joint = calibrate_with_stars(res, [paired_fields()["images"][1]], min_stars=8, seed=3)
    assert joint.tension["p_value"] < 1e-4
    assert joint.tension["worst"][0]["what"] == "field0:size"
    assert joint.tension["worst"][0]["pull"] < -4      # the flats template over-corrects
    assert any(w.startswith("tension between the a-matrix and the stars") for w in joint.warnings)
    # the same flats with this sensor's own stars: no tension
    own = calibrate_with_stars(res, [paired_fields()["images"][2]], min_stars=8, seed=3)
    assert own.tension["p_value"] > 0.05
    assert "worst" not in own.tension
