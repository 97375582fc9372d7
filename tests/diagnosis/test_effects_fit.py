"""The diagnosis finds effects injected into simulated flats without being told.

Flat pairs are simulated with the linearised area model of the electrostatic
a_ij (``tests/data/itl_basis_lag3.json``: made by
``linear_basis(SensorParameters(xi0=4722.4, channel_depth=0.56159,
collection_height=0.5), max_lag=3, near_samples=16, far_samples=6,
tol=5e-5)``), one effect injected at a time; the PTC statistics are measured
from the images and :func:`diagnose` runs on them with the whole library.
"""

import json
import os
import re

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose

from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.calibration.acoeff_model import LinearBasis
from lsst_bfdrift.cli.main import main
from lsst_bfdrift.diagnosis.effects_fit import (Observations, diagnose, load_input,
                                             observations_from_pairs)
from lsst_bfdrift.diagnosis.observations import pair_statistics
from lsst_bfdrift.simulation.effects import ChargeCloud
from lsst_bfdrift.simulation.flats import _static_pattern, simulate_flat_pairs, write_flat_pairs
from tests._shared import shared

BASIS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "data", "itl_basis_lag3.json")
E2V = "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt"
LEVELS = np.linspace(1e4, 8e4, 8)


@pytest.fixture(scope="module")
def basis():
    with open(BASIS) as fh:
        return LinearBasis.from_dict(json.load(fh))


def _run(basis, inject, *, seed=1, n_steps=20):
    pairs = simulate_flat_pairs(basis.a0, LEVELS, inject=inject, shape=(128, 128),
                                n_steps=n_steps, depth_derivative=basis.dlog_depth(3),
                                seed=seed)
    return diagnose(observations_from_pairs(pairs, max_lag=3), basis)


def test_null_adds_nothing(basis):
    d = _run(basis, {})
    assert d.effects_added == []
    assert not d.unexplained
    assert 0.8 < d.chi2_dof_before < 1.2  # the error model is right


@pytest.mark.slow
@pytest.mark.parametrize("name, params, n_steps", [
    ("cti_parallel", (0.03,), 20),
    ("gain_nonlinearity", (2e-6,), 20),
    # the b term is sensitive to the accumulation step: 40 steps keep its
    # discretisation bias (~(1 - 1/n)) well inside the errors
    ("well_filling", (4e-5,), 40),
])
def test_injected_effect_is_found(basis, name, params, n_steps):
    """Magnitudes chosen to be found in every seed tried (1-5); at half of them
    (beta 2e-5, nu 1e-6) the 128 x 128, 8-level data find them in 1-2 of 4 seeds."""
    d = _run(basis, {name: params}, n_steps=n_steps)
    assert d.effects_added == [name]
    assert not d.unexplained
    assert d.chi2_dof_after < d.chi2_dof_before
    e = d.steps[-1]["effects"][0]
    (k, v), = e["params"].items()
    assert abs(v - params[0]) < 4 * e["errors"][k]


@pytest.mark.slow
def test_static_area_found_and_measured(basis):
    d = _run(basis, {"static_area": (1e-5, 3.0)})
    assert d.effects_added == ["static_area"]
    # S_ij / mu^2 is the realised pattern's autocovariance, computed directly
    pat = _static_pattern((128, 128), 1e-5, 3.0, np.random.default_rng(2))
    p = pat - pat.mean()
    v = d.steps[-1]["effects"][0]
    for (i, j) in ((0, 0), (1, 0), (0, 1), (2, 1)):
        direct = 0.5 * (np.mean(p * np.roll(p, (j, i), axis=(0, 1)))
                        + np.mean(p * np.roll(p, (-j, i), axis=(0, 1))))
        fitted = v["params"][f"v_{i}_{j}"]
        assert abs(fitted - direct) < 4 * v["errors"][f"v_{i}_{j}"] + 0.05 * abs(direct)


@pytest.mark.slow
def test_diffusion_leaves_flats_unchanged(basis):
    """Injected diffusion: nothing to find (uniform flats stay Poisson)."""
    d = _run(basis, {"diffusion": (0.5,)}, n_steps=10)
    assert d.effects_added == []
    assert not d.unexplained
    assert "diffusion" in d.not_identifiable


def test_effect_outside_library_is_unexplained(basis):
    d = _run(basis, {"echo": (0.05, 3)})
    assert d.unexplained
    assert d.verdict.startswith("unexplained residual")
    assert "nothing in the library explains" in d.verdict
    assert d.worst_lag == "C3,0"


def test_charge_cloud_found_in_precise_table(basis):
    """The cloud is ~96 % degenerate with the electrostatic parameters; with
    a_ij errors of 1e-9 the rest (~1e-8 at lags 1-2) is found."""
    rng = np.random.default_rng(8)
    sig = np.full(basis.a0.shape, 1e-9)
    inj = (0.15, 0.02)
    a = ChargeCloud().apply_a(basis.a0, inj, None) + rng.normal(0, sig)
    d = diagnose(Observations.from_table(AcoeffTable(a, sig)), basis)
    assert d.effects_added == ["charge_cloud"]
    e = d.steps[-1]["effects"][0]
    assert abs(e["params"]["var_serial"] - inj[0]) < 4 * e["errors"]["var_serial"]
    null = diagnose(Observations.from_table(
        AcoeffTable(basis.a0 + rng.normal(0, sig), sig)), basis)
    assert null.effects_added == [] and not null.unexplained
    # a table cannot identify CTI, static structure, non-linearity or diffusion
    assert {"cti_serial", "static_area", "gain_nonlinearity", "diffusion"} <= \
        set(d.not_identifiable)


def test_pair_statistics_static_cancels():
    """S_ij of two independent Poisson flats is zero within errors."""
    rng = np.random.default_rng(5)
    f1 = rng.poisson(1e4, (128, 128)).astype(float)
    f2 = rng.poisson(1e4, (128, 128)).astype(float)
    mu, cov, S, npix = pair_statistics(f1, f2, max_lag=2)
    assert abs(cov[0, 0] - 1e4) < 5 * 1e4 * np.sqrt(2 / npix[0, 0])
    assert np.all(np.abs(S) < 5 * 1e4 / np.sqrt(npix))


def test_cli_ptc_json_and_report(tmp_path, capsys):
    rc = main(["diagnose", E2V, "--json", "--basis", BASIS, "--report", str(tmp_path)])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("effects_added", "chi2_dof_before", "chi2_dof_after", "residuals_before",
                "residuals_after", "verdict", "not_identifiable"):
        assert key in out
    assert out["kind"] == "ptc"
    assert set(out["effects_added"]) <= set(out["vocabulary"])
    assert (tmp_path / "report.md").exists() and (tmp_path / "chi2_per_lag.png").exists()
    assert "Verdict" in (tmp_path / "report.md").read_text()
    # the directory now holds a report: replaced only with --overwrite (issue 20)
    before = (tmp_path / "report.md").stat().st_mtime_ns
    rc = main(["diagnose", E2V, "--basis", BASIS, "--report", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 3 and "holds files; use --overwrite" in err
    assert (tmp_path / "report.md").stat().st_mtime_ns == before
    assert main(["diagnose", E2V, "--basis", BASIS, "--report", str(tmp_path),
                 "--overwrite"]) == 0


@pytest.mark.slow
def test_cli_directory_of_flat_pairs(tmp_path, basis, capsys):
    pairs = simulate_flat_pairs(basis.a0, LEVELS, inject={"cti_serial": (0.03,)},
                                shape=(128, 128), n_steps=20, seed=1)
    for k, (a, b) in enumerate(pairs):
        fits.writeto(tmp_path / f"flat_{k:02d}_a.fits", a.astype(np.float32))
        fits.writeto(tmp_path / f"flat_{k:02d}_b.fits", b.astype(np.float32))
    # what the found effect does to the template (two calibrations, most of this test's
    # time) is tested in tests/diagnosis/test_consequence.py and tests/cli/test_main.py
    rc = main(["diagnose", str(tmp_path), "--json", "--basis", BASIS, "--no-template-change"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kind"] == "flats" and out["effects_added"] == ["cti_serial"]
    assert out["chi2_dof_after"] < out["chi2_dof_before"] and not out["unexplained"]
    e = out["steps"][-1]["effects"][0]
    assert abs(e["params"]["eps"] - 0.03) < 4 * e["errors"]["eps"]


def test_bad_inputs(tmp_path, basis, capsys):
    p = tmp_path / "three.txt"
    p.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(ValueError, match=r"three\.txt: text file with 3 numeric columns"):
        load_input(str(p))
    with pytest.raises(ValueError, match="no such file"):
        load_input(str(tmp_path / "missing.txt"))
    fits.writeto(tmp_path / "one.fits", np.ones((8, 8), np.float32))
    with pytest.raises(ValueError, match="even number"):
        load_input(str(tmp_path))
    with pytest.raises(ValueError, match="shape"):
        Observations.from_flats(np.arange(4.0), np.zeros((4, 2, 2)), np.zeros((4, 3, 3)),
                                np.ones((4, 2, 2)))
    with pytest.raises(ValueError, match="at least 6"):
        Observations.from_ptc([1.0, 2.0], [1.0, np.nan])
    big = AcoeffTable(np.zeros((6, 6)), np.ones((6, 6)))
    with pytest.raises(ValueError, match="basis has lags"):
        diagnose(Observations.from_table(big), basis)
    assert main(["diagnose", str(p), "--basis", BASIS]) == 2
    assert "3 numeric columns" in capsys.readouterr().err


def _ecsv(path, a, s, unit):
    from astropy.table import Table
    L = a.shape[0] - 1
    i, j = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    t = Table({"i": i.ravel(), "j": j.ravel(), "a": a.ravel(), "a_err": s.ravel()})
    if unit is not None:
        t["a"].unit = t["a_err"].unit = unit
    t.write(path, format="ascii.ecsv")
    return str(path)


def test_ecsv_tables_are_read_with_their_units(tmp_path, basis, capsys):
    """Issue 44 item 2: diagnose reads an a-matrix as calibrate does (one reader): an
    ECSV table's unit is converted (0.001 / electron) or refused (1 / adu, pix) naming
    the file and what is accepted, never taken as per electron."""
    import astropy.units as u

    from lsst_bfdrift.ptc.inputs import read_calibration_input

    a, s = basis.a0.copy(), np.full(basis.a0.shape, 2e-9)
    milli = _ecsv(tmp_path / "milli.ecsv", a * 1e3, s * 1e3, 1 / (1000 * u.electron))
    obs = load_input(milli)
    assert_allclose(obs.a, a, rtol=1e-12)
    assert_allclose(obs.sigma, s, rtol=1e-12)
    assert_allclose(obs.a, read_calibration_input(milli).acoeff_table().a, rtol=1e-15)
    for name, unit, text in (("adu", 1 / u.adu, "1 / adu"), ("pix", u.pix, "pix")):
        bad = _ecsv(tmp_path / f"{name}.ecsv", a, s, unit)
        with pytest.raises(ValueError, match=re.escape(f"{bad}: column a has unit {text}; "
                                                       "accepted: per electron")):
            load_input(bad)
        assert main(["diagnose", bad, "--basis", BASIS, "--no-template-change"]) == 2
        err = capsys.readouterr().err
        assert f"{bad}: column a has unit" in err and "Traceback" not in err


def test_a00_alone_is_refused_naming_the_file(tmp_path, basis, capsys):
    """Issue 44 item 1: a table of a00 alone reaches the diagnosis (no IndexError) and
    is refused there with the file, the count and what is accepted."""
    path = tmp_path / "a00.txt"
    path.write_text("i j a sigma\n0 0 -1.333030e-06 1.334e-07\n")
    obs = load_input(str(path))
    assert obs.a.shape == (1, 1)
    msg = (re.escape(f"{path}: 1 lag(s) in chi2 (lags 0..0), no more than the 4 free "
                     "parameters of the base model") + r".*accepted: a table with more lags "
           r"than parameters \(lags 0\.\.2 or more\)")
    with pytest.raises(ValueError, match=msg):
        diagnose(obs, basis)
    assert main(["diagnose", str(path), "--basis", BASIS, "--no-template-change"]) == 2
    err = capsys.readouterr().err
    assert f"{path}: 1 lag(s) in chi2" in err and "Traceback" not in err


def test_a_pair_of_one_exposure_twice_is_refused(tmp_path, rng):
    """Issue 44 item 9: a pair of one exposure twice is named (both files), not read
    as saturation that drops every brighter pair."""
    import shutil

    for k, level in enumerate((2e3, 6e3, 1.2e4, 2.4e4)):
        for half in "ab":
            fits.PrimaryHDU(rng.poisson(level, (48, 48)).astype(np.float32),
                            header=fits.Header({"EXPTIME": k + 1.0})).writeto(
                tmp_path / f"flat_{k}{half}.fits")
    shutil.copyfile(tmp_path / "flat_1a.fits", tmp_path / "flat_1b.fits")
    with pytest.raises(ValueError, match=re.escape(
            f"flat pair {tmp_path / 'flat_1a.fits'} and {tmp_path / 'flat_1b.fits'}: the two "
            "images are one exposure")):
        load_input(str(tmp_path))
    img = rng.poisson(500.0, (48, 48)).astype(float)
    with pytest.raises(ValueError, match=r"flat pair 0 \(arrays\): the two images are one"):
        observations_from_pairs([(img, img.copy())] * 4)


def test_ptc_refusal_names_the_file_and_the_reasons(tmp_path):
    """Issue 44 item 10 (diagnose's side): too few PTC points names the file and why
    the others were left out."""
    dec = tmp_path / "dec.txt"
    dec.write_text("".join(f"{m} {1e5 / m}\n" for m in (100, 200, 300, 400, 500, 600, 700)))
    with pytest.raises(ValueError, match=re.escape(
            f"{dec}: need at least 6 valid PTC points, got 1 of 7 (6 past the turn-off at 100 "
            "ADU")):
        load_input(str(dec))


def test_cli_itl_table_with_shipped_basis(capsys):
    """The measured ITL table against the shipped fit: nothing to add."""
    rc = main(["diagnose", "/work/shared/data/measured/itl_covariances_21oct19.txt", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["kind"] == "table" and out["n_points"] == 80  # a00 left out (sum rule)
    assert out["effects_added"] == [] and not out["unexplained"]
    assert out["chi2_dof_before"] < 0.1  # the file's errors are generous (docs/calibration.rst)
    assert out["tried"] == ["charge_cloud"]
    assert len(out["residuals_before"]) == 80


def test_directory_reader_ignores_temporary_files(tmp_path, monkeypatch):
    """A partial .tmp-* file left by a killed write is never taken as a flat."""
    from lsst_bfdrift.diagnosis import effects_fit as diagnosis
    for k in range(8):
        fits.writeto(tmp_path / f"flat_{k}.fits", np.ones((8, 8), np.float32))
    (tmp_path / ".tmp-k1x2.fits").write_bytes(b"")  # killed run
    (tmp_path / f".tmp-{os.getpid()}-host-abcd1234.fits").write_bytes(b"")  # a live writer
    monkeypatch.setattr(diagnosis, "observations_from_pairs", lambda pairs, max_lag: pairs)
    pairs = load_input(str(tmp_path))
    assert [os.path.basename(p) for pair in pairs for p in pair] == \
        [f"flat_{k}.fits" for k in range(8)]


@pytest.fixture(scope="module")
def galsim_pairs():
    """Effect-free flats made by galsim.SiliconSensor (its own pixel areas, open image
    edges): an independent simulator; 144 x 144 px, 2 pairs at 8 levels to 80 ke, each
    flat filled in 10 steps (seeds 11-13 give chi2/dof 0.87-1.01 and the edge named)."""
    levels = np.repeat(np.geomspace(4e3, 8e4, 8), 2)
    return shared("galsim_itl_flats_144", lambda: simulate_flat_pairs(
        "lsst_itl_50_8", levels, engine="galsim", shape=(144, 144), n_steps=10, seed=11))


def test_galsim_flats_come_back_clean_with_the_edge_named(galsim_pairs):
    """Independent data (GalSim): the fit region is consistent with the base model and
    nothing is added; the image edges, where GalSim's flats are dimmer because no charge
    lies beyond them, are named as an edge signature, never silently absorbed."""
    from lsst_bfdrift.calibration.acoeff_model import load_default_basis
    res = diagnose(observations_from_pairs(galsim_pairs, max_lag=3), load_default_basis())
    assert res.effects_added == [] and not res.unexplained, res.verdict
    assert 0.75 < res.chi2_dof_before < 1.3
    assert res.edge["detected"] and "dimmer" in res.edge["description"]
    assert "grows with the signal" in res.edge["description"]
    assert "edge signature" in res.verdict
    # ring 1 (second pixel from the edge) at the top level: dimmer by 0.1 - 1 %
    assert -1e-2 < res.edge["at_top"][1] < -1e-3


def test_galsim_edges_left_in_spoil_the_fit(galsim_pairs):
    """The same GalSim flats with the border kept: the edge pattern enters the static
    term and the fit fails, so the border default is what makes the previous test pass."""
    from lsst_bfdrift.calibration.acoeff_model import load_default_basis
    res = diagnose(observations_from_pairs(galsim_pairs, max_lag=3, border=0),
                   load_default_basis())
    assert res.chi2_dof_before > 3.0
    assert res.edge is None


def test_periodic_flats_have_no_edge_signature(basis):
    """Consistency: the package's linear engine is periodic, so no ring differs."""
    pairs = simulate_flat_pairs(basis.a0, LEVELS, shape=(96, 96), n_steps=10, seed=5)
    res = diagnose(observations_from_pairs(pairs, max_lag=3), basis)
    assert res.edge is not None and not res.edge["detected"], res.edge["description"]


@pytest.mark.slow
def test_well_filling_named_on_galsim_flats():
    """Independent data (GalSim's own areas): each pixel's pull on its neighbours'
    boundaries grows with its charge, a_ij (1 + beta Q) with beta = 4e-5 per e, in e2v
    flats of 128 x 128 px, 3 pairs at 8 levels to 80 ke, each filled in 10 steps. The
    diagnosis names well_filling and nothing else. Its beta (the library's shape,
    d a_ij / d ln depth, not GalSim's a_ij) comes back within a factor 2 (seeds 12, 14,
    15 and 21 give 4.4-4.6e-5); at 3e-5 one of two ITL sets of this size missed it (the
    threshold is in docs/benchmarks.rst)."""
    from lsst_bfdrift.calibration.acoeff_model import load_default_basis
    levels = np.repeat(np.geomspace(4e3, 8e4, 8), 3)
    pairs = simulate_flat_pairs("lsst_e2v_50_8", levels, engine="galsim", shape=(128, 128),
                                n_steps=10, seed=14, inject={"well_filling": (4e-5,)})
    d = diagnose(observations_from_pairs(pairs, max_lag=3, exptimes=levels * 1e-4),
                 load_default_basis())
    assert d.effects_added == ["well_filling"], d.verdict
    assert not d.unexplained
    beta = d.steps[-1]["effects"][0]["params"]["beta"]
    assert 2e-5 < beta < 8e-5


def test_well_filling_below_threshold_is_reported_as_not_excluded(basis, tmp_path, capsys):
    """Consistency (the package's linear engine): well filling of 1e-5 per e on
    192 x 192 px, 3 pairs at 8 levels, is not added (below the threshold), and the
    final base a00 takes up the mean of a_ij (1 + beta Q): many sigma from the
    zero-charge truth. ``not_excluded`` reports what freeing it does: a00 within
    1.5 of its (3x larger) error of the truth, and the shift it would make; the
    Markdown report names it."""
    from lsst_bfdrift.diagnosis.effects_fit import base_acoeffs
    from lsst_bfdrift.diagnosis.effects_fit import scaled_basis
    from lsst_bfdrift.diagnosis.report import diagnosis_markdown

    levels = np.repeat(np.geomspace(4e3, 8e4, 8), 3)
    pairs = simulate_flat_pairs(basis.a0, levels, inject={"well_filling": (1e-5,)},
                                shape=(192, 192), n_steps=20,
                                depth_derivative=basis.dlog_depth(3), seed=1)
    d = diagnose(observations_from_pairs(pairs, max_lag=3, exptimes=levels * 1e-4), basis)
    assert d.effects_added == []
    truth = basis.a0[0, 0] * (1 - 1 / 20)  # discrete filling
    a, s = base_acoeffs(d.steps[-1], scaled_basis(basis, d.base_scales), 1)
    assert abs(a[0, 0] - truth) > 5 * s[0, 0]
    w = {x["effect"]: x for x in d.not_excluded}["well_filling"]
    assert abs(w["a00"][0] - truth) < 1.5 * w["a00"][1]
    assert w["a00_shift_sd"] > 5 and w["a00"][1] > 2 * s[0, 0]
    assert d.not_excluded[0]["effect"] == "well_filling"  # the largest shift first
    md = diagnosis_markdown(d.as_dict())
    assert "## Not excluded" in md and "**well_filling**" in md
    # the command line says it too (the same basis, the flats as FITS with EXPTIME)
    write_flat_pairs(pairs, levels, tmp_path, exptime_per_e=1e-4)
    assert main(["diagnose", str(tmp_path), "--basis", BASIS, "--no-template-change"]) == 0
    assert "not excluded: well_filling would move a00 by" in capsys.readouterr().out
