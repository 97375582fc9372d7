"""Tests of lsst_bfdrift.validation.sky (validate-sky) on synthetic catalogs and GalSim fields."""

import json

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose

from tests.validation._galsim_fields import STRENGTHS, galsim_template, paired_fields
from lsst_bfdrift.cli.main import main
from lsst_bfdrift.catalogs.slopes import shape_flux_relations
from lsst_bfdrift.validation.sky import sky_verdict, validate_sky
from lsst_bfdrift.simulation.skysim import scale_template


def test_too_few_stars_and_all_saturated_get_clear_messages():
    rng = np.random.default_rng(3)
    import galsim

    from lsst_bfdrift.catalogs.catalog import measure_stars
    img = galsim.ImageD(160, 160, xmin=0, ymin=0)
    for k in range(9):
        galsim.Gaussian(sigma=1.8, flux=2e5).drawImage(
            img, scale=1.0, add_to_image=True,
            center=galsim.PositionD(25 + 50 * (k % 3), 25 + 50 * (k // 3)))
    arr = img.array + rng.normal(800.0, 28.0, img.array.shape)
    cat = measure_stars(arr, saturation=2000.0)
    assert len(cat) == 9 and np.all(cat["flag_saturated"])
    with pytest.raises(ValueError, match=r"only 0 of 9 .*9 saturated"):
        shape_flux_relations(cat)
    with pytest.raises(ValueError, match="catalog is empty"):
        shape_flux_relations(cat[:0])
    with pytest.raises(ValueError, match="no sources detected"):
        validate_sky(rng.normal(800.0, 28.0, (128, 128)))
    with pytest.raises(ValueError, match="no usable pixel"):
        validate_sky(np.full((128, 128), np.nan))
    with pytest.raises(ValueError, match="blank"):
        validate_sky(np.zeros((128, 128)))
    with pytest.raises(ValueError, match="route"):
        validate_sky(arr, route="sideways")


@pytest.mark.slow
def test_galsim_fields_known_strengths():
    """Size-flux slope of SiliconSensor fields scales with strength; zero strength is null."""
    fields = paired_fields()
    tpl = galsim_template()
    res = {}
    for s, img in zip(STRENGTHS, fields["images"]):
        v = validate_sky(img, template=scale_template(tpl, max(s, 1.0)), n_boot=100)
        res[s] = v
    lo, mid, hi = STRENGTHS
    s0, s1, s2 = (res[s].fits["before"]["size"] for s in STRENGTHS)
    assert not res[lo].summary["bf_detected_before"] and abs(s0["z"]) < 3
    # expected z ~ 0.8 per unit strength here (22 stars), so both are detected
    assert res[mid].summary["bf_detected_before"] and res[hi].summary["bf_detected_before"]
    # the same photons and noise in all three fields: the slope difference is linear
    assert_allclose((s2["slope"] - s0["slope"]) / (s1["slope"] - s0["slope"]),
                    (hi - lo) / (mid - lo), rtol=0.15)
    per_strength = (s2["slope"] - s0["slope"]) / (hi - lo)
    assert 3e-4 < per_strength < 1.2e-3  # GalSim lsst_itl_50_8, Moffat 0.7-0.95"
    for s in (mid, hi):
        assert not res[s].summary["residual_bf_detected"], res[s].summary["verdict"]
        assert "BF removed" in res[s].summary["verdict"]
    # correcting a BF-free image with a strength-`mid` template over-corrects: detected
    v = validate_sky(fields["images"][0], template=scale_template(tpl, mid), n_boot=0)
    assert v.summary["residual_bf_detected"] and "over-corrected" in v.summary["verdict"]
    # no correction: the verdict is about the recorded image only
    v = validate_sky(fields["images"][2], route="none", n_boot=0)
    assert v.summary["after"] == {} and v.summary["verdict"].startswith("BF slope detected")


@pytest.mark.slow
def test_cli_validate_sky_adu_json_and_plot(tmp_path, capsys):
    img = paired_fields()["images"][2]
    hdr = fits.Header()
    hdr["BUNIT"] = "ADU"
    hdr["GAIN"] = 1.7
    path = tmp_path / "field.fits"
    fits.PrimaryHDU((img / 1.7).astype(np.float32), header=hdr).writeto(path)
    tpl_path = tmp_path / "tpl.fits"
    scale_template(galsim_template(), STRENGTHS[2]).save(str(tpl_path))
    png = tmp_path / "sky.png"
    cat = tmp_path / "cat.ecsv"
    rc = main(["validate-sky", str(path), "--json", "--plot", str(png), "--template",
               str(tpl_path), "--route", "both", "--catalog", str(cat), "--quiet",
               "--n-boot", "50"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["gain"] == pytest.approx(1.7)
    assert out["bf_detected_before"] and not out["residual_bf_detected"]
    assert set(out["after"]) == {"catalog", "pixel"}
    for route in ("catalog", "pixel"):
        assert abs(out["after"][route]["size"]["slope"]) < 0.25 * out["before"]["size"]["slope"]
    assert png.stat().st_size > 10000 and cat.stat().st_size > 1000
    blank = tmp_path / "blank.fits"
    fits.PrimaryHDU(np.zeros((64, 64), np.float32)).writeto(blank)
    assert main(["validate-sky", str(blank), "--quiet"]) == 2
    assert "blank" in capsys.readouterr().err


def _rel(z_size, z_e1=0.0, z_e2=0.0, err=1e-4):
    return {k: {"slope": z * err, "slope_err": err, "z": z}
            for k, z in (("size", z_size), ("e1", z_e1), ("e2", z_e2))}


def test_verdict_and_json_give_the_same_signed_significance():
    """Issue 43 item 5: --json said significance_before 0.94 where the verdict
    said z = -0.9; both are the signed z of the size slope now."""
    out = sky_verdict({"before": _rel(-0.94), "catalog": _rel(0.3, z_e1=-1.2)})
    assert out["significance_before"] == pytest.approx(-0.94)
    assert "z = -0.9" in out["verdict"] and not out["bf_detected_before"]
    assert out["significance_after"] == {"catalog": pytest.approx(0.3)}
    assert out["max_significance_after"] == {"catalog": pytest.approx(1.2)}
    assert not out["residual_bf_detected"]
    # a strong slope of the opposite sign is no BF detection, and is said to be so
    out = sky_verdict({"before": _rel(-5.0)})
    assert out["significance_before"] == -5.0 and not out["bf_detected_before"]
    assert "opposite sign to BF" in out["verdict"] and "z = -5.0" in out["verdict"]
    out = sky_verdict({"before": _rel(4.7), "pixel": _rel(-3.5)})
    assert out["bf_detected_before"] and out["residual_bf_detected"]
    assert out["significance_after"]["pixel"] == -3.5 and "over-corrected" in out["verdict"]
    assert "z = +4.7" in out["verdict"] and out["significance_before"] == 4.7


def test_one_spelling_of_catalog():
    """Issue 43 item 5: "catalog" (astropy's, photutils') everywhere: package,
    command-line help, docs and README."""
    import pathlib

    from lsst_bfdrift.cli.main import build_parser
    root = pathlib.Path(__file__).resolve().parents[2]
    files = [p for d in ("lsst_bfdrift", "docs") for p in (root / d).rglob("*")
             if p.suffix in (".py", ".rst", ".md", ".txt", ".yaml") and "_build" not in p.parts]
    files.append(root / "README.md")
    found = [str(p.relative_to(root)) for p in files if "catalogue" in p.read_text().lower()]
    assert found == []
    parser = build_parser()
    helps = [parser.format_help()]
    for action in parser._subparsers._group_actions:
        helps += [sub.format_help() for sub in action.choices.values()]
    assert not any("catalogue" in h.lower() for h in helps)
