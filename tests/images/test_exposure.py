"""Tests of lsst_bfdrift.images.exposure and of exposure files through the Task and the CLI.

Files are written with astropy in the LSST Exposure layout (as lsst.afw writes
it: empty primary, IMAGE, MASK with MP_ cards, VARIANCE, archive HDUs), as
CCDData.write writes them, and as plain images; they are read back and
compared with what was written (round trips, and conservation of flux and of
every HDU and header card: checks against the input itself, not against the
package's model).
"""

import numpy as np
import pytest
from astropy import units as u
from astropy.io import fits
from astropy.nddata import CCDData
from astropy.wcs import WCS
from numpy.testing import assert_allclose, assert_array_equal

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.utils.errors import InputError, InputFileError
from lsst_bfdrift.images.exposure import (MaskedExposure, add_mask_plane, plane_mask,
                                          read_exposure, write_exposure)

SHAPE = (60, 64)
PLANES = {"BAD": 0, "SAT": 1, "INTRP": 2, "CR": 3, "EDGE": 4, "DETECTED": 5, "SUSPECT": 7,
          "NO_DATA": 8}


def _image(seed=1, peak=5e5):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    img = rng.poisson(600.0, SHAPE).astype(np.float32)
    img += (peak * np.exp(-((yy - 30.2)**2 + (xx - 31.7)**2) / (2 * 1.5**2))).astype(np.float32)
    return img


#: A header that says the image is in electrons (the unit rule).
ELECTRONS = fits.Header({"BUNIT": "electron"})


def _lsst_file(path, img=None, *, mask=None, variance=True, bunit="electron", extra=True):
    img = _image() if img is None else img
    if mask is None:
        mask = np.zeros(SHAPE, np.int32)
        mask[7, :] |= 1 << PLANES["BAD"]
        mask[img > 3000] |= 1 << PLANES["DETECTED"]
    mh = fits.Header()
    for name, bit in PLANES.items():
        mh[f"MP_{name}" if len(name) <= 5 else f"HIERARCH MP_{name}"] = bit
    ih = fits.Header({"EXTTYPE": "IMAGE", "INHERIT": True})
    if bunit is not None:
        ih["BUNIT"] = bunit
    hdus = [fits.PrimaryHDU(header=fits.Header({"OBSID": "x1", "GAIN": 1.5})),
            fits.ImageHDU(img, header=ih, name="IMAGE"),
            fits.ImageHDU(mask.astype(np.int32), header=mh, name="MASK")]
    if variance:
        hdus.append(fits.ImageHDU((img + 20.0).astype(np.float32), name="VARIANCE"))
    if extra:
        hdus.append(fits.BinTableHDU.from_columns(
            [fits.Column(name="id", format="J", array=[3, 4])], name="ARCHIVE_INDEX"))
    fits.HDUList(hdus).writeto(path)
    return str(path)


def test_lsst_layout_round_trip(tmp_path):
    path = _lsst_file(tmp_path / "in.fits")
    exp = read_exposure(path)
    assert exp.layout == "lsst" and exp.mask_planes == PLANES
    assert exp.header["BUNIT"] == "electron" and exp.header_value("OBSID") == "x1"
    write_exposure(tmp_path / "out.fits", exp)
    with fits.open(path) as a, fits.open(tmp_path / "out.fits") as b:
        assert [h.name for h in a] == [h.name for h in b]
        for ha, hb in zip(a, b):
            if ha.data is not None and ha.is_image:
                assert_array_equal(ha.data, hb.data)
                assert ha.data.dtype == hb.data.dtype
            for key in ha.header:
                assert key in hb.header and (key in ("CHECKSUM", "DATASUM") or
                                             hb.header[key] == ha.header[key]), key
        assert_array_equal(b["ARCHIVE_INDEX"].data["id"], [3, 4])


def test_ccddata_file_round_trip(tmp_path):
    img = _image().astype(np.float64)
    mask = np.zeros(SHAPE, bool)
    mask[3, 4] = True
    from astropy.nddata import StdDevUncertainty
    CCDData(img, unit="electron", mask=mask, uncertainty=StdDevUncertainty(np.sqrt(img)),
            meta={"OBJECT": "star"}).write(tmp_path / "ccd.fits")
    exp = read_exposure(tmp_path / "ccd.fits")
    assert exp.layout == "ccddata" and exp.mask_planes == {"BAD": 0}
    assert_allclose(exp.variance, img)  # the standard deviations, squared
    write_exposure(tmp_path / "back.fits", exp)
    back = CCDData.read(tmp_path / "back.fits")
    assert_allclose(back.data, img)
    assert_array_equal(back.mask, mask)
    assert_allclose(back.uncertainty.array, np.sqrt(img))
    assert back.meta["OBJECT"] == "star"


def test_compressed_input_gives_compressed_output(tmp_path):
    img = _image()
    fits.HDUList([fits.PrimaryHDU(), fits.CompImageHDU(img, compression_type="RICE_1",
                                                       quantize_level=0.0, header=ELECTRONS)]
                 ).writeto(tmp_path / "in.fits.fz")
    code = main(["correct", str(tmp_path / "in.fits.fz"), str(tmp_path / "out.fits.fz"),
                 "--quiet"])
    assert code == 0
    fits.PrimaryHDU(img, header=ELECTRONS).writeto(tmp_path / "plain.fits")
    assert main(["correct", str(tmp_path / "plain.fits"), str(tmp_path / "plain_out.fits"),
                 "--quiet"]) == 0
    with fits.open(tmp_path / "out.fits.fz") as h, fits.open(tmp_path / "in.fits.fz") as i, \
            fits.open(tmp_path / "plain_out.fits") as ref:
        assert isinstance(h[1], fits.CompImageHDU)
        assert (h[1].compression_type, h[1].quantize_level) == \
            (i[1].compression_type, i[1].quantize_level)
        # the corrected image, within the (noise-scaled) quantisation of the compression
        assert np.abs(h[1].data - ref[0].data).max() < 0.1 * np.sqrt(img.min())
        assert "FLUX_MOVED" in h


def test_refusals(tmp_path):
    # a MASK of another shape
    p = tmp_path / "shape.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(_image(), name="IMAGE"),
                  fits.ImageHDU(np.zeros((5, 5), np.int32), name="MASK")]).writeto(p)
    with pytest.raises(InputError, match=r"shape.fits: MASK HDU shape \(5, 5\) does not match"):
        read_exposure(p)
    # a float MASK
    p = tmp_path / "float.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(_image(), name="IMAGE"),
                  fits.ImageHDU(np.zeros(SHAPE, np.float32), name="MASK")]).writeto(p)
    with pytest.raises(InputError, match="float32 values; a mask is integer bit planes"):
        read_exposure(p)
    # a raw file: one image HDU per amplifier
    p = tmp_path / "raw.fits"
    fits.HDUList([fits.PrimaryHDU()] + [fits.ImageHDU(np.full((20, 10), 15000.0),
                                                      name=f"Segment{k:02d}")
                                        for k in range(16)]).writeto(p)
    with pytest.raises(InputError, match=r"raw.fits: 16 image HDUs .*SEGMENT00.*assemble"):
        read_exposure(p)
    code = main(["correct", str(p), str(tmp_path / "o.fits"), "--quiet"])
    assert code == 1 and not (tmp_path / "o.fits").exists()  # the file failed, reported
    # no image at all
    p = tmp_path / "table.fits"
    fits.HDUList([fits.PrimaryHDU(), fits.BinTableHDU.from_columns(
        [fits.Column(name="a", format="J", array=[1])])]).writeto(p)
    with pytest.raises(InputFileError, match="no 2-d image HDU"):
        read_exposure(p)


def test_plane_mask_uses_named_planes_only():
    m = np.array([[0, 1 << 5, 1 << 1, (1 << 5) | (1 << 0)]], np.int32)
    assert_array_equal(plane_mask(m, PLANES, ["SAT", "BAD", "UNKNOWN"]),
                       [[False, False, True, True]])
    assert_array_equal(plane_mask(m, PLANES, []), [[False] * 4])
    exp = MaskedExposure(image=np.zeros((1, 4)), mask=m, mask_planes=dict(PLANES))
    assert add_mask_plane(exp, "BF") == 6  # first free bit
    assert add_mask_plane(exp, "BF") == 6 and exp.mask_planes["BF"] == 6


def test_lsst_file_through_bfdrift_correct(tmp_path):
    """Issue 16's case: IMAGE/MASK/VARIANCE through `bfdrift correct` comes back in the
    same layout, masked pixels untouched, DETECTED not blocking, variance present and a BF
    plane declared; flux is conserved."""
    img = _image()
    mask = np.zeros(SHAPE, np.int32)
    mask[7, :] |= 1 << PLANES["BAD"]
    mask[30, 31] |= 1 << PLANES["SAT"]
    mask[img > 3000] |= 1 << PLANES["DETECTED"]
    src = _lsst_file(tmp_path / "in.fits", img, mask=mask)
    code = main(["correct", src, str(tmp_path / "out.fits"), "--quiet"])
    assert code == 0
    with fits.open(src) as a, fits.open(tmp_path / "out.fits") as b:
        assert [h.name for h in b][:len(a)] == [h.name for h in a]
        assert [h.name for h in b][len(a):] == ["FLUX_MOVED", "BFFLAGS", "AREA", "CENTROID_X",
                                                "CENTROID_Y", "E1", "E2"]  # geometry on
        assert b["AREA"].header["BUNIT"] == "pixel2"
        # the area is written in float64 (1 + a signal below float32's 6e-8 at 1)
        assert b["AREA"].data.dtype.itemsize == 8 and b["E1"].data.dtype.itemsize == 4
        task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig())
        area = task.run(read_exposure(src)).area
        assert_array_equal(b["AREA"].data, area)
        bits = {k[3:]: v for k, v in b["MASK"].header.items() if k.startswith("MP_")}
        assert bits["BF"] == 6 and {k: bits[k] for k in PLANES} == PLANES
        out_img, out_mask = b["IMAGE"].data, b["MASK"].data
        assert_array_equal(out_mask & ~np.int32(1 << 6), mask)
        blocked = (mask & 0b11) != 0
        assert_array_equal(out_img[blocked], img[blocked])
        det = ((mask >> 5) & 1).astype(bool) & ~blocked
        assert np.abs(out_img[det] - img[det]).max() > 10.0  # DETECTED pixels corrected
        # afw reads the metadata of an INHERIT exposure from the primary header
        assert b[0].header["HIERARCH LSST ISR BF APPLIED"] is True
        assert b[0].header["BFTSUM"] and b[0].header["BFGAIN"] == 1.0
        assert "BFDRIFT" not in b["IMAGE"].header
        assert_array_equal(b["VARIANCE"].data, a["VARIANCE"].data)
        assert abs(float(out_img.astype(float).sum()) - float(img.astype(float).sum())) < 1.0
        assert b["FLUX_MOVED"].header["BUNIT"] == "electron"
        flagged = (out_mask >> 6) & 1
        assert_array_equal(flagged.astype(bool), b["BFFLAGS"].data != 0)


def test_masked_hot_pixel_does_not_stop_the_run(tmp_path):
    """A pixel above the model's range, masked BAD, is excluded from the range check."""
    img = _image()
    img[40, 10] = 5e12
    mask = np.zeros(SHAPE, np.int32)
    mask[40, 10] = 1 << PLANES["BAD"]
    exp = read_exposure(_lsst_file(tmp_path / "hot.fits", img, mask=mask))
    res = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False)).run(exp)
    assert res.exposure.image[40, 10] == img[40, 10] and res.converged
    with pytest.raises(InputError, match=r"pixel values up to 5e\+12 e.*mask them"):
        BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False)).run(
            img.astype(float))


def test_missing_variance_and_missing_bunit(tmp_path):
    """No VARIANCE: nothing is invented; no BUNIT: ADU with the GAIN inherited from
    the primary header (the unit rule: a gain means ADU), as with BUNIT = 'adu'; no
    BUNIT and no GAIN: refused, naming the two ways to state the unit."""
    exp = read_exposure(_lsst_file(tmp_path / "a.fits", _image(peak=2e5), variance=False,
                                   bunit=None))
    assert exp.variance is None and exp.unit() == ""
    res = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False)).run(exp)
    assert res.exposure.variance is None and res.header["BFGAIN"] == 1.5
    del exp.primary_header["GAIN"]
    with pytest.raises(InputError, match="a.fits: the image states no unit .* BUNIT = "
                                         "'electron'"):
        BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False)).run(exp)
    exp = read_exposure(_lsst_file(tmp_path / "adu.fits", _image(peak=2e5), bunit="adu"))
    res = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False)).run(exp)
    assert res.header["BFGAIN"] == 1.5  # GAIN from the primary header (INHERIT)


def test_ccddata_wcs_and_meta_survive_the_task():
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [150.0, 2.0]
    ccd = CCDData(_image().astype(float), unit=u.electron, wcs=w, meta={"OBJECT": "f1"})
    out = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False)).run(ccd).exposure
    assert out.wcs is not None and list(out.wcs.wcs.crval) == [150.0, 2.0]
    assert out.meta["OBJECT"] == "f1" and out.unit == u.electron


def test_ccddata_file_mask_stays_boolean_and_planes_from_the_cli(tmp_path, capsys):
    """A CCDData file keeps a boolean-meaning MASK (the correction's flags go to BFFLAGS,
    not into the mask its readers apply); --blocking-planes names the blocking planes."""
    img = _image().astype(np.float64)
    mask = np.zeros(SHAPE, bool)
    mask[3, 4] = True
    CCDData(img, unit="electron", mask=mask).write(tmp_path / "ccd.fits")
    assert main(["correct", str(tmp_path / "ccd.fits"), str(tmp_path / "out.fits"),
                 "--no-geometry"]) == 0
    text = capsys.readouterr().out
    assert "moved" in text and "e between pixels" in text and "converged" in text
    back = CCDData.read(tmp_path / "out.fits")
    assert_array_equal(back.mask, mask)
    # DETECTED made blocking on purpose: the star is then left as recorded
    img2 = _image()
    m2 = np.zeros(SHAPE, np.int32)
    m2[img2 > 3000] = 1 << PLANES["DETECTED"]
    src = _lsst_file(tmp_path / "lsst.fits", img2, mask=m2)
    assert main(["correct", src, str(tmp_path / "o2.fits"), "--no-geometry", "--quiet",
                 "--blocking-planes", "DETECTED,BAD"]) == 0
    with fits.open(tmp_path / "o2.fits") as h:
        det = (m2 >> PLANES["DETECTED"]) & 1 == 1
        assert_array_equal(h["IMAGE"].data[det], img2[det])
def _headers(path):
    with fits.open(path) as h:
        return [hdu.header.copy() for hdu in h]


def test_mask_plane_docs_and_the_bf_bit(tmp_path):
    """MPD_ descriptions (newer afw) are read and written back; the BF plane takes the
    lowest bit that is neither declared nor set in the data, and is described. Checked
    against the cards and bits written here (consistency with the input)."""
    mask = np.zeros(SHAPE, np.int32)
    mask[2, 3] = 1 << 6  # bit 6 is set but declared by no MP_ card
    path = _lsst_file(tmp_path / "in.fits", mask=mask)
    with fits.open(path, mode="update") as h:
        h["MASK"].header["MPD_BAD"] = "known bad pixel"
    exp = read_exposure(path)
    assert exp.mask_plane_docs == {"BAD": "known bad pixel"}
    assert add_mask_plane(exp, "BF", doc="bf doc") == 9  # 6 is taken by the data, 7, 8 declared
    write_exposure(tmp_path / "out.fits", exp)
    mh = _headers(tmp_path / "out.fits")[2]  # MASK
    assert mh["MPD_BAD"] == "known bad pixel" and mh["MP_BF"] == 9 and mh["MPD_BF"] == "bf doc"
    full = MaskedExposure(image=np.zeros((2, 2)), mask=np.zeros((2, 2), np.int32),
                          mask_planes={f"P{b}": b for b in range(31)})
    with pytest.raises(InputError, match="no free bit in the mask for plane 'BF'"):
        add_mask_plane(full, "BF")


def test_integer_image_is_written_as_float32(tmp_path):
    """An int16 image (BZERO-scaled, as cameras write them) comes back as float32 and
    the corrected flux is kept to float32 precision: writing it back as integers
    truncated 0.4 e per pixel. Independent reference: the input's own sum."""
    img = np.clip(_image(peak=2e4), 0, 32000).astype(np.int16)
    fits.PrimaryHDU(img.astype(np.uint16), header=ELECTRONS).writeto(
        tmp_path / "u16.fits")  # BZERO = 32768
    assert main(["correct", str(tmp_path / "u16.fits"), str(tmp_path / "out.fits"),
                 "--quiet", "--no-geometry"]) == 0
    with fits.open(tmp_path / "out.fits") as h:
        out = h[0].data
        assert out.dtype.kind == "f" and "BZERO" not in h[0].header
        assert np.abs(h["FLUX_MOVED"].data).max() > 1.0  # the star was corrected
    assert abs(float(out.astype(float).sum()) - float(img.astype(float).sum())) < 1.0


def test_lsst_fz_round_trip(tmp_path):
    """A compressed LSST Exposure (.fits.fz: IMAGE, MASK, VARIANCE as compressed image
    HDUs, as afw writes them) comes back compressed with the same settings, mask and
    variance losslessly kept, the BF plane declared and flux conserved (consistency
    with the input)."""
    img = _image()
    mask = np.zeros(SHAPE, np.int32)
    mask[7, :] = 1 << PLANES["BAD"]
    mh = fits.Header({"MP_BAD": 0, "MP_SAT": 1, "HIERARCH MP_DETECTED": 5})
    ih = fits.Header({"EXTTYPE": "IMAGE", "INHERIT": True, "BUNIT": "electron"})
    fits.HDUList([fits.PrimaryHDU(),
                  fits.CompImageHDU(img, header=ih, name="IMAGE", compression_type="GZIP_2",
                                    quantize_level=0.0),
                  fits.CompImageHDU(mask, header=mh, name="MASK", compression_type="RICE_1"),
                  fits.CompImageHDU(img + 20, name="VARIANCE", compression_type="GZIP_2",
                                    quantize_level=0.0)]).writeto(tmp_path / "in.fits.fz")
    assert main(["correct", str(tmp_path / "in.fits.fz"), str(tmp_path / "out.fits.fz"),
                 "--quiet", "--no-geometry"]) == 0
    with fits.open(tmp_path / "in.fits.fz") as a, fits.open(tmp_path / "out.fits.fz") as b:
        for name in ("IMAGE", "MASK", "VARIANCE"):
            assert isinstance(b[name], fits.CompImageHDU), name
            assert b[name].compression_type == a[name].compression_type
        bit = b["MASK"].header["MP_BF"]
        assert_array_equal(b["MASK"].data & ~np.int32(1 << bit), mask)
        assert_array_equal(b["VARIANCE"].data, a["VARIANCE"].data)
        assert_array_equal(b["IMAGE"].data[7], img[7])  # the BAD row untouched
        assert abs(float(b["IMAGE"].data.sum(dtype=float)) - float(img.sum(dtype=float))) < 1.0
        assert b[0].header["BFDRIFT"] is True
    exp = read_exposure(tmp_path / "out.fits.fz")  # bfdrift's products are not more images
    assert exp.layout == "lsst" and "BF" in exp.mask_planes


def test_unknown_planes_kept_and_never_blocking(tmp_path):
    """A plane of a name the package does not know (here over the star) is kept with its
    bit and does not block unless named in blocking_mask_planes (consistency: the
    pixels it covers change only when it is configured to block)."""
    img = _image()
    mask = np.zeros(SHAPE, np.int32)
    mask[img > 3000] = 1 << 12
    path = _lsst_file(tmp_path / "in.fits", img, mask=mask)
    with fits.open(path, mode="update") as h:
        h["MASK"].header["HIERARCH MP_MYSTAR"] = 12
    exp = read_exposure(path)
    star = img > 3000
    cfg = BrighterFatterDriftConfig(compute_geometry=False)
    res = BrighterFatterDriftTask(config=cfg).run(exp)
    assert res.exposure.mask_planes["MYSTAR"] == 12 and not res.warnings
    assert np.abs(res.exposure.image[star] - img[star]).max() > 10.0
    cfg = BrighterFatterDriftConfig(compute_geometry=False,
                                    blocking_mask_planes=["BAD", "MYSTAR"])
    res = BrighterFatterDriftTask(config=cfg).run(exp)
    assert_array_equal(res.exposure.image[star], img[star])


def test_undeclared_mask_bits_warn_and_strict_refuses(tmp_path, capsys):
    """Bits set in MASK without an MP_ card do not block (their meaning is unknown) and
    are named in a warning, printed by `bfdrift correct`; --strict refuses the file
    (consistency checks of the messages)."""
    mask = np.zeros(SHAPE, np.int32)
    mask[3:5, 3:5] = 1 << 20
    src = _lsst_file(tmp_path / "in.fits", mask=mask)
    res = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False)).run(read_exposure(src))
    assert len(res.warnings) == 1 and "mask bits [20] are set in 4 pixels" in res.warnings[0]
    assert res.header["BFWARN"] == 1
    assert main(["correct", src, str(tmp_path / "out.fits"), "--quiet"]) == 0
    out, err = capsys.readouterr()
    assert "1 input warning" in out and "warning: mask bits [20]" in err
    assert main(["correct", src, str(tmp_path / "strict.fits"), "--quiet", "--strict"]) == 1
    out, err = capsys.readouterr()
    assert "on_input_warning='raise'" in err and not (tmp_path / "strict.fits").exists()


def test_bias_pedestal_is_a_warning_in_the_cli(tmp_path, capsys):
    """Issue 19 row 1: a raw-looking amplifier (15000 ADU flat pedestal, scatter far below
    Poisson) is corrected with a printed warning, listed in --json; --strict refuses it
    (a warning by default: noiseless simulations have such pedestals too)."""
    rng = np.random.default_rng(4)
    fits.PrimaryHDU((15000 + rng.normal(0, 5, SHAPE)).astype(np.float32),
                    header=ELECTRONS).writeto(tmp_path / "bias.fits")  # says electrons
    assert main(["correct", str(tmp_path / "bias.fits"), str(tmp_path / "o.fits"), "--quiet",
                 "--json", "--no-geometry"]) == 0
    out, err = capsys.readouterr()
    import json
    files = json.loads(out)["files"]
    assert "bias pedestal" in files[0]["warnings"][0] and "bias pedestal" in err
    assert main(["correct", str(tmp_path / "bias.fits"), str(tmp_path / "s.fits"), "--quiet",
                 "--strict"]) == 1
    assert "bias pedestal" in capsys.readouterr().err and not (tmp_path / "s.fits").exists()


@pytest.mark.parametrize("where", ["primary", "image"])
def test_already_corrected_input_is_refused(tmp_path, where):
    """An image whose metadata says the BF correction was applied (ip_isr's LSST ISR BF
    APPLIED, in the primary header of an INHERIT exposure or the image header) is
    refused: a second correction would double it. bfdrift's own outputs too."""
    path = _lsst_file(tmp_path / "in.fits", variance=False)
    with fits.open(path, mode="update") as h:
        hdr = h[0].header if where == "primary" else h["IMAGE"].header
        hdr["HIERARCH LSST ISR BF APPLIED"] = True
        hdr["HIERARCH LSST ISR BF CORR METHOD"] = "COULTON18"
    task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False))
    with pytest.raises(InputError, match=r"already corrected .*LSST ISR BF APPLIED = True, "
                                         r"method COULTON18.*doBrighterFatter=False"):
        task.run(read_exposure(path))
    out = task.run(_image().astype(float) / 2)
    ccd = CCDData(_image().astype(float), unit="electron")
    ccd_out = task.run(ccd).exposure
    with pytest.raises(InputError, match="already corrected .*method LSST_BFDRIFT"):
        task.run(ccd_out)
    assert out.converged


def test_metadata_goes_where_afw_reads_it(tmp_path):
    """afw reads an INHERIT exposure's metadata from the primary header, else from the
    image header (ExposureFitsReader); the BF keys follow that rule, and the BFFLAGS
    extension declares its bits as mask planes with full descriptions."""
    src = _lsst_file(tmp_path / "inherit.fits")
    assert main(["correct", src, str(tmp_path / "a.fits"), "--quiet", "--no-geometry"]) == 0
    h = _headers(tmp_path / "a.fits")
    assert h[0]["LSST ISR BF APPLIED"] is True and h[0]["BFVERS"]
    assert "BFMETHOD" not in h[1] and h[1]["BUNIT"] == "electron"
    flags = h[-1]
    assert flags["EXTNAME"] == "BFFLAGS" and flags["MP_BLOCKED"] == 0 and flags["MP_EDGE"] == 1
    assert flags["BFDESC"].endswith("(aggressors missing)") and flags["MPD_EDGE"]
    assert h[2]["MPD_BF"].startswith("BF correction incomplete")
    img = _image()
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(img, name="IMAGE", header=ELECTRONS)]).writeto(
        tmp_path / "old.fits")  # no INHERIT: old-style, metadata in the image HDU
    assert main(["correct", str(tmp_path / "old.fits"), str(tmp_path / "b.fits"), "--quiet",
                 "--no-geometry"]) == 0
    h = _headers(tmp_path / "b.fits")
    assert h[1]["LSST ISR BF APPLIED"] is True and "BFDRIFT" not in h[0]


def test_lsst_isr_units_and_gain_from_the_primary(tmp_path):
    """Units from `LSST ISR UNITS` (where ip_isr records them) when BUNIT is missing, GAIN
    from the primary header (INHERIT): an ADU image is converted with it. Reference:
    the same image in electrons gives the same flux moved (in e)."""
    img = _image(peak=2e5)
    gain = 1.5
    e_path = _lsst_file(tmp_path / "e.fits", img, variance=False)
    adu_path = _lsst_file(tmp_path / "adu.fits", (img / gain).astype(np.float32), bunit=None,
                          variance=False)
    with fits.open(adu_path, mode="update") as h:
        h[0].header["HIERARCH LSST ISR UNITS"] = "adu"
    task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False))
    ref = task.run(read_exposure(e_path))
    res = task.run(read_exposure(adu_path))
    assert res.header["BFGAIN"] == gain
    assert_allclose(res.flux_moved, ref.flux_moved, rtol=1e-3,
                    atol=1e-3 * np.abs(ref.flux_moved).max())


def test_two_paths_with_overwrite_keep_an_input(tmp_path, capsys):
    """Issue 19 row 9: `correct a.fits b.fits --overwrite` with b.fits an input (forgot
    --out-dir) is refused and b.fits kept; an output bfdrift wrote is replaced; three
    paths need --out-dir."""
    a = _lsst_file(tmp_path / "a.fits")
    b = _lsst_file(tmp_path / "b.fits")
    before = (tmp_path / "b.fits").read_bytes()
    assert main(["correct", a, b, "--overwrite", "--quiet"]) == 3
    assert "not written by bfdrift" in capsys.readouterr().err
    assert (tmp_path / "b.fits").read_bytes() == before
    out = str(tmp_path / "out.fits")
    assert main(["correct", a, out, "--quiet", "--no-geometry"]) == 0
    assert main(["correct", a, out, "--quiet", "--no-geometry", "--overwrite"]) == 0
    assert main(["correct", a, b, out, "--quiet"]) == 2
    assert "3 paths without --out-dir" in capsys.readouterr().err


def test_afw_shaped_exposure_gets_every_key_and_a_clone():
    """An object of afw's Exposure shape: a clone is returned (input untouched) with the BF
    plane added through addMaskPlane, and the package's keys and LSST's in its metadata;
    masked pixels (SAT) untouched, DETECTED not blocking (consistency checks)."""
    from tests.pipeline._afw_like import FakeExposure

    img = _image()
    exp = FakeExposure(img, planes={"BAD": 0, "SAT": 1, "DETECTED": 5})
    exp.mask.array[30, 31] = 1 << 1
    exp.mask.array[img > 3000] |= 1 << 5
    before = exp.image.array.copy()
    res = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False)).run(
        exp)
    out = res.exposure
    assert out is not exp
    assert_array_equal(exp.image.array, before)
    md = out.getMetadata()
    assert md["LSST ISR BF APPLIED"] is True and md["BFMETHOD"] == "drift" and md["BFTSUM"]
    bit = out.mask.getMaskPlaneDict()["BF"]
    assert out.mask.array[30, 31] & (1 << bit) and out.image.array[30, 31] == img[30, 31]
    det = (img > 3000) & (exp.mask.array & 0b11 == 0)
    assert np.abs(out.image.array[det] - img[det]).max() > 10.0
