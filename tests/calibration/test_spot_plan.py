"""Tests of lsst_bfdrift.calibration.spot_plan (how many spots a lab needs).

Kinds:

* correctness against Monte Carlo: the propagated row errors of a spot
  against the scatter of noisy realisations measured the same way;
* correctness against GalSim: the peak pixel's share of a Gaussian spot;
* correctness against the analytic Gaussian update: the spots needed for a
  goal, in one direction, where the update is exact;
* consistency: the information of a design against the package's own spot
  fit's formal error; the plan's wiring with a stated result;
* physics: the slope a template predicts falls with the spot's size;
* bad input: each refusal names the value.
"""

import types

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy.special import erf

from lsst_bfdrift.calibration.spot_plan import (SpotDesign, design_information,
                                                gaussian_peak_fraction, information_ratio,
                                                plan_spot_acquisition, precision_for_spots,
                                                predicted_slope, spot_row_errors,
                                                spots_for_precision)
from lsst_bfdrift.catalogs.spot_slopes import fit_spot_slope
from lsst_bfdrift.catalogs.spots import RADIUS_FACTOR, fixed_weight_moments
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.utils.errors import InputError


def test_row_errors_match_the_scatter_of_noisy_spots():
    """CORRECTNESS (Monte Carlo): the e1 and size errors of a spot row are the standard
    deviations of the same measurement over Poisson + read-noise realisations."""
    rng = np.random.default_rng(42)
    d = SpotDesign(sigma=1.5, levels=(1e4, 2e5), read_noise=5.0, background=20.0)
    ws = d.weight
    radius = max(RADIUS_FACTOR * ws, 3.0)
    half = int(np.ceil(radius)) + 1
    edges = np.arange(-half, half + 2) - 0.5
    p1 = np.diff(0.5 * (1 + erf(edges / (np.sqrt(2) * d.sigma))))
    unit = np.outer(p1, p1) / p1.sum() ** 2
    for flux in (2e4, 3e5):
        vals = {"e1": [], "size": []}
        for _ in range(400):
            img = rng.poisson(flux * unit + d.background).astype(float) - d.background
            img += rng.normal(0.0, d.read_noise, img.shape)
            m = fixed_weight_moments(img, weight_sigma=ws, radius=radius, center=(half, half),
                                     tol=1e-6)
            for q in vals:
                vals[q].append(m[q])
        for q in vals:
            pred = spot_row_errors([flux], d, quantity=q)[0]
            # 400 draws: the standard deviation is known to 3.5 %
            assert_allclose(np.std(vals[q], ddof=1), pred, rtol=0.12)


def test_peak_fraction_is_galsims_peak_pixel():
    """CORRECTNESS (GalSim): the share of a pixel-centred Gaussian's flux in its peak pixel."""
    galsim = pytest.importorskip("galsim")
    for sigma in (1.0, 1.5, 3.0):
        img = galsim.Gaussian(sigma=sigma).drawImage(nx=31, ny=31, scale=1.0)
        # GalSim's k-space drawing is accurate to ~1e-4 of the peak (its gsparams);
        # a point-sampled centre would be 4-20 % off
        assert_allclose(gaussian_peak_fraction(sigma), img.array.max(), rtol=1e-3)


def test_design_information_is_the_spot_fits_formal_error():
    """CONSISTENCY: N spots of a design, their rows fitted by fit_spot_slope (one
    intercept per spot) with the design's row errors, have the formal slope error
    1 / sqrt(N I)."""
    d = SpotDesign.saturating(1.5, 5)
    err = spot_row_errors(d.levels, d, quantity="e1")
    n = 12
    rng = np.random.default_rng(7)
    spot = np.repeat(np.arange(n), len(d.levels))
    image = np.tile(np.arange(len(d.levels)), n)
    flux = np.tile(d.levels, n)
    e = np.tile(err, n)
    q = rng.normal(0.0, 0.01, n)[spot] + 3e-4 * flux / 1e5 + e * rng.normal(size=e.size)
    fit = fit_spot_slope(spot, image, flux, q, e, tau=0.0)
    assert_allclose(fit["err_formal"], 1.0 / np.sqrt(n * design_information(d)), rtol=1e-9)


def test_spots_for_precision_inverts_the_gaussian_update():
    """CORRECTNESS (analytic): in one direction the joint precision of N0 spots of
    information i each is (1/f^2 + N0 i)^-1/2, and the goal g needs (1/g^2 - 1/f^2) / i
    spots; a design with r times the information needs 1/r as many."""
    f, i, n0 = 40.0, 2e-4, 50
    j = (1 / f ** 2 + n0 * i) ** -0.5
    for g in (10.0, 5.0, 2.5):
        exact = (1 / g ** 2 - 1 / f ** 2) / i
        assert spots_for_precision(f, j, n0, g) == int(np.ceil(exact - 1e-6))
        assert spots_for_precision(f, j, n0, g, information_ratio=4.0) == \
            int(np.ceil(exact / 4 - 1e-6))
    assert spots_for_precision(f, j, n0, 50.0) == 0  # the flats meet the goal
    assert spots_for_precision(f, f, n0, 5.0) is None  # the spots added nothing
    assert spots_for_precision(f, np.nan, n0, 5.0) is None


def test_precision_for_spots_is_the_inverse_of_the_plan():
    """CORRECTNESS (analytic): N spots of information i give (1/f^2 + N i)^-1/2, the fitted
    series' own N0 give back its stated precision, and the spots the plan asks for reach
    the goal (and one spot fewer does not)."""
    f, i, n0 = 40.0, 2e-4, 50
    j = (1 / f ** 2 + n0 * i) ** -0.5
    assert_allclose(precision_for_spots(f, j, n0, n0), j, rtol=1e-12)
    assert_allclose(precision_for_spots(f, j, n0, 0), f, rtol=1e-12)
    assert_allclose(precision_for_spots(f, j, n0, 300, information_ratio=2.0),
                    (1 / f ** 2 + 600 * i) ** -0.5, rtol=1e-12)
    for g in (10.0, 5.0, 2.5):
        n = spots_for_precision(f, j, n0, g)
        assert precision_for_spots(f, j, n0, n) <= g < precision_for_spots(f, j, n0, n - 1)
    assert np.isnan(precision_for_spots(f, np.inf, n0, 10))
    with pytest.raises(InputError, match="n_planned -1"):
        precision_for_spots(f, j, n0, -1)


def test_predicted_slope_falls_with_spot_size():
    """CORRECTNESS (physics): a template's size and |e1| slopes per flux fall as the
    spot widens (the boundary shifts are largest next to the charge), and the size
    slope is positive (brighter is fatter)."""
    tpl = load_default_template()
    slopes = {s: (predicted_slope(tpl, SpotDesign.saturating(s, 3), quantity="size"),
                  predicted_slope(tpl, SpotDesign.saturating(s, 3), quantity="e1"))
              for s in (1.0, 2.5)}
    size = [v[0] for v in slopes.values()]
    e1 = [abs(v[1]) for v in slopes.values()]
    assert size[0] > size[1] > 0
    assert e1[0] > e1[1] > 0
    # a design's information ratio to itself is 1
    d = SpotDesign(sigma=1.5, levels=(1e4, 1e5))
    assert_allclose(information_ratio(tpl, d, d), 1.0)


def _result(flats=(40.0, 8.0), joint=(20.0, 1.5)):
    sig = {"e1_slope_sigma": {"spots": {"flats_percent": flats[0], "joint_percent": joint[0]}},
           "size_slope_sigma": {"spots": {"flats_percent": flats[1],
                                          "joint_percent": joint[1]}}}
    return types.SimpleNamespace(uncertainty=sig, flats_template=load_default_template())


def test_plan_uses_the_stated_precision_and_scales_with_the_design():
    """CONSISTENCY: the plan of the fitted design is spots_for_precision of the stated
    precisions; another design's needs scale with its information ratio."""
    d0 = SpotDesign.saturating(1.5, 6)
    top = d0.levels[-1]
    # three exposures at the top flux and three at 0.3 of it: photon noise weights a row
    # by its flux, so the lever arm is best spent where the photons are
    other = SpotDesign(sigma=1.5, levels=(0.3 * top, top) * 3)
    plan = plan_spot_acquisition(_result(), "spots", fitted_design=d0, n_spots=36,
                                 designs={"as fitted": d0, "top": other},
                                 goals={"e1": (5.0, 2.5), "size": (2.0, 10.0)})
    rows = {(r["design"], r["quantity"], r["goal_percent"]): r for r in plan["rows"]}
    assert rows[("as fitted", "e1", 5.0)]["spots"] == spots_for_precision(40, 20, 36, 5.0)
    assert rows[("as fitted", "size", 2.0)]["spots"] == spots_for_precision(8, 1.5, 36, 2.0)
    assert rows[("as fitted", "size", 2.0)]["spots"] > 0
    assert rows[("as fitted", "size", 10.0)]["spots"] == 0  # the flats' 8 % meet it
    r = rows[("top", "e1", 5.0)]
    assert r["information_ratio"] > 1
    assert r["spots"] == spots_for_precision(40, 20, 36, 5.0,
                                             information_ratio=r["information_ratio"])
    assert r["exposures"] == 6 * r["spots"]


def test_bad_input_is_refused_with_the_value():
    """Bad input: designs, precisions and results the plan cannot use."""
    with pytest.raises(InputError, match="sigma must be a positive.*-1"):
        SpotDesign(sigma=-1)
    with pytest.raises(InputError, match="two or more positive fluxes"):
        SpotDesign(levels=(1e4, 1e4))
    with pytest.raises(InputError, match="read_noise must be >= 0.*-2"):
        SpotDesign(read_noise=-2)
    with pytest.raises(InputError, match="peak_max 10 e is reached"):
        SpotDesign.saturating(1.5, 4, peak_max=10)
    with pytest.raises(InputError, match="n_spots 0"):
        spots_for_precision(40, 20, 0, 5)
    with pytest.raises(InputError, match="goal -5"):
        spots_for_precision(40, 20, 10, -5)
    d0 = SpotDesign()
    with pytest.raises(InputError, match="no stated e1 precision for spot series 'other'"):
        plan_spot_acquisition(_result(), "other", fitted_design=d0, n_spots=10)
    with pytest.raises(InputError, match="goals may name.*'e2'"):
        plan_spot_acquisition(_result(), "spots", fitted_design=d0, n_spots=10,
                              goals={"e2": (5.0,)})
