"""``bfdrift spots`` and ``bfdrift spot-sim`` (consistency of the commands with the
library, and their refusals of bad input)."""

import json
import os

import numpy as np
import pytest
from astropy.io import fits

from lsst_bfdrift.cli.main import main


def _spot_files(tmp_path, *, bunit="electron", exptime=True, n=3, shape=(110, 110)):
    """Three synthetic spot images (3 x 3 Gaussian spots) as FITS files."""
    rng = np.random.default_rng(2)
    jj, ii = np.mgrid[:shape[0], :shape[1]]
    paths = []
    for k, f in enumerate(np.geomspace(3e4, 6e5, n)):
        img = np.zeros(shape)
        for x in (25.3, 55.1, 84.8):
            for y in (24.9, 55.2, 85.1):
                s = 1.5 + 0.01 * f / 1e5
                img += f * np.exp(-0.5 * ((ii - x) ** 2 + (jj - y) ** 2) / s ** 2) / (2 * np.pi
                                                                                      * s * s)
        img = rng.poisson(img + 10.0) + rng.normal(0, 5.0, shape)
        hdr = fits.Header()
        if exptime:
            hdr["EXPTIME"] = float(k + 1)
        if bunit:
            hdr["BUNIT"] = bunit
        path = str(tmp_path / f"spot{k}.fits")
        fits.PrimaryHDU(img.astype(np.float32), header=hdr).writeto(path)
        paths.append(path)
    return paths


def test_spot_sim_then_spots_with_a_prediction(capsys, tmp_path):
    """Consistency: spot-sim writes a series (and twins) that spots reads; the
    JSON holds the slopes with their three errors, the exclusions per image,
    the per-spot slopes and the prediction of the sensor's template; --plot
    and --catalog write their files; the text report names the same figures."""
    out = tmp_path / "sim"
    assert main(["spot-sim", str(out), "--grid", "3", "3", "--n-images", "3", "--peak-max",
                 "2e4", "--twin", "--full-well", "9e4", "--bias", "200", "--updates", "100",
                 "--json", "--quiet"]) == 0
    sim = json.loads(capsys.readouterr().out)
    assert len(sim["images"]) == 3 and len(sim["twins"]) == 3 and os.path.isfile(sim["truth"])
    assert sim["settings"]["grid"] == [3, 3] and sim["exptimes"][0] == pytest.approx(0.1)
    argv = ["spots", *sim["images"], "--galsim-sensor", "lsst_itl_50_8", "--match", "none",
            "--plot", str(tmp_path / "s.png"), "--catalog", str(tmp_path / "s.ecsv"), "--quiet"]
    assert main(argv + ["--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["grid"]["n_spots"] == 9 and res["excluded"]["rows"] == 27
    assert [im["exptime"] for im in res["images"]] == pytest.approx(sim["exptimes"])
    size = res["slopes"]["size"]
    assert size["slope_err"] == max(size["err_formal"], size["err_image"], size["err_spot"])
    assert size["slope"] > 0 and res["predicted"]["size"]["predicted"] > 0
    assert res["predicted"]["template"].startswith("galsim:lsst_itl_50_8")
    assert len(res["per_spot"]) == 9 and "sigma_x_err" in res["per_spot"][0]
    assert os.path.isfile(res["plot"]) and os.path.isfile(res["catalog"])
    assert main(argv + ["--overwrite"]) == 0
    text = capsys.readouterr().out
    assert "9 spots, 3 images" in text and f"{size['slope']:+.3e}" in text
    assert "measured/predicted" in text
    # the output directory holds files: replaced only with --overwrite
    assert main(["spot-sim", str(out), "--quiet"]) == 3
    assert "use --overwrite" in capsys.readouterr().err


def test_spots_refuses_bad_input(capsys, tmp_path):
    """Bad input: ADU without a gain (the message names BUNIT = 'electron' and
    --gain), no EXPTIME, a missing file, and two templates are usage errors
    (exit status 2); with --gain the ADU series is measured."""
    os.makedirs(tmp_path / "adu")
    adu = _spot_files(tmp_path / "adu", bunit=None)
    assert main(["spots", *adu, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "BUNIT = 'electron'" in err and "--gain" in err and adu[0] in err
    assert main(["spots", *adu, "--gain", "1", "--quiet", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["grid"]["n_spots"] == 9
    os.makedirs(tmp_path / "nt")
    no_time = _spot_files(tmp_path / "nt", exptime=False)
    assert main(["spots", *no_time, "--quiet"]) == 2
    assert "no EXPTIME keyword" in capsys.readouterr().err
    assert main(["spots", str(tmp_path / "none.fits"), "--quiet"]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["spots", *adu, "--template", "t.fits", "--galsim-sensor", "x"]) == 2
    assert "not both" in capsys.readouterr().err


# --------------------------------------------------------------------------- calibrate --spots

def _flats_result(table):
    """What ``calibrate`` returns, without its minutes-long search: the cheap
    template of ``test_star_fit._calibration`` (GalSim ITL's a-matrix at
    strength 10, refined onto the bundled model) as a result with a fit of no
    parameter to the command's a-matrix."""
    from lsst_bfdrift.calibration.fitting import ParameterFit
    from lsst_bfdrift.calibration.tuning import CalibrationResult
    from lsst_bfdrift.templates.refine import combine_templates, template_alpha
    from tests.calibration.test_star_fit import _calibration

    base = _calibration()
    c, L = base.template.center, table.max_lag
    model = template_alpha(base.template)[c:c + L + 1, c:c + L + 1].T
    mask = table.mask()
    chi2 = float(np.sum(((table.a - model) / table.sigma)[mask] ** 2))
    fit = ParameterFit(names=[], values={}, errors={}, start={}, covariance=np.zeros((0, 0)),
                       correlation=np.zeros((0, 0)), data=table.a, sigma=table.sigma,
                       model=model, mask=mask, jacobian=np.zeros(table.a.shape + (0,)),
                       chi2=chi2, dof=int(mask.sum()), n_evaluations=0, seconds=0.0,
                       converged=True, at_bound=[])
    template = combine_templates(base.template, [], [],
                                 meta={**base.template.meta, "calibration": {}})
    return CalibrationResult(params=base.params, fit=fit, table=table, model=model,
                             template_acoeffs=model, template=template,
                             built_template=base.built_template, settings=base.settings,
                             candidates=base.candidates, selection=[],
                             sum_rule={"sum": 0.0, "error": 1.0}, seconds={"total": 0.0},
                             refined=True, poor_fit=False, misfit=None)


def _stub_calibrate(monkeypatch, calls, result):
    """Replace the command's ``calibrate`` (its signature kept: the parser reads
    its defaults) by ``result(table)``, recording the tables in ``calls``."""
    import functools

    from lsst_bfdrift.cli import calibration_commands

    @functools.wraps(calibration_commands.calibrate)
    def stub(table, **kw):
        calls.append(table)
        return result(table)
    monkeypatch.setattr(calibration_commands, "calibrate", stub)


def _calibrate_inputs(tmp_path, *, bunit="electron"):
    """The a-matrix of the cheap calibration as a text table, and the curl-free
    sensor's spot series (tests/calibration/_spot_series.py) as FITS files."""
    from tests.calibration._spot_series import curl_free_spots
    from tests.calibration.test_star_fit import _calibration

    table = _calibration().table
    rows = [(i, j, table.a[i, j], table.sigma[i, j]) for i in range(table.max_lag + 1)
            for j in range(table.max_lag + 1)]
    flats = tmp_path / "amatrix.txt"
    np.savetxt(flats, rows, header="i j a sigma")
    _, images, times = curl_free_spots()
    paths = []
    for k, (img, t) in enumerate(zip(images, times)):
        hdr = fits.Header()
        hdr["EXPTIME"] = t
        if bunit:
            hdr["BUNIT"] = bunit
        paths.append(str(tmp_path / f"spot{k}.fits"))
        fits.PrimaryHDU(img, header=hdr).writeto(paths[-1])
    return str(flats), paths


def test_calibrate_with_spots_end_to_end(capsys, tmp_path, monkeypatch):
    """Consistency of the command with the library: ``calibrate AMATRIX
    --spots SPOT_IMAGES`` reads the spot files, fits the template to the
    a-matrix and the spots (curl always in), prints the tension with its
    drivers and the held-out spots, and writes the template with the fit in
    its metadata. The flats calibration itself is stubbed with a cheap one
    (the real search takes minutes); everything from the spot files on is
    the command's."""
    from lsst_bfdrift.templates.template import DistortionTemplate

    calls = []
    _stub_calibrate(monkeypatch, calls, _flats_result)
    flats, spots = _calibrate_inputs(tmp_path)
    out = tmp_path / "joint.fits"
    code = main(["calibrate", flats, "--spots", *spots, "--out", str(out), "--holdout", "split",
                 "--quiet"])
    text, err = capsys.readouterr()
    assert code == 0, err
    assert len(calls) == 1
    assert "with 1 spot series: directions curl" in text
    assert "driven by the a_ij moved" in text and "held-out spots of" in text
    assert "(a-matrix and 1 spot series)" in text
    assert "asked to keep the correction's own slopes on its design (per 1e5 e): size " in text
    meta = DistortionTemplate.load(out).meta["calibration"]
    s = meta["spots"]
    assert s["directions"][0] == "curl" and s["kinds"] == ["spots"] and s["holdout"] == "split"
    assert 0 <= s["tension"]["p_value"] <= 1 and s["tension"]["drivers"]["slopes"]
    assert set(s["correction_bias"][s["fields"][0]]) == {"size", "e1", "e2"}
    held = s["held_out"][s["fields"][0]]
    assert held["kind"] == "spots" and held["n_stars"] > 0
    assert meta["inputs"] == [os.path.abspath(p) for p in [flats] + spots]


def test_calibrate_with_spots_refuses_bad_series(capsys, tmp_path, monkeypatch):
    """Bad input, refused before the flats are calibrated: spot images in ADU
    without a gain (exit 2, naming BUNIT and --gain), a series with too few
    spots per half for the cross-validation (exit 4, with the count), and
    --spots with LSST's routes (exit 2)."""
    from lsst_bfdrift.cli import calibration_commands

    calls = []
    _stub_calibrate(monkeypatch, calls, lambda table: None)
    flats, spots = _calibrate_inputs(tmp_path, bunit=None)
    out = tmp_path / "joint.fits"
    assert main(["calibrate", flats, "--spots", *spots, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "BUNIT = 'electron'" in err and "--gain" in err
    argv = ["calibrate", flats, "--spots", *spots, "--out", str(out), "--quiet", "--gain", "1"]
    assert main(argv + ["--min-spots", "13"]) == 4
    err = capsys.readouterr().err
    assert "12 usable spots to fit per half" in err and "need at least 13 spots" in err
    assert main(argv + ["--model", "astier23"]) == 2
    assert "--spots: options of --model electrostatic" in capsys.readouterr().err
    assert calls == [] and not out.exists()


# --------------------------------------------------------------------------- spot-plan

def _plan_json(path, names=("spot*",), *, out=None):
    """The part of ``calibrate --spots --json`` that spot-plan reads: the stated
    precisions of each fitted series (``spots.uncertainty``) and its counts."""
    unc = {"e1_slope_sigma": {n: {"flats_percent": 40.0, "joint_percent": 20.0}
                              for n in names},
           "size_slope_sigma": {n: {"flats_percent": 8.0, "joint_percent": 1.5}
                                for n in names}}
    doc = {"spots": {"uncertainty": unc, "fields": [
        {"name": n, "kind": "spots", "n_usable": 27, "n_fit": 27} for n in names]},
        "out": out or str(path) + ".missing.fits"}
    with open(path, "w") as fh:
        json.dump(doc, fh)
    return str(path)


def test_spot_plan_is_the_library_plan_of_the_stated_precision(capsys, tmp_path):
    """Consistency of the command with the library: spot-plan measures the series'
    design (9 spots, 3 levels) and prints spots_for_precision of the stated
    precisions for each goal, in JSON and in text."""
    from lsst_bfdrift.calibration.spot_plan import spots_for_precision

    files = _spot_files(tmp_path)
    cal = _plan_json(tmp_path / "cal.json")
    assert main(["spot-plan", cal, *files, "--goal-e1", "5", "--goal-size", "1", "--json",
                 "--quiet"]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert plan["series"] == "spot*" and plan["n_spots_fitted"] == 9
    assert len(plan["fitted_design"]["levels"]) == 3
    assert plan["fitted_design"]["sigma"] == pytest.approx(1.5, abs=0.2)
    rows = {r["quantity"]: r for r in plan["rows"]}
    assert rows["e1"]["spots"] == spots_for_precision(40.0, 20.0, 9, 5.0) > 9
    assert rows["e1"]["exposures"] == 3 * rows["e1"]["spots"]
    assert rows["size"]["spots"] == spots_for_precision(8.0, 1.5, 9, 1.0)
    assert main(["spot-plan", cal, *files, "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "9 spots x 3 levels" in text and "+- 40.0 % (flats alone) -> +- 20.0 %" in text
    assert f"e1 to +- 5 %: {spots_for_precision(40.0, 20.0, 9, 5.0)} spots" in text


def test_spot_plan_refuses_bad_input(capsys, tmp_path):
    """Bad input: a JSON without a spot fit's stated precision, several fitted
    series without --series (the names listed), an unknown --series, a goal not
    positive, and other spot sizes without a template (each exit 2 with the
    reason)."""
    files = _spot_files(tmp_path)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"a_fit": {}}))
    assert main(["spot-plan", str(bad), *files, "--quiet"]) == 2
    assert "no stated spot precision" in capsys.readouterr().err
    two = _plan_json(tmp_path / "two.json", names=("a*", "b*"))
    assert main(["spot-plan", two, *files, "--quiet"]) == 2
    assert "fitted 2 spot series; name one with --series (a*, b*)" in capsys.readouterr().err
    assert main(["spot-plan", two, *files, "--series", "c*", "--quiet"]) == 2
    assert "--series 'c*' is not a fitted spot series" in capsys.readouterr().err
    cal = _plan_json(tmp_path / "cal.json")
    assert main(["spot-plan", cal, *files, "--goal-e1", "-5", "--quiet"]) == 2
    assert "--goal-e1 must be positive percentages, got [-5.0]" in capsys.readouterr().err
    assert main(["spot-plan", cal, *files, "--sigma", "2", "--quiet"]) == 2
    assert "give --template" in capsys.readouterr().err
