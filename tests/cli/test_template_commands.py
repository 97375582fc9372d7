"""Tests of lsst_bfdrift.cli.template_commands: per-band ``template build`` and ``summary``."""

import json

import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.cli.template_commands import band_sources
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.bands import build_band_templates, load_templates
from lsst_bfdrift.templates.template import TemplateSettings

TINY = ["--size", "3", "--samples", "2", "--tol", "1e-2", "--workers", "1", "--quiet"]


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_build_bands_and_wavelength_one_file(capsys, tmp_path):
    """CONSISTENCY: the CLI's multi-band file equals build_band_templates with the same inputs."""
    out = tmp_path / "bands.fits"
    code, text, err = _run(capsys, "template", "build", "--out", str(out), "--band", "u",
                           "--band", "y", "--wavelength", "700", "--nodes", "3", "--json",
                           *TINY)
    assert code == 0, err
    s = json.loads(text)
    assert s["bands"] == ["u", "y", "700nm"]
    mb = load_templates(out)
    assert mb.bands == ("u", "y", "700nm")
    ref = build_band_templates(SensorParameters(), ("u", "y", 700.0), nodes=3,
                               settings=TemplateSettings(size=3, edge_samples=2, tol=1e-2,
                                                         workers=1))
    for key in mb.bands:
        assert_allclose(mb[key].corner_d, ref[key].corner_d, rtol=0, atol=0)
        assert s["summary"][key]["A00"] == pytest.approx(ref[key].summary()["A00"], rel=1e-12)
    assert s["summary"]["y"]["A00"] > s["summary"]["u"]["A00"]  # y distorts less
    code, text, _ = _run(capsys, "template", "summary", str(out), "--json")
    assert code == 0 and set(json.loads(text)) == {"u", "y", "700nm"}


def test_band_sources():
    assert band_sources(["all"], None) == ["u", "g", "r", "i", "z", "y"]
    assert band_sources(["r", "ALL"], [500.0]) == ["r", "u", "g", "i", "z", "y", 500.0]
    assert band_sources(None, None) == []


@pytest.mark.parametrize("extra, match", [
    (["--band", "w"], "unknown band 'w'"),
    (["--wavelength", "2000"], "outside the silicon absorption table"),
    (["--sed", "5800K"], "--sed applies to per-band templates"),
    (["--nodes", "4"], "--nodes applies to per-band templates"),
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
