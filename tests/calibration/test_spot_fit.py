"""Tests of lsst_bfdrift.calibration.spot_fit (joint a-matrix + spot-series calibration).

Kinds:

* hand-computed small cases: the rows each data set fits, a direction
  always in the fit (against the direct least-squares solution), the
  tension's drivers;
* wiring with a real spot series: halves of spots and of images, the
  minimum of spots, the reading of several series;
* consistency (the package's forward model on both sides): spots recorded
  through a template whose divergence-free part differs from the flats
  template's; the joint fit moves the template's e1 toward the spots';
* independent data: a spot series drawn by galsim.SiliconSensor with
  GalSim's own a-matrix: the joint calibration runs, states its tension and
  its held-out spots.
"""

import functools
import types

import numpy as np
import pytest
from numpy.testing import assert_allclose

from tests.calibration._spot_series import curl_free_spots, forward_spot_images
from tests.calibration.test_star_fit import _calibration
from lsst_bfdrift.calibration.spot_fit import (MIN_FIT_SPOTS, SpotField, calibrate_with_spots,
                                               read_spot_fields)
from lsst_bfdrift.calibration.star_fit import split_fields
from lsst_bfdrift.calibration.star_report import tension_drivers
from lsst_bfdrift.calibration.star_solve import fitted_rows, solve_joint
from lsst_bfdrift.calibration.tuning import CalibrationError, CalibrationResult
from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs
from lsst_bfdrift.simulation.spots import simulate_spot_series
from lsst_bfdrift.templates.refine import (lag_multiplicity, match_area_coefficients,
                                           template_alpha)
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.utils.errors import InputError


# --------------------------------------------------------------------------- hand cases

def test_each_data_set_fits_its_own_slopes():
    """A spot series fits the slopes it states (size, e1, e2); a star field
    (none stated) the calibration's."""
    spots = types.SimpleNamespace(fitted_slopes=("size", "e1", "e2"))
    field = types.SimpleNamespace()
    assert fitted_rows([field, spots], ("size",)).tolist() == [True, False, False,
                                                               True, True, True]
    assert fitted_rows([spots, field], ("size", "e2")).tolist() == [True, True, True,
                                                                    True, False, True]


def test_a_direction_always_in_the_fit_is_solved_with_its_prior():
    """One star slope of 0.5 that only 'c' moves (1 per step): the drop of its
    chi2 (0.225 with the prior of 3 steps) is below ln N, so 'c' is not
    chosen; always in, it is first in ``chosen`` and its step is the direct
    solution with its prior, -0.5 / (1 + 1/9)."""
    Ja = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    Js = np.array([[0.0, 0.01, 1.0]])
    args = (Ja, Js, np.array([0.5]), np.ones(2), np.ones(1), np.array([True, False, False]),
            ["l0", "m", "c"])
    free = solve_joint(*args, max_directions=2)
    assert free["chosen"] == [] and free["cols"] == [0]
    fixed = solve_joint(*args, max_directions=0, always=("c", "absent"))
    assert fixed["chosen"] == ["c"] and fixed["cols"] == [0, 2]
    assert_allclose(fixed["coef"], [0.0, -0.5 / (1 + 1 / 9)], atol=1e-12)
    assert_allclose(fixed["cov"][1, 1], 1 / (1 + 1 / 9))


def test_tension_drivers_name_the_lags_moved_and_the_slopes_left():
    """Lags by |a_ij change / error|, fitted slopes by |value / error| after
    the fit (the unfitted e2 is not a driver), with their pulls at T_a."""
    rows = types.SimpleNamespace(size=2, sigma=np.array([0.5, 1.0]),
                                 labels=lambda: ["a00", "a10"])
    final = {"a_change": np.array([0.5, -3.0]),
             "r_fin": np.array([9.0, 9.0, 0.05, -0.3, 7.0]),
             "r_s0": np.array([0.2, 0.6, 7.0])}
    fields = [types.SimpleNamespace(name="s")]
    d = tension_drivers(final, rows, np.array([0.1, 0.2, np.inf]), fields)
    assert [(x["what"], x["pull"]) for x in d["lags"]] == [("a10", -3.0), ("a00", 1.0)]
    assert [x["what"] for x in d["slopes"]] == ["s:e1", "s:size"]
    assert d["slopes"][0]["pull"] == pytest.approx(-1.5)
    assert d["slopes"][0]["pull_flats"] == pytest.approx(3.0)
    assert d["slopes"][1]["value"] == pytest.approx(0.05)


# --------------------------------------------------------------------------- SpotField

@functools.lru_cache(maxsize=None)
def _small_series():
    """4 x 4 spots through the bundled template, 5 images (cheap: no calibration)."""
    images, times = forward_spot_images(load_default_template(), grid=4)
    return SpotSeries(images, exptimes=times)


def test_spot_field_halves_minimum_and_reading():
    """Halves of spots are disjoint and keep every row of a spot on one side;
    halves of images keep every spot on both; a series short of spots per
    half is refused with the count; one or several series are read."""
    series = _small_series()
    f = SpotField(series)
    assert (f.kind, f.fitted_slopes, f.n_detections) == ("spots", ("size", "e1", "e2"), 16)
    assert f.usable.sum() == 80 and f.min_spots == MIN_FIT_SPOTS
    assert split_fields([f], "cross", seed=3) == []
    a, b = set(f.spot[f.half_a]), set(f.spot[f.half_b])
    assert not a & b and len(a) == len(b) == 8
    assert np.array_equal(f.half_a | f.half_b, f.usable)
    assert np.array_equal(f.fit_stars, f.usable) and np.array_equal(f.held_out, f.usable)
    s = f.slopes(None, f.half_a)
    assert set(s) == {"size", "e1", "e2", "n_stars"} and s["n_stars"] == 40
    assert s["size"][0] > 5 * s["size"][1]                 # the bundled template's BF
    assert s == f.slopes(None, f.half_a)
    g = SpotField(series, split_by="images")
    split_fields([g], "split", seed=3)
    assert set(g.spot[g.fit_stars]) == set(g.spot[g.held_out]) == set(range(16))
    assert not set(g.image[g.fit_stars]) & set(g.image[g.held_out])
    h = SpotField(series, min_spots=9)
    with pytest.raises(CalibrationError, match=r"spot series spots: 8 usable spots to fit per "
                                               r"half .*need at least 9 spots"):
        split_fields([h], "cross", seed=3)
    split_fields([h], "last", seed=3)  # all 16 spots fitted
    assert [x.name for x in read_spot_fields([series, series])] == ["spots0", "spots1"]
    # a field given is copied: its split stays the caller's
    given = SpotField(series, name="mine")
    read = read_spot_fields(given)[0]
    split_fields([read], "split", seed=3)
    assert read is not given and read.name == "mine" and read.held_out.any()
    assert not given.held_out.any() and np.array_equal(given.fit_stars, given.usable)
    with pytest.raises(CalibrationError, match="no spot series"):
        read_spot_fields([])
    with pytest.raises(InputError, match="split_by must be one of"):
        SpotField(series, split_by="rows")
    with pytest.raises(InputError, match="spot fitted_slopes must be a non-empty subset"):
        SpotField(series, fitted_slopes=("e3",))


# --------------------------------------------------------------------------- the joint fit

def test_spots_pin_the_divergence_free_part_the_flats_cannot_see():
    """Consistency (the drift forward model makes the spots, the Task
    corrects them): spots of a sensor whose boundary shifts are curl-free,
    with the flats template's a_ij. The a-matrix cannot tell the two apart;
    the spots' e1 slope can. The joint fit (curl always in, e1 fitted) moves
    the template along ``curl`` toward the truth's -1 step, at no a-matrix
    cost; the e1 slope the template predicts for the spots (drift forward
    model) moves toward the measured one, the fitted and the held-out spots
    (two-fold cross-validation over halves of the spots) keep less of their
    e1 slope, and their size slope stays corrected."""
    res = _calibration()
    truth, images, times = curl_free_spots()
    series = SpotSeries(images, exptimes=times)
    # spots made by the correction's own forward model: it inverts them exactly, so the
    # correction's error on real photons (correction_bias) does not apply
    joint = calibrate_with_spots(res, series, seed=3, iterations=1, correction_bias=False)
    name = joint.fields[0]["name"]
    assert joint.fields[0]["kind"] == "spots" and joint.fields[0]["n_detections"] == 25
    assert joint.directions[0] == "curl"
    curl = joint.coefficients["curl"]["steps"]
    assert -1.3 < curl < -0.3, joint.coefficients
    # the fitted spots: e1 left by the flats template, less by the joint one
    fs = joint.fit_slopes[name]
    e1_true = series.slopes(truth)["e1"][0]
    miss_flats = fs["flats_only"]["e1"][0] - e1_true
    miss_joint = fs["joint"]["e1"][0] - e1_true
    assert abs(miss_flats) > 1e-5
    assert abs(miss_joint) < 0.6 * abs(miss_flats), (miss_flats, miss_joint)
    assert abs(fs["joint"]["size"][0]) < 0.01 * fs["before"]["size"][0]
    # the prediction of the drift forward model, on four spots: toward the measured e1
    rows = np.isin(np.asarray(series.catalog["spot"]), [0, 1, 2, 3])
    measured = series.fit(use=rows)["e1"]["slope"]
    pred = {k: series.predict(t, use=rows, quantities=("size", "e1"))["e1"]["slope"]
            for k, t in (("flats", res.template), ("joint", joint.template))}
    assert abs(measured - pred["joint"]) < abs(measured - pred["flats"]), (measured, pred)
    # held-out spots: each half measured with the template fitted to the other half
    held = joint.held_out[name]
    assert held["kind"] == "spots" and [f["fitted_on"] for f in held["folds"]] == \
        ["half A", "half B"]
    assert abs(held["joint"]["e1"][0] - e1_true) < abs(held["flats_only"]["e1"][0] - e1_true)
    assert "held-out spots of spots0 (two-fold cross-validation)" in joint.held_out_table()
    # the a-matrix does not pay for it; the data agree
    assert joint.chi2["joint"]["amatrix"] - joint.chi2["flats_only"]["amatrix"] < 1.0
    assert joint.tension["p_value"] > 0.01 and joint.tension["dof"] == 3
    assert "driven by the a_ij moved" in joint.tension_line()
    meta = joint.template.meta["calibration"]["spots"]
    assert meta["directions"][0] == "curl" and meta["kinds"] == ["spots"]
    print(f"curl {curl:+.3f} +- {joint.coefficients['curl']['steps_err']:.3f} steps; fitted "
          f"e1 slope (per 1e5 e) before {fs['before']['e1'][0]:+.3e}, flats "
          f"{fs['flats_only']['e1'][0]:+.3e}, joint {fs['joint']['e1'][0]:+.3e}, truth "
          f"{e1_true:+.3e} (err {fs['joint']['e1'][1]:.1e}); predicted e1 on 4 spots: "
          f"measured {measured:+.3e}, flats {pred['flats']:+.3e}, joint {pred['joint']:+.3e}; "
          f"held-out e1 flats {held['flats_only']['e1'][0]:+.3e}, joint "
          f"{held['joint']['e1'][0]:+.3e}; {joint.tension_line()}")


def test_galsim_spots_and_galsim_a_matrix_calibrate_jointly():
    """Independent data: a 3 x 3 spot series drawn by galsim.SiliconSensor
    (lsst_itl_50_8, 4 exposures to near full well) and GalSim's a-matrix of
    the same sensor (errors 3 % + 1e-9 per e) on the bundled model. The
    joint calibration runs with cross-validation over halves of the spots,
    states its tension (p-value, the lags and slopes that drive it) and the
    held-out spots' slopes: their size slope is seen before correction and
    mostly removed by either template."""
    base = _calibration()
    a = galsim_acoeffs("lsst_itl_50_8", 3)
    table = AcoeffTable(a, 0.03 * np.abs(a) + 1e-9, source="galsim lsst_itl_50_8")
    ta = match_area_coefficients(base.built_template, table.a, max_lag=3)
    res = CalibrationResult(params=base.params, table=table, template=ta,
                            built_template=base.built_template, settings=base.settings,
                            candidates=base.candidates)
    sim = simulate_spot_series(grid=(3, 3), n_images=4, peak_max=8e4, full_well=1e5, seed=3,
                               updates=100)
    series = SpotSeries(sim["images"], exptimes=sim["exptimes"], saturation=1e5)
    given = SpotField(series, name="spots0")
    joint = calibrate_with_spots(res, given, seed=3, iterations=1)
    # the caller's field is left as it was: not split or given a bias
    assert given.bias == {} and not given.held_out.any()
    # photons, not the forward model: the correction's own slopes on the design are asked
    bias = joint.fields[0]["correction_bias"]
    assert set(bias) == {"size", "e1", "e2"} and bias["size"][1] > 0
    assert abs(bias["size"][0]) < 0.05 * joint.held_out["spots0"]["before"]["size"][0]
    t = joint.tension
    assert 0.0 <= t["p_value"] <= 1.0 and t["dof"] == 3
    assert len(t["drivers"]["lags"]) == 3 and t["drivers"]["lags"][0]["what"].startswith("a")
    assert {d["what"] for d in t["drivers"]["slopes"]} == {"spots0:size", "spots0:e1",
                                                           "spots0:e2"}
    held = joint.held_out["spots0"]
    before, flats, fixed = (held[k]["size"] for k in ("before", "flats_only", "joint"))
    assert before[0] > 3 * before[1]
    assert abs(flats[0]) < 0.3 * before[0] and abs(fixed[0]) < 0.3 * before[0]
    assert joint.fields[0]["n_held_out"] == joint.fields[0]["n_usable"]
    print(joint.tension_line())
    print(joint.held_out_table())


def test_spots_move_the_area_the_template_sends_beyond_the_measured_lags():
    """Consistency (the drift forward model makes the spots, the Task
    corrects them): a sensor whose a00 is 10 % weaker than the flats' a00
    (2 of its errors), the area made up beyond the measured lags 0..3, seen
    through spots of 1.5 and 2.5 px. With the a-matrix's directions kept on
    the measured lags' area sum (``keep_lag_sum=True``, the star route's
    default) the fit cannot send less area beyond lag 3: that sum stays the
    flats template's, the two spot sizes stay in tension and keep a third of
    their size slope or more. With the full errors (the spot route's
    default) the sum moves to the truth's, the held-out spots of both sizes
    keep under 3 % of their size slope and the tension is gone."""
    res = _calibration()
    a_truth = res.table.a.copy()
    a_truth[0, 0] *= 0.9
    truth = match_area_coefficients(res.built_template, a_truth, max_lag=3)
    series = []
    for sigma, pitch, margin in ((1.5, 26, 20), (2.5, 44, 32)):
        images, times = forward_spot_images(truth, sigma=sigma, pitch=pitch, margin=margin)
        series.append(SpotSeries(images, exptimes=times))

    def lag_sum(t):
        c = t.center
        return float(np.sum(lag_multiplicity(3) * template_alpha(t)[c:c + 4, c:c + 4].T))

    s_flats, s_truth = lag_sum(res.template), lag_sum(truth)
    assert abs(s_flats - s_truth) > 0.05 * abs(res.table.a[0, 0])
    kept, free = (calibrate_with_spots(res, series, seed=3, iterations=1, correction_bias=False,
                                       keep_lag_sum=k) for k in (True, False))
    assert kept.template.meta["calibration"]["spots"]["keep_lag_sum"] is True
    assert free.template.meta["calibration"]["spots"]["keep_lag_sum"] is False
    assert_allclose(lag_sum(kept.template), s_flats, atol=0.01 * abs(s_flats - s_truth))
    assert abs(lag_sum(free.template) - s_truth) < 0.1 * abs(s_flats - s_truth)
    assert kept.tension["p_value"] < 1e-3 < free.tension["p_value"]
    for name in ("spots0", "spots1"):
        before = free.held_out[name]["before"]["size"][0]
        assert abs(kept.held_out[name]["joint"]["size"][0]) > 0.3 * before
        assert abs(free.held_out[name]["joint"]["size"][0]) < 0.03 * before
