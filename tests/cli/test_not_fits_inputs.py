"""A file that is not FITS given where a FITS file is read (issue 43 item 3):
one clear error naming the file, once, on stderr, and a nonzero exit status;
never astropy's advice to pass ``ignore_missing_simple=True``."""

import json

import numpy as np
import pytest
from astropy.io import fits

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.ptc.inputs import detect_input_kind
from lsst_bfdrift.templates.template import DistortionTemplate
from lsst_bfdrift.utils.errors import InputFileError, TemplateFileError
from lsst_bfdrift.utils.io import not_fits_reason, open_fits


@pytest.fixture
def bad(tmp_path):
    """A text file named .fits, an empty one and a second text file."""
    (tmp_path / "bad.fits").write_text("hello this is text\n")
    (tmp_path / "bad2.fits").write_text("hello this is text\n")
    (tmp_path / "empty.fits").write_bytes(b"")
    return tmp_path


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_not_fits_reason_says_what_the_file_is(bad, tmp_path):
    assert "text file starting with 'hello this is text'" in not_fits_reason(bad / "bad.fits")
    assert "the file is empty" in not_fits_reason(bad / "empty.fits")
    (tmp_path / "bin.fits").write_bytes(b"\x00\x01\x02\xff" * 10)
    assert "starts with the bytes" in not_fits_reason(tmp_path / "bin.fits")
    fits.PrimaryHDU(np.zeros((2, 2))).writeto(tmp_path / "ok.fits")
    assert not_fits_reason(tmp_path / "ok.fits") is None
    with pytest.raises(InputFileError, match=r"bad\.fits: not a FITS file: it is a text file"):
        with open_fits(bad / "bad.fits"):
            pass
    with pytest.raises(TemplateFileError,
                       match=r"bad\.fits: cannot read template file: not a FITS file"):
        DistortionTemplate.load(bad / "bad.fits")
    with pytest.raises(InputFileError, match=r"bad\.fits: not a FITS file.*accepted: FITS flats"):
        detect_input_kind(bad / "bad.fits")


@pytest.mark.parametrize("argv", [
    ["maps", "{bad}", "--quiet"],
    ["maps", "--template", "{bad}", "--quiet"],
    ["validate-sky", "{bad}", "--quiet"],
    ["ptc", "{bad}", "{bad2}"],
    ["calibrate", "{bad}", "{bad2}", "--out", "{tmp}/x.fits"],
    ["diagnose", "{bad}"],
    ["calibrate", "/work/shared/data/measured/itl_covariances_21oct19.txt", "--out",
     "{tmp}/y.fits", "--stars", "{bad}", "--quiet"],
])
def test_commands_name_a_file_that_is_not_fits(capsys, bad, argv):
    argv = [a.format(bad=bad / "bad.fits", bad2=bad / "bad2.fits", tmp=bad) for a in argv]
    code, out, err = _run(capsys, *argv)
    assert code == 2 and out == ""
    assert "bad.fits: " in err and "not a FITS file: it is a text file starting with" in err
    assert "ignore_missing_simple" not in err
    assert err.count("not a FITS file") == 1


def test_correct_reports_a_file_that_is_not_fits_once_and_not_done(capsys, bad):
    code, out, err = _run(capsys, "correct", bad / "bad.fits", bad / "out.fits")
    assert code == 1
    assert out == ""  # the failure is said once, on stderr
    assert err.count("not a FITS file") == 1 and "ignore_missing_simple" not in err
    assert "bfdrift correct: error:" in err and "InputFileError" not in err
    assert "done" not in err and "100.0%" not in err and "bad.fits: failed" in err
    assert not (bad / "out.fits").exists()
    # several files: each failure once, a count, the JSON keeps the message
    code, out, err = _run(capsys, "correct", bad / "bad.fits", bad / "empty.fits", "--out-dir",
                          bad / "od", "--quiet", "--json")
    res = json.loads(out)
    assert code == 1 and res["failed"] == 2
    assert "the file is empty" in res["files"][1]["error"]
    assert err.count("not a FITS file") == 2 and "2 of 2 files failed" in err


def test_ptc_says_what_runs_and_warns_of_exptime_before_the_fit(capsys, tmp_path):
    """Issue 43 item 1: `bfdrift ptc` (and calibrate, through the same reader)
    labels its stages from the start, and flats whose levels do not follow
    EXPTIME are said before the covariance model fit, naming the files."""
    rng = np.random.default_rng(4)
    for k, level in enumerate((2e3, 6e3, 1.2e4, 2.4e4, 4e4)):
        for half in "ab":
            hdr = fits.Header({"EXPTIME": float(k + 1), "BUNIT": "adu", "GAIN": 1.0})
            fits.PrimaryHDU(rng.poisson(level, (48, 48)).astype(np.float32),
                            header=hdr).writeto(tmp_path / f"flat_{k}{half}.fits")
    code, out, err = _run(capsys, "ptc", tmp_path, "--max-lag", "1")
    assert code == 0, err
    lines = err.splitlines()
    assert lines[0].startswith("ptc: reading 10 flats, covariances of their pairs   0.0%")
    warn = next(k for k, ln in enumerate(lines) if "not proportional to EXPTIME" in ln)
    fit = next(k for k, ln in enumerate(lines) if ln.startswith("ptc: covariance model fit"))
    assert warn < fit and lines[warn].startswith("bfdrift ptc: warning:")
    assert "flat_0a.fits, flat_0b.fits: EXPTIME 1 s" in lines[warn]
    assert "done in" in lines[-1]
    code, out, err = _run(capsys, "ptc", tmp_path, "--max-lag", "1", "--quiet")
    assert code == 0 and err.count("\n") == 1 and "not proportional" in err
