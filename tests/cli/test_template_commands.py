"""Tests of lsst_bfdrift.cli.template_commands: per-band ``template build`` and ``summary``."""

import json

import pytest
import numpy as np
from numpy.testing import assert_allclose

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.cli.template_commands import band_sources
from lsst_bfdrift.templates.bands import band_weights, load_templates
from lsst_bfdrift.templates.template import TemplateSettings

TINY = ["--size", "3", "--samples", "2", "--tol", "1e-2", "--workers", "1", "--quiet"]


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_build_bands_and_wavelength_one_file(capsys, tmp_path):
    """CONSISTENCY: the CLI's multi-band file holds the bands asked for, each built on the
    default sensor's grid of conversion heights with the band's weights, at the options'
    settings."""
    out = tmp_path / "bands.fits"
    code, text, err = _run(capsys, "template", "build", "--out", str(out), "--band", "u",
                           "--band", "y", "--wavelength", "700", "--nodes", "3", "--json",
                           *TINY)
    assert code == 0, err
    s = json.loads(text)
    assert s["bands"] == ["u", "y", "700nm"]
    mb = load_templates(out)
    assert mb.bands == ("u", "y", "700nm")
    z, weights, _ = band_weights(("u", "y", 700.0), nodes=3)  # the default sensor's grid
    for key in mb.bands:
        depth = mb[key].meta["depth"]
        assert_allclose(depth["nodes"], z)
        assert_allclose(depth["weights"], weights[key])
        assert s["summary"][key]["A00"] == pytest.approx(mb[key].summary()["A00"], rel=1e-12)
        assert mb[key].meta["settings"]["size"] == 3
    assert s["summary"]["y"]["A00"] > s["summary"]["u"]["A00"]  # y distorts less
    code, text, _ = _run(capsys, "template", "summary", str(out), "--json")
    assert code == 0 and set(json.loads(text)) == {"u", "y", "700nm"}


def test_a_cold_sensor_builds_a_weaker_y_template(capsys, tmp_path):
    """CONSISTENCY with the absorption model: at 173 K the y photons convert deeper, so
    the y template's A00 shrinks less than at 300 K, the u template's hardly moves, and the
    files record the temperature."""
    a00 = {}
    for temp in ("300", "173"):
        out = tmp_path / f"bands_{temp}.fits"
        code, text, err = _run(capsys, "template", "build", "--out", str(out), "--band", "u",
                               "--band", "y", "--nodes", "3", "--temperature", temp, "--json",
                               *TINY)
        assert code == 0, err
        a00[temp] = {k: v["A00"] for k, v in json.loads(text)["summary"].items()}
        mb = load_templates(out)
        assert mb["y"].meta["depth"]["temperature"] == float(temp)
    loss = {t: {k: 1 - v for k, v in a.items()} for t, a in a00.items()}  # area lost: > 0
    assert loss["173"]["y"] < 0.99 * loss["300"]["y"]       # 3 % weaker on this tiny grid
    assert abs(loss["173"]["u"] - loss["300"]["u"]) < 0.002 * loss["300"]["u"]


def test_band_sources():
    assert band_sources(["all"], None) == ["u", "g", "r", "i", "z", "y"]
    assert band_sources(["r", "ALL"], [500.0]) == ["r", "u", "g", "i", "z", "y", 500.0]
    assert band_sources(None, None) == []


@pytest.mark.parametrize("extra, match", [
    (["--band", "w"], "unknown band 'w'"),
    (["--wavelength", "2000"], "outside the silicon absorption table"),
    (["--sed", "5800K"], "--sed applies to per-band templates"),
    (["--nodes", "4"], "--nodes applies to per-band templates"),
    (["--temperature", "173"], "--temperature applies to per-band templates"),
    (["--band", "y", "--temperature", "5"], "temperature must lie in [20, 500] K"),
    (["--band", "r", "--sed", "nonesuch"], "unknown sed 'nonesuch'"),
])
def test_bad_band_input(capsys, tmp_path, extra, match):
    out = tmp_path / "x.fits"
    code, _, err = _run(capsys, "template", "build", "--out", str(out), *TINY, *extra)
    assert code == 2 and match in err
    assert not out.exists()


def test_bad_depth_response_choice(capsys, tmp_path):
    with pytest.raises(SystemExit) as exc:
        main(["template", "build", "--out", str(tmp_path / "x.fits"), "--band", "r",
              "--depth-response", "exact"])
    assert exc.value.code == 2 and "invalid choice" in capsys.readouterr().err


# -- bfdrift calibrate --band (templates for every band from one calibration) ----------


PTC = "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt"


def test_calibrate_band_writes_every_band(capsys, tmp_path, monkeypatch):
    """CONSISTENCY: calibrate --band r writes six bands; r is the calibrated template, the
    others differ by the model's band change; the a00 table carries errors from the fit's
    covariance. (The fit is replaced by a tiny calibrated template with a known Jacobian
    and covariance: the test is of the command's wiring, the fit has its own tests.)"""
    import functools
    import types

    from lsst_bfdrift.cli import calibration_commands as cc
    from lsst_bfdrift.physics.sensor import SensorParameters
    from lsst_bfdrift.templates.template import build_template
    tpl = build_template(SensorParameters.paper(), TemplateSettings(size=3, edge_samples=2,
                                                                     tol=1e-2, workers=1))
    jac = np.zeros((2, 2, 1))
    jac[0, 0, 0] = 4e-7
    tpl.meta["calibration"] = {"max_lag": 1, "uncertainty": {
        "kind": "parameters", "jacobian": jac.tolist(), "covariance": [[0.01]]}}
    fit = types.SimpleNamespace(jacobian=jac, covariance=np.array([[0.01]]))
    res = types.SimpleNamespace(template=tpl, fit=fit, summary=lambda: {"names": ["x"]})
    monkeypatch.setattr(cc, "calibrate", functools.wraps(cc.calibrate)(lambda table, **kw: res))
    out = tmp_path / "cal.fits"
    code, text, err = _run(capsys, "calibrate", PTC, "--out", str(out), "--band", "r",
                           "--band-nodes", "3", "--json", "--quiet")
    assert code == 0, err
    s = json.loads(text)
    mb = load_templates(out)
    assert mb.bands == ("u", "g", "r", "i", "z", "y")
    assert s["bands"]["flats"] == "r"
    rows = s["bands"]["a00"]
    assert rows["u"]["a00"] < rows["r"]["a00"] < rows["y"]["a00"] < 0
    for b in mb.bands:
        assert rows[b]["a00_err_params"] == pytest.approx(
            abs(rows[b]["ratio_a00"]) * 4e-7 * 0.1, rel=1e-12)
    assert_allclose(mb["r"].corner_d, tpl.corner_d, rtol=0)
    assert mb["r"].meta["calibration"]["inputs"] == [PTC]
    assert mb["z"].meta["calibration"]["band"]["flats"] == "r"
    # the same at the sensor's operating temperature: recorded, y weaker, r unchanged
    cold = tmp_path / "cold.fits"
    code, text, err = _run(capsys, "calibrate", PTC, "--out", str(cold), "--band", "r",
                           "--band-nodes", "3", "--temperature", "173", "--json", "--quiet")
    assert code == 0, err
    mc = load_templates(cold)
    assert mc["y"].meta["depth"]["temperature"] == 173.0
    assert_allclose(mc["r"].corner_d, tpl.corner_d, rtol=0)
    cold_rows = json.loads(text)["bands"]["a00"]
    assert cold_rows["y"]["ratio_a00"] < rows["y"]["ratio_a00"]


def _flat_file(path, **keys):
    from astropy.io import fits
    hdr = fits.Header({"EXPTIME": 1.0, **keys})
    fits.HDUList([fits.PrimaryHDU(header=hdr),
                  fits.ImageHDU(np.zeros((4, 4), np.float32))]).writeto(path)
    return str(path)


def test_calibrate_band_refusals(capsys, tmp_path):
    """Refused before any fit, with nothing written."""
    out = tmp_path / "x.fits"
    code, _, err = _run(capsys, "calibrate", PTC, "--out", str(out), "--band", "q", "--quiet")
    assert code == 2 and "unknown band 'q'" in err
    code, _, err = _run(capsys, "calibrate", PTC, "--out", str(out), "--band", "header",
                        "--quiet")
    assert code == 2 and "--band header reads the FILTER or BAND keyword" in err
    code, _, err = _run(capsys, "calibrate", PTC, "--out", str(out), "--band", "r", "--model",
                        "astier23", "--quiet")
    assert code == 2 and "--band" in err and "options of --model electrostatic" in err
    code, _, err = _run(capsys, "calibrate", PTC, "--out", str(out), "--temperature", "173",
                        "--quiet")
    assert code == 2 and "--temperature sets the absorption lengths" in err
    code, _, err = _run(capsys, "calibrate", PTC, "--out", str(out), "--band", "r",
                        "--temperature", "900", "--quiet")
    assert code == 2 and "temperature must lie in [20, 500] K" in err
    a = _flat_file(tmp_path / "a.fits", FILTER="r_57")
    b = _flat_file(tmp_path / "b.fits", BAND="g")
    c = _flat_file(tmp_path / "c.fits")
    code, _, err = _run(capsys, "calibrate", a, b, "--out", str(out), "--band", "header",
                        "--quiet")
    assert code == 2 and "flats are of different bands (a.fits: r, b.fits: g)" in err
    code, _, err = _run(capsys, "calibrate", a, c, "--out", str(out), "--band", "header",
                        "--quiet")
    assert code == 2 and "c.fits has no BAND or FILTER keyword" in err
    assert not out.exists()


def test_flats_band_from_headers(tmp_path):
    import argparse

    from lsst_bfdrift.cli.calibration_commands import _flats_band
    a = _flat_file(tmp_path / "a.fits", FILTER="i_39")
    b = _flat_file(tmp_path / "b.fits", BAND="i", FILTER="i_39")
    assert _flats_band(argparse.Namespace(band="header", input=[a, b])) == "i"
    assert _flats_band(argparse.Namespace(band="LSST_z", input=[a])) == "z"
    assert _flats_band(argparse.Namespace(band=None, input=[a])) is None


def test_correct_with_a_multi_band_template(capsys, tmp_path):
    """CONSISTENCY: bfdrift correct --band y uses the file's y template (BFBAND in the output);
    without a band, an image lacking BAND/FILTER is refused naming the keywords."""
    from astropy.io import fits

    from lsst_bfdrift.templates.bands import MultiBandTemplate, combine_templates
    from lsst_bfdrift.templates.template import load_default_template
    d = load_default_template()
    tpath = tmp_path / "bands.fits"
    MultiBandTemplate({"r": d, "y": combine_templates([d], [0.5])}).save(tpath)
    yy, xx = np.mgrid[:40, :40] - 20.0
    img = 500.0 + 2e5 / (2 * np.pi * 1.4**2) * np.exp(-0.5 * (xx**2 + yy**2) / 1.4**2)
    src = tmp_path / "in.fits"
    fits.PrimaryHDU(img, header=fits.Header({"BUNIT": "electron"})).writeto(src)
    out = tmp_path / "out.fits"
    code, _, err = _run(capsys, "correct", str(src), str(out), "--template", str(tpath),
                        "--band", "y", "--no-geometry")
    assert code == 0, err
    assert fits.getheader(out)["BFBAND"] == "y"
    code, _, err = _run(capsys, "correct", str(src), str(tmp_path / "o2.fits"), "--template",
                        str(tpath), "--no-geometry")
    assert code != 0 and "read header keywords BAND, FILTER" in err
    # an LSST-layout file: FILTER in the primary header, inherited by the IMAGE HDU
    lsst = tmp_path / "lsst.fits"
    fits.HDUList([fits.PrimaryHDU(header=fits.Header({"FILTER": "y_10"})),
                  fits.ImageHDU(img, header=fits.Header({"BUNIT": "electron", "INHERIT": True}),
                                name="IMAGE")]).writeto(lsst)
    out3 = tmp_path / "o3.fits"
    code, _, err = _run(capsys, "correct", str(lsst), str(out3), "--template", str(tpath),
                        "--no-geometry")
    assert code == 0, err
    with fits.open(out3) as h:
        band = h[0].header.get("BFBAND", h["IMAGE"].header.get("BFBAND"))
        assert_allclose(h["IMAGE"].data, fits.getdata(out, 0), rtol=1e-6)
    assert band == "y"
