"""Tests of the one unit, gain and saturation rule (lsst_bfdrift.images.electrons).

Kinds: the rule tables are checked against hand-written expectations (the
rule as the module docstring states it); the command tests check that
every command that reads an image (ptc, calibrate, correct, maps,
validate-sky) gives the same answer for the same file (consistency across
entry points); the conversions are checked against the direct product
image x gain.
"""

import json

import astropy.units as u
import numpy as np
import pytest
from astropy.io import fits
from astropy.nddata import CCDData, NDData
from numpy.testing import assert_allclose

from lsst_bfdrift.images.electrons import (ImageUnit, gain_value, image_unit, saturation_level,
                                           to_electrons)
from lsst_bfdrift.images.exposure import read_image
from lsst_bfdrift.utils.errors import InputError, InputFileError


def _write(path, data, **cards):
    hdr = fits.Header()
    for k, v in cards.items():
        hdr[k] = v
    fits.PrimaryHDU(np.asarray(data, dtype=np.float32), header=hdr).writeto(path)
    return str(path)


@pytest.mark.parametrize("stated, gain, header_gain, from_file, expect", [
    ("electron", None, None, True, ("electron", 1.0, "BUNIT")),
    ("e-", None, 1.7, True, ("electron", 1.0, "BUNIT")),  # a GAIN in an e image is ignored
    ("ADU", None, 1.7, True, ("adu", 1.7, "BUNIT")),
    ("adu", 2.0, 1.7, True, ("adu", 2.0, "BUNIT")),  # the caller's gain first
    ("adu", None, None, True, ("adu", None, "BUNIT")),
    ("", 2.0, None, True, ("adu", 2.0, "gain")),
    (None, None, 1.7, True, ("adu", 1.7, "gain")),
    (None, None, None, True, ("adu", None, "none")),  # a file that says neither
    (None, None, None, False, ("electron", 1.0, "memory")),  # an array
    (u.electron, None, None, False, ("electron", 1.0, "BUNIT")),
    (u.adu, 3.0, None, False, ("adu", 3.0, "BUNIT")),
    (u.dimensionless_unscaled, None, None, False, ("electron", 1.0, "memory")),
])
def test_the_unit_rule(stated, gain, header_gain, from_file, expect):
    unit = image_unit(stated, gain=gain, header_gain=header_gain, from_file=from_file)
    assert isinstance(unit, ImageUnit)
    assert (unit.unit, unit.gain, unit.origin) == expect
    assert unit.known == (expect[1] is not None)


@pytest.mark.parametrize("stated, gain, header_gain, match", [
    ("electron", 2.0, None, r"img.fits: a gain of 2 e/ADU was given \(--gain\) but the image "
                            "states it is in electrons"),
    ("MJy/sr", None, None, r"img.fits: BUNIT = MJy/sr is not a charge image; accepted"),
    (None, 0.0, None, r"--gain 0.0 is not positive and finite"),
    (None, -1.0, None, r"--gain -1.0 is not positive"),
    (None, float("nan"), None, r"--gain nan is not positive"),
    (None, True, None, r"--gain True is not a number of e/ADU"),
    (None, None, "abc", r"img.fits: GAIN keyword 'abc' is not a number"),
    (None, None, -2.0, r"img.fits: GAIN keyword -2.0 is not positive"),
])
def test_the_unit_rule_refuses(stated, gain, header_gain, match):
    with pytest.raises(InputError, match=match):
        image_unit(stated, gain=gain, header_gain=header_gain, source="img.fits",
                   gain_name="--gain")


def test_to_electrons_converts_with_the_gain(tmp_path):
    """ADU x gain, against the direct product; the input file is not changed."""
    rng = np.random.default_rng(11)
    adu = rng.normal(500.0, 20.0, (32, 40))
    path = _write(tmp_path / "a.fits", adu, BUNIT="adu", GAIN=1.5)
    before = (tmp_path / "a.fits").read_bytes()
    img = to_electrons(path)
    assert_allclose(img.data, adu.astype(np.float32).astype(np.float64) * 1.5, rtol=1e-12)
    assert (img.gain, img.unit.unit, img.kind) == (1.5, "adu", "path")
    img2 = to_electrons(path, gain=2.0)
    assert_allclose(img2.data, adu.astype(np.float32).astype(np.float64) * 2.0, rtol=1e-12)
    assert (tmp_path / "a.fits").read_bytes() == before
    arr = adu.copy()
    assert to_electrons(arr).data is arr  # float64 electrons: no copy, never written


def test_a_file_without_unit_or_gain_is_refused_where_electrons_are_needed(tmp_path):
    path = _write(tmp_path / "raw.fits", np.ones((16, 16)))
    with pytest.raises(InputError, match=r"raw.fits: the image states no unit \(no BUNIT or "
                                         r"LSST ISR UNITS\) and no gain .* --gain 1\)"):
        to_electrons(path, gain_name="--gain")
    assert to_electrons(path, gain=1.0).gain == 1.0
    path = _write(tmp_path / "adu.fits", np.ones((16, 16)), BUNIT="ADU")
    with pytest.raises(InputError, match=r"adu.fits: the image is in ADU \(BUNIT\) and no gain"):
        to_electrons(path)


@pytest.mark.parametrize("given, header, level, origin", [
    (None, {}, None, None),
    (1000.0, {}, 1500.0, "given"),
    (None, {"SATURATE": 2000}, 3000.0, "SATURATE"),
    (1000.0, {"SATURATE": 2000}, 1500.0, "given"),
])
def test_the_saturation_rule(given, header, level, origin):
    img = np.random.default_rng(2).normal(100.0, 5.0, (20, 20))
    got = saturation_level(img, saturation=given, header=header, gain=1.5)
    assert got[:2] == (level, origin) and got[2] is None


@pytest.mark.parametrize("given, header, match", [
    (True, {}, "saturation True is not a positive level"),
    (float("nan"), {}, "saturation nan is not a positive level"),
    (-5.0, {}, "saturation -5.0 is not a positive level"),
    (None, {"SATURATE": "high"}, "img: SATURATE keyword 'high' is not a positive level"),
    (None, {"SATURATE": 0}, "img: SATURATE keyword 0 is not a positive level"),
])
def test_the_saturation_rule_refuses(given, header, match):
    with pytest.raises(InputError, match=match):
        saturation_level(np.ones((4, 4)), saturation=given, header=header, source="img")


def test_a_plateau_is_the_saturation_with_a_warning():
    img = np.random.default_rng(4).normal(1000.0, 30.0, (40, 40))
    img[5, 5:9] = 7.5e4
    level, origin, warning = saturation_level(img)
    assert (level, origin) == (7.5e4, "plateau")
    assert "4 pixels share the image's largest value, 75000 e" in warning
    image = to_electrons(img)
    assert image.saturation == 7.5e4 and image.saturated.sum() == 4
    assert image.warnings == [warning]


@pytest.mark.parametrize("make", ["ccddata", "nddata", "masked", "ndarray"])
def test_every_in_memory_kind(make):
    """Each accepted in-memory input gives the same electrons (unit stated or not)."""
    data = np.random.default_rng(9).normal(200.0, 10.0, (12, 14))
    mask = np.zeros(data.shape, bool)
    mask[3, 4] = True
    obj = {"ccddata": lambda: CCDData(data / 2.0, unit="adu", mask=mask, meta={"GAIN": 2.0}),
           "nddata": lambda: NDData(data, mask=mask),
           "masked": lambda: np.ma.MaskedArray(data, mask=mask),
           "ndarray": lambda: data}[make]()
    image = to_electrons(obj)
    assert_allclose(image.data, data, rtol=1e-12)
    assert image.kind == make
    assert bool(image.bad[3, 4]) == (make != "ndarray")


def test_truncated_fits_is_named(tmp_path):
    """A truncated FITS gives an error naming the file and saying so (was
    numpy's 'cannot reshape array'), in every shared image loader."""
    full = tmp_path / "full.fits"
    fits.PrimaryHDU(np.random.default_rng(3).normal(size=(64, 64))).writeto(full)
    cut = tmp_path / "cut.fits"
    cut.write_bytes(full.read_bytes()[:2880 + 3600])
    with pytest.warns(Warning, match="truncated"):
        with pytest.raises(InputFileError, match="cut.fits: truncated"):
            read_image(cut)
    with pytest.warns(Warning, match="truncated"):
        with pytest.raises(InputFileError, match="cut.fits: truncated"):
            to_electrons(str(cut), gain=1.0)
    (tmp_path / "empty.fits").write_bytes(b"")
    with pytest.raises(InputFileError, match="empty.fits: not a FITS file: the file is empty"):
        read_image(tmp_path / "empty.fits")
    with pytest.raises(FileNotFoundError, match="nope.fits"):
        read_image(tmp_path / "nope.fits")



def test_gain_as_quantity():
    assert gain_value(2.0 * u.electron / u.adu) == 2.0
    assert gain_value(None) is None
    with pytest.raises(ValueError, match="not in electron/adu"):
        gain_value(2.0 * u.m)
    with pytest.raises(ValueError, match="not a number"):
        gain_value("abc")


def _flats(directory, header):
    """Five pairs of Poisson flats (64 x 64 px, 2000 to 40000 e, gain 1.5 e/ADU)."""
    rng = np.random.default_rng(17)
    paths = []
    for k, level in enumerate((2e3, 6e3, 1.2e4, 2.4e4, 4e4)):
        for half in "ab":
            hdr = fits.Header(header)
            hdr["EXPTIME"] = level / 2e3  # proportional to the level (issue 43 item 1)
            adu = rng.poisson(level, (64, 64)) / 1.5
            paths.append(_write(directory / f"flat_{k}{half}.fits", adu, **hdr))
    return paths


@pytest.mark.parametrize("header, ptc_note, correct", [
    ({}, "no BUNIT and no gain: ADU with an unknown gain, as raw images are",
     "the image states no unit"),
    ({"GAIN": 1.5}, "no BUNIT: ADU, as the GAIN keyword 1.5 e/ADU says", 1.5),
    ({"BUNIT": "electron", "GAIN": 1.5}, "BUNIT electron: electrons", 1.0),
])
def test_ptc_and_correct_read_a_file_alike(tmp_path, capsys, header, ptc_note, correct):
    """Consistency across entry points: ``bfdrift ptc`` (and ``calibrate``, which
    reads flats with the same reader) and ``bfdrift correct`` decide the same
    unit for the same flat: ADU with an unknown gain (ptc measures it, correct
    refuses), ADU with its GAIN, or electrons."""
    from lsst_bfdrift.cli.main import main
    from lsst_bfdrift.ptc.inputs import read_calibration_input

    paths = _flats(tmp_path, header)
    data = read_calibration_input(paths, max_lag=2)
    assert ptc_note in data.notes
    assert main(["ptc", *paths, "--json"]) == 0
    assert ptc_note in json.loads(capsys.readouterr().out)["notes"]
    code = main(["correct", paths[0], str(tmp_path / "out.fits"), "--quiet", "--no-geometry"])
    err = capsys.readouterr().err
    if isinstance(correct, str):
        assert code != 0 and correct in err
    else:
        assert code == 0
        with fits.open(tmp_path / "out.fits") as h:
            assert h[0].header["BFGAIN"] == correct
