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
