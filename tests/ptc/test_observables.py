"""The checks beside the covariance fit find what GalSim-made flats carry, and nothing else.

One effect-free set of flat pairs is made with ``galsim.SiliconSensor``'s own
pixel areas (100 x 100 px, 2 pairs at 5 levels to 80 ke, 10 steps a flat:
about 10 s); each test changes a copy the way a lab's data would differ
(a non-linear exposure, a brighter second flat, one half with another gain, a
saturated level) and runs the diagnosis on it.
"""

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import stats

from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.calibration.acoeff_model import load_default_basis
from lsst_bfdrift.diagnosis.effects_fit import (Observations, diagnose, load_input,
                                             observations_from_pairs)
from lsst_bfdrift.diagnosis.findings import CHECKS, assess_observables, linearity_finding
from lsst_bfdrift.ptc.observables import exposure_scatter, pair_observables, turnoff_cut
from lsst_bfdrift.diagnosis.report import diagnosis_markdown
from lsst_bfdrift.templates.refine import lag_multiplicity
from lsst_bfdrift.simulation.effects import (BASE_OBSERVABLES, OBSERVABLES, GainNonlinearity,
                                             cti_filter_covariance, effect_library)
from lsst_bfdrift.simulation.flats import simulate_flat_pairs, write_flat_pairs
from lsst_bfdrift.utils.errors import InputError

LEVELS = np.repeat(np.geomspace(5e3, 8e4, 5), 2)  # e (gain 1: ADU)
EXPTIME_PER_E = 1e-4  # s


@pytest.fixture(scope="module")
def basis():
    return load_default_basis()


@pytest.fixture(scope="module")
def galsim_pairs():
    return simulate_flat_pairs("lsst_itl_50_8", LEVELS, engine="galsim", shape=(100, 100),
                               n_steps=10, seed=21)


def _copy(pairs):
    return [(a.copy(), b.copy()) for a, b in pairs]


def _diagnose(pairs, basis, exptimes=LEVELS * EXPTIME_PER_E):
    return diagnose(observations_from_pairs(pairs, max_lag=3, exptimes=exptimes), basis)


def _detected(d):
    return [k for k, f in d.observables.items() if f["detected"]]


def test_clean_galsim_set_has_no_finding(galsim_pairs, basis):
    d = _diagnose(galsim_pairs, basis)
    assert set(d.observables) == set(CHECKS)
    assert all(d.observables[k]["available"] for k in CHECKS)
    assert _detected(d) == [] and d.signatures == []
    for k in ("linearity", "sum_rule", "halves", "pair_ratio"):
        assert d.observables[k]["p_value"] > 1e-3, d.observables[k]["description"]
    lin = d.observables["linearity"]
    assert_allclose(lin["slope"], 1.0 / EXPTIME_PER_E, rtol=1e-3)  # ADU per s
    assert abs(lin["offset"]) < 5 * lin["offset_err"]
    assert d.observables["turnoff"]["excluded"] == []
    # the means against EXPTIME are a block of the fit ('M'): the same statistics
    # given as arrays, without exposure times, fit the covariances alone
    obs = observations_from_pairs(galsim_pairs, max_lag=3)
    bare = diagnose(Observations.from_flats(obs.mu, obs.cov, obs.static, obs.npix), basis)
    means = d.residuals_before["M0,0"]
    assert means["n"] == LEVELS.size and "M0,0" not in bare.residuals_before
    assert means["chi2"] < stats.chi2.ppf(0.999, LEVELS.size - 2)
    assert_allclose(d.steps[0]["base_params"]["rate"], 1.0 / EXPTIME_PER_E, rtol=1e-3)
    assert_allclose(bare.chi2_dof_before, d.chi2_dof_before, rtol=0.1)
    assert bare.effects_added == d.effects_added
    json.dumps(d.as_dict()["observables"])  # plain JSON, no numpy objects


def test_nonlinear_exposure_is_flagged_by_linearity(galsim_pairs, basis):
    """One level's flats 2 % brighter than their EXPTIME says."""
    pairs = _copy(galsim_pairs)
    hit = np.flatnonzero(LEVELS == LEVELS[6])
    for k in hit:
        pairs[k] = (pairs[k][0] * 1.02, pairs[k][1] * 1.02)
    d = _diagnose(pairs, basis)
    lin = d.observables["linearity"]
    assert lin["detected"] and lin["p_value"] < 1e-6
    assert lin["sign"] == "+"
    assert_allclose(lin["level"], 1.02 * LEVELS[6], rtol=2e-3)
    assert 0.01 < lin["value"] < 0.02 and lin["error"] < 1e-3
    assert lin["moved_by"] == ["gain_nonlinearity"] and not lin["base_model_moves"]
    assert not d.observables["pair_ratio"]["detected"]
    assert not d.observables["halves"]["detected"]
    assert "linearity: the mean departs from a line" in d.verdict
    # the means are a block of the fit: whatever the library tries (a gain
    # non-linearity is the only effect that moves the means), the jump stays
    # an unexplained residual, named at its level
    assert set(d.effects_added) <= {"gain_nonlinearity"}
    assert d.unexplained and d.worst_lag == "M0,0" and "M(0,0)@" in d.verdict
    for step in (d.steps[0], d.steps[-1]):
        worst = step["largest_residuals"][0]
        assert worst["block"] == "M" and worst["level"] in hit and worst["pull"] > 10


def test_lamp_noise_is_not_taken_for_a_nonlinearity(galsim_pairs, basis):
    """Every flat's exposure off by a random 0.5 % (a lamp): the pair ratios
    measure that scatter, and the linearity check, with it in its errors,
    finds no non-linearity; with shot noise alone it would call one."""
    rng = np.random.default_rng(7)
    pairs = [(a * (1 + 0.005 * rng.standard_normal()), b * (1 + 0.005 * rng.standard_normal()))
             for a, b in galsim_pairs]
    d = _diagnose(pairs, basis)
    lin = d.observables["linearity"]
    assert d.observables["pair_ratio"]["detected"]  # the lamp is named where it shows
    assert 0.002 < lin["exposure_scatter"] < 0.01 and lin["test"] == "F"
    assert not lin["detected"] and lin["p_value"] > 1e-3
    assert "exposure scatter" in lin["description"]
    mu = np.array([0.5 * (a.mean() + b.mean()) for a, b in pairs])
    shot = np.sqrt(mu / (2 * pairs[0][0].size))
    bare = linearity_finding(mu, LEVELS * EXPTIME_PER_E, shot)
    assert bare["detected"] and bare["p_value"] < 1e-6
    # the same non-linear level as below is still found through the lamp noise
    hit = np.flatnonzero(LEVELS == LEVELS[6])
    for k in hit:
        pairs[k] = (pairs[k][0] * 1.04, pairs[k][1] * 1.04)
    assert _diagnose(pairs, basis).observables["linearity"]["detected"]


def test_exposure_scatter_of_clean_pairs_is_small():
    """Pairs that agree within shot noise: no scatter (seeded normal ratios)."""
    rng = np.random.default_rng(3)
    mu = np.full(20, 1e4)
    n = np.full(20, 1e4)
    s = np.sqrt(2 * mu / n) / mu
    mu1 = mu * (1 - 0.5 * s * rng.standard_normal(20))
    mu2 = mu1 * (1 + s * rng.standard_normal(20))
    assert exposure_scatter(mu, mu1, mu2, n, 1.0, 0.0) < 0.5 * s[0]
    assert_allclose(exposure_scatter(mu, mu1, mu2 * (1 + 0.01 * rng.standard_normal(20)), n,
                                     1.0, 0.0), 0.01 / np.sqrt(2), rtol=0.5)
    with pytest.raises(InputError, match="exposure_scatter must be >= 0"):
        linearity_finding(mu, np.arange(1, 21.0), s * mu, exposure_scatter=-1)


def test_brighter_second_flat_is_flagged_by_pair_ratio(galsim_pairs, basis):
    pairs = _copy(galsim_pairs)
    pairs[3] = (pairs[3][0], pairs[3][1] * 1.01)
    d = _diagnose(pairs, basis)
    pr = d.observables["pair_ratio"]
    assert pr["detected"] and pr["sign"] == "+"
    assert_allclose(pr["value"], 0.01, atol=5 * pr["error"])
    assert_allclose(pr["levels"], [pr["level"]])  # only that pair beyond 3 sigma
    assert_allclose(pr["level"], 1.005 * LEVELS[3], rtol=2e-3)
    assert pr["moved_by"] == [] and "lamp or a shutter" in pr["description"]
    assert not d.observables["halves"]["detected"]


def test_right_half_with_another_gain_is_flagged_by_halves(galsim_pairs, basis):
    pairs = _copy(galsim_pairs)
    for a, b in pairs:
        a[:, 50:] *= 1.03
        b[:, 50:] *= 1.03
    d = _diagnose(pairs, basis)
    h = d.observables["halves"]
    assert h["detected"] and h["split"] == "left_right" and h["test"] == "offset"
    assert_allclose(h["value"], 0.03, atol=5 * h["error"])
    assert h["sign"] == "+" and "right half is 3 % brighter" in h["description"]
    # bottom/top unchanged
    bt = h["splits"]["bottom_top"]
    assert abs(bt["mean_ratio_mean"]) < 5 * bt["mean_ratio_err"]
    assert "static_area" in h["moved_by"]
    assert not d.observables["linearity"]["detected"]
    assert not d.observables["pair_ratio"]["detected"]
    assert "halves:" in d.verdict


def test_saturated_level_gives_the_break_level(galsim_pairs, basis):
    pairs = _copy(galsim_pairs)
    top = np.flatnonzero(LEVELS == LEVELS.max())
    for k in top:
        pairs[k] = tuple(np.minimum(f, LEVELS.max()) for f in pairs[k])  # full well
    obs = observations_from_pairs(pairs, max_lag=3, exptimes=LEVELS * EXPTIME_PER_E)
    assert obs.mu.size == LEVELS.size - top.size  # left out of the fit
    d = diagnose(obs, basis)
    t = d.observables["turnoff"]
    assert t["detected"] and t["significance"] > 5
    below = max(np.mean(galsim_pairs[k]) for k in np.flatnonzero(LEVELS == LEVELS[7]))
    assert_allclose(t["value"], below, rtol=2e-3)
    assert len(t["excluded"]) == top.size and all(e["drop"] > 0.3 for e in t["excluded"])
    assert_allclose(t["levels"], sorted(np.mean(pairs[k]) for k in top), rtol=1e-3)
    assert not d.observables["linearity"]["detected"]  # the clipped means are left out too
    assert "turn-off" in d.verdict and "left out of the fit" in d.verdict


def test_fits_pairs_carry_exptime(galsim_pairs, basis, tmp_path):
    write_flat_pairs(galsim_pairs[:8], LEVELS[:8], tmp_path, exptime_per_e=EXPTIME_PER_E)
    obs = load_input(str(tmp_path))
    assert_allclose(obs.exptime, np.sort(LEVELS[:8]) * EXPTIME_PER_E, rtol=1e-6)
    f = diagnose(obs, basis).observables["linearity"]
    assert f["available"] and not f["detected"]
    # one pair without EXPTIME, then one with EXPTIME = 0: said, not guessed
    from astropy.io import fits
    for tag in ("a", "b"):
        with fits.open(tmp_path / f"flat_002_{tag}.fits", mode="update") as h:
            del h[0].header["EXPTIME"]
    obs = load_input(str(tmp_path))
    assert obs.exptime is None and obs.exptime_note == "EXPTIME missing for 1 of 8 pairs"
    for tag in ("a", "b"):
        with fits.open(tmp_path / f"flat_002_{tag}.fits", mode="update") as h:
            h[0].header["EXPTIME"] = 0.0
    f = diagnose(load_input(str(tmp_path)), basis).observables["linearity"]
    assert not f["available"] and "EXPTIME not positive in 1 pair(s)" in f["reason"]


def test_not_available_says_so(galsim_pairs, basis):
    # arrays without exposure times
    d = _diagnose(galsim_pairs, basis, exptimes=None)
    lin = d.observables["linearity"]
    assert not lin["available"] and "no exposure times" in lin["reason"]
    assert "not available with these data" in lin["description"]
    # statistics given as arrays: no halves, no pairs
    obs = observations_from_pairs(galsim_pairs, max_lag=3)
    d = diagnose(Observations.from_flats(obs.mu, obs.cov, obs.static, obs.npix), basis)
    assert not d.observables["halves"]["available"]
    assert d.observables["sum_rule"]["available"]
    # a table whose a00 was set by the sum rule, and one whose a00 was measured
    sig = np.full((4, 4), 1e-8)
    a = basis.a0[:4, :4] + np.random.default_rng(3).normal(0, 1e-8, (4, 4))
    d = diagnose(Observations.from_table(AcoeffTable(a, sig, exclude_a00=True)), basis)
    assert not d.observables["sum_rule"]["available"]
    assert "set by the sum rule" in d.observables["sum_rule"]["reason"]
    d = diagnose(Observations.from_table(AcoeffTable(a, sig)), basis)
    assert d.observables["sum_rule"]["available"] and d.observables["sum_rule"]["unit"] == "1/e"
    assert not d.observables["linearity"]["available"]
    md = diagnosis_markdown(d.as_dict())
    assert "## Observables beside the fit" in md
    assert "| linearity | no |" in md and "not available with these data" in md


def test_ptc_input_reports_its_turnoff(basis):
    mu = np.geomspace(1e3, 9e4, 12)
    var = mu * (1 - 1e-6 * mu)
    var[-2:] = [0.3 * var[-3], 0.1 * var[-3]]  # saturated
    obs = Observations.from_ptc(mu, var)
    f = assess_observables(obs)
    assert f["turnoff"]["detected"]
    assert_allclose(f["turnoff"]["value"], mu[-3])
    assert_allclose(f["turnoff"]["levels"], mu[-2:])
    assert f["turnoff"]["significance"] is None  # pixel counts unknown
    for k in ("linearity", "sum_rule", "halves", "pair_ratio"):
        assert not f[k]["available"]


def test_bad_exptimes(galsim_pairs):
    with pytest.raises(ValueError, match="one positive exposure time"):
        observations_from_pairs(galsim_pairs, exptimes=[1.0, 2.0])
    with pytest.raises(ValueError, match="one positive exposure time"):
        observations_from_pairs(galsim_pairs, exptimes=np.zeros(len(galsim_pairs)))
    f = linearity_finding([1.0, 2.0, 2.0], [1.0, 2.0, 2.0], [0.1] * 3)
    assert not f["available"] and "2 distinct exposure time(s)" in f["reason"]


def test_turnoff_ignores_noise_of_small_images():
    """A 6 % scatter of the variance is no turn-off when each has 3 % errors."""
    rng = np.random.default_rng(4)
    mu = np.repeat(np.geomspace(5e3, 8e4, 6), 2)
    npix = np.full(mu.size, 2000.0)
    c00 = mu * (1 + rng.normal(0, np.sqrt(2 / 2000), mu.size))
    c00[3] = 0.94 * c00[2]
    keep, info = turnoff_cut(mu, c00, npix)
    assert keep.all() and info["break_level"] is None and info["drop"] > 0.2


def test_effects_state_their_observables():
    lib = effect_library()
    for e in lib:
        assert set(e.observables) <= set(OBSERVABLES), e.name
    moves = {e.name: set(e.observables) for e in lib}
    assert BASE_OBSERVABLES == ("covariances",)
    assert moves["diffusion"] == set()
    assert [n for n, m in moves.items() if "sum_rule" in m] == ["gain_nonlinearity"]
    # CTI moves charge to the next pixel: the covariances summed over lags are kept
    cov = np.zeros((1, 4, 4))
    cov[0, 0, 0], cov[0, 1, 0], cov[0, 0, 1] = 1.0, 0.02, 0.03
    m = lag_multiplicity(3)
    for axis in (0, 1):
        out = cti_filter_covariance(cov, 0.05, axis)
        assert_allclose(np.sum(m * out), np.sum(m * cov), rtol=1e-12)
    # a gain non-linearity scales them against the mean by ~ 1 + 3 nu mu
    nu, mu = 1e-7, 5e4
    lin, fac = GainNonlinearity().measured_signal(np.array([mu]), (nu,))
    assert_allclose(fac[0] * lin[0] / mu, 1 + 3 * nu * lin[0], rtol=1e-4)


@pytest.mark.parametrize("shape, border", [((96, 130), None), ((200, 170), 10), ((181, 240), 3)])
def test_halves_on_cut_outs_equal_the_masked_whole_image(shape, border):
    """Each half is measured on its own cut-out with the whole image's border
    band as a mask; the reference is the whole image with the other half
    masked (the same pixels and pixel pairs, independent of the cut-out's
    transform shapes). NaN, masked-by-value and clipped pixels included."""
    from lsst_bfdrift.ptc.covariances import pair_covariances

    rng = np.random.default_rng(sum(shape))
    a = rng.poisson(3e4, shape).astype(float)
    b = rng.poisson(3.1e4, shape).astype(float)
    a[5, 7] = np.nan
    b[shape[0] // 2 + 3, 20] = 1e7  # clipped (a cosmic ray)
    got = pair_observables(a, b, max_lag=3, border=border)["halves"]
    ny, nx = shape
    for split, cut in (("left_right", lambda r: r[1] < nx // 2),
                       ("bottom_top", lambda r: r[0] < ny // 2)):
        yy, xx = np.mgrid[:ny, :nx]
        first = cut((yy, xx))
        for k, region in enumerate((first, ~first)):
            ref = pair_covariances(a, b, max_lag=3, mask=~region, border=border,
                                   min_pixels=min(1000, a.size // 16))
            assert_allclose(got[split]["mu"][k], ref.mu, rtol=1e-12)
            assert got[split]["nvalid"][k] == ref.nvalid
            assert_allclose(got[split]["npix"][k], ref.npix)
            assert_allclose(got[split]["cov"][k], ref.cov, rtol=1e-9, atol=1e-9 * ref.cov[0, 0])


def test_gain_nonlinearity_is_named_through_the_means(galsim_pairs, basis):
    """A signal chain with nu = 2e-7 per ADU (0.3 % at 16 ke, 1.6 % at 80 ke) on
    GalSim-made flats, applied as the library's generator applies it. The
    means against EXPTIME are in the fit, so the effect is named and measured,
    and the free a00 scale does not take it up: a00 stays within 1 sigma of the
    clean set's. Without exposure times the same covariances alone do not
    constrain it as well."""
    nu = 2e-7
    pairs = [(a * (1 + nu * a), b * (1 + nu * b)) for a, b in galsim_pairs]
    d = _diagnose(pairs, basis)
    clean = _diagnose(galsim_pairs, basis)
    assert d.effects_added == ["gain_nonlinearity"] and not d.unexplained
    e = d.steps[-1]["effects"][0]
    assert abs(e["params"]["nu"] - nu) < 3 * e["errors"]["nu"]
    assert e["errors"]["nu"] < 0.2 * nu

    (v, s), (v0, s0) = _a00(d, basis), _a00(clean, basis)
    assert abs(v - v0) < max(s, s0)
    bare = diagnose(observations_from_pairs(pairs, max_lag=3), basis)
    eb = [x for x in bare.steps[-1]["effects"] if x["name"] == "gain_nonlinearity"]
    assert not eb or eb[0]["errors"]["nu"] > 2 * e["errors"]["nu"]


def test_flats_report_plots_the_residuals_against_the_mean(galsim_pairs, basis, tmp_path):
    """The report of a flats diagnosis with exposure times: the means' block is
    a residual like the lags, the scales' prior is not, and a figure shows the
    pulls against the mean signal."""
    from lsst_bfdrift.diagnosis.report import write_report

    d = _diagnose(galsim_pairs, basis).as_dict()
    assert "M0,0" in d["residuals_before"]
    assert not [k for k in d["residuals_before"] if k.startswith("P")]
    assert_allclose(d["levels"], np.sort(LEVELS), rtol=0.01)
    paths = write_report(d, str(tmp_path))
    assert (tmp_path / "residuals_vs_mean.png").exists()
    assert (tmp_path / "pull_map_C.png").exists() and not (tmp_path / "pull_map_M.png").exists()
    assert "residuals_vs_mean.png" in (tmp_path / "report.md").read_text()
    assert str(tmp_path / "report.md") in paths


def _a00(diag, basis):
    """a00 of the final fit and its error, through the basis the diagnosis used."""
    from lsst_bfdrift.diagnosis.effects_fit import base_acoeffs
    from lsst_bfdrift.diagnosis.effects_fit import scaled_basis

    a, s = base_acoeffs(diag.steps[-1], scaled_basis(basis, diag.base_scales), 0)
    return a[0, 0], s[0, 0]


@pytest.mark.parametrize("name, eps", [("cti_serial", 2e-2), ("cti_parallel", 3e-2)])
def test_cti_on_galsim_flats_is_named_on_its_axis(galsim_pairs, basis, name, eps):
    """CTI applied to the read-out of GalSim-made flats (the same flats are the
    exact effect-free twin): named on its axis with eps within 3 sigma, nothing
    else added, and a00 within 1 sigma of the twin's. Amplitudes where these
    small data (10 pairs of 100 x 100 px) find it; the detection thresholds at
    larger sizes are in benchmarks/diagnosis/diagnose_power_results.txt."""
    from lsst_bfdrift.simulation.flats import apply_readout_effects

    inj = {name: (eps,)}
    pairs = [(apply_readout_effects(a, inj), apply_readout_effects(b, inj))
             for a, b in galsim_pairs]
    d = _diagnose(pairs, basis)
    assert d.effects_added == [name] and not d.unexplained
    e = d.steps[-1]["effects"][0]
    assert abs(e["params"]["eps"] - eps) < 3 * e["errors"]["eps"]
    (v, s), (v0, _) = _a00(d, basis), _a00(_diagnose(galsim_pairs, basis), basis)
    assert abs(v - v0) < s


def test_an_undeclared_echo_is_named_where_it_is(galsim_pairs, basis):
    """An effect the library lacks (an electronic echo: 3 % of the charge 3
    serial pixels earlier) on GalSim-made flats: not silence and not a
    library effect, but an unexplained residual at lag (3, 0), positive."""
    from lsst_bfdrift.simulation.flats import apply_readout_effects

    inj = {"echo": (3e-2, 3)}
    pairs = [(apply_readout_effects(a, inj), apply_readout_effects(b, inj))
             for a, b in galsim_pairs]
    d = _diagnose(pairs, basis)
    assert d.effects_added == [] and d.unexplained
    assert d.worst_lag == "C3,0" and d.worst_lag_p < 1e-6
    assert np.mean(d.residuals_after["C3,0"]["pull"]) > 1.0
    assert "C(3,0)" in d.verdict and "nothing in the library explains" in d.verdict
