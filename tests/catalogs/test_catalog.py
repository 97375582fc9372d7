"""Tests of lsst_bfdrift.catalogs.catalog: detection, flags, adaptive moments, bad input."""

import galsim
import numpy as np
import pytest
from astropy.io import fits
from astropy.utils.exceptions import AstropyUserWarning
from numpy.testing import assert_allclose

from lsst_bfdrift.catalogs.catalog import (FLAG_BLENDED, FLAG_EDGE, FLAG_MASKED, FLAG_NOT_STAR,
                                           FLAG_SATURATED, measure_stars)

SKY = 500.0


def _gauss_field(stars, shape=(160, 160), seed=3, noise=True):
    """GalSim Gaussian stars (x, y, flux, sigma, e1, e2) drawn by FFT on a noisy sky."""
    img = galsim.ImageD(shape[1], shape[0], xmin=0, ymin=0)
    for x, y, f, s, e1, e2 in stars:
        prof = galsim.Gaussian(sigma=s, flux=f).shear(e1=e1, e2=e2)
        prof.drawImage(img, scale=1.0, method="no_pixel", add_to_image=True,
                       center=galsim.PositionD(x, y))
    arr = img.array + SKY
    if noise:
        rng = np.random.default_rng(seed)
        arr = arr + rng.normal(0.0, np.sqrt(SKY), shape)
    return arr


def _nearest(cat, x, y):
    d = np.hypot(cat["x"].value - x, cat["y"].value - y)
    return int(np.argmin(d)), float(d.min())


def test_moments_match_the_drawn_gaussian():
    # point-sampled elliptical Gaussians: adaptive moments are exactly the covariance
    # (bright, so that the noise on each moment is < 1e-3 of T)
    stars = [(50.3, 60.7, 4e6, 2.0, 0.1, -0.05), (110.2, 100.4, 2e6, 1.6, -0.08, 0.06)]
    cat = measure_stars(_gauss_field(stars))
    assert len(cat) == 2 and np.all(cat["use"])
    for x, y, f, s, e1, e2 in stars:
        k, d = _nearest(cat, x, y)
        assert d < 0.02
        shear = galsim.Shear(e1=e1, e2=e2)
        m = shear.getMatrix()
        cov = s ** 2 * m @ m.T
        assert_allclose([cat["ixx"][k].value, cat["iyy"][k].value, cat["ixy"][k].value],
                        [cov[0, 0], cov[1, 1], cov[0, 1]], rtol=3e-3, atol=2e-3)
        assert_allclose([cat["e1"][k], cat["e2"][k]], [e1, e2], atol=1e-3)
        assert_allclose(cat["flux"][k].value, f, rtol=0.02)
        assert cat["snr"][k] > 1000
    assert cat["flux"].unit == "electron" and cat["T"].unit == "pix2"


def test_flags_saturation_blending_edges_masks():
    stars = [(40.0, 40.0, 3e5, 1.8, 0, 0),     # saturated (level set below its peak)
             (100.0, 40.0, 5e4, 1.8, 0, 0), (106.0, 42.0, 5e4, 1.8, 0, 0),  # blended pair
             (3.0, 120.0, 5e4, 1.8, 0, 0),     # at the edge
             (120.0, 120.0, 5e4, 1.8, 0, 0),   # masked pixel in the aperture
             (60.0, 110.0, 5e4, 1.8, 0, 0),    # clean
             (20.0, 80.0, 5e4, 1.8, 0, 0), (140.0, 80.0, 5e4, 1.8, 0, 0),
             (80.0, 140.0, 5e4, 1.8, 0, 0), (140.0, 145.0, 5e4, 1.8, 0, 0),
             (75.0, 80.0, 3e5, 4.0, 0, 0)]     # galaxy-like: twice the stars' size
    arr = _gauss_field(stars)
    arr[122, 123] = np.nan
    peak_sat = 3e5 / (2 * np.pi * 1.8 ** 2) + SKY
    cat = measure_stars(arr, saturation=0.5 * peak_sat)
    k, _ = _nearest(cat, 40, 40)
    assert cat["flags"][k] & FLAG_SATURATED and cat["flag_saturated"][k] and not cat["use"][k]
    k, d = _nearest(cat, 103.0, 41.0)  # one segment with two peaks: flagged, not split
    assert d < 2 and cat["flags"][k] & FLAG_BLENDED and not cat["use"][k]
    k, _ = _nearest(cat, 3, 120)
    assert cat["flags"][k] & FLAG_EDGE
    k, _ = _nearest(cat, 120, 120)
    assert cat["flags"][k] & FLAG_MASKED
    k, _ = _nearest(cat, 60, 110)
    assert cat["flags"][k] == 0 and cat["use"][k]
    k, _ = _nearest(cat, 75, 80)
    assert cat["flags"][k] & FLAG_NOT_STAR and cat["flag_not_star"][k]
    assert cat["T"][k].value > 3 * np.median(cat["T"].value[cat["use"]])


def test_a_clipped_image_gives_its_saturation_level():
    """An image clipped at a level (a flat top on its brightest stars) and no
    saturation given: that level is taken, with a warning, and only the
    clipped stars are flagged; the same image unclipped infers nothing (and
    integer pixels do not fake a plateau)."""
    stars = [(40.0, 40.0, 3e5, 1.8, 0, 0), (120.0, 40.0, 2e5, 1.8, 0, 0),
             (60.0, 110.0, 5e4, 1.8, 0, 0), (120.0, 120.0, 5e4, 1.8, 0, 0)]
    arr = _gauss_field(stars)
    level = 0.5 * 2e5 / (2 * np.pi * 1.8 ** 2) + SKY  # below the two bright peaks
    clipped = np.minimum(arr, level)
    before = clipped.copy()
    with pytest.warns(AstropyUserWarning, match=r"pixels share the image's largest value"):
        cat = measure_stars(clipped)
    np.testing.assert_array_equal(clipped, before)  # the input is not modified
    assert cat.meta["saturation"] == pytest.approx(level)
    for x, y, sat in ((40, 40, True), (120, 40, True), (60, 110, False), (120, 120, False)):
        k, _ = _nearest(cat, x, y)
        assert bool(cat["flags"][k] & FLAG_SATURATED) == sat
    for img in (arr, np.round(arr).astype(np.int32)):
        cat = measure_stars(img)  # warnings are errors here: none is raised
        assert cat.meta["saturation"] is None and not np.any(cat["flags"] & FLAG_SATURATED)


def _lsst_file(path, arr, mask, planes):
    """An LSST Exposure layout (IMAGE, MASK with its MP_ cards, VARIANCE), in e."""
    mh = fits.Header()
    for name, bit in planes.items():
        mh[f"MP_{name}"] = bit
    fits.HDUList([fits.PrimaryHDU(),
                  fits.ImageHDU(arr.astype(np.float32), name="IMAGE",
                                header=fits.Header({"BUNIT": "electron"})),
                  fits.ImageHDU(mask.astype(np.int32), header=mh, name="MASK"),
                  fits.ImageHDU(arr.astype(np.float32), name="VARIANCE")]).writeto(path)
    return str(path)


def test_sat_plane_stars_are_saturated_not_masked(tmp_path):
    """An LSST exposure whose SAT plane covers a star's core (values left as
    ISR's interpolation would: no level is exceeded, no SATURATE keyword):
    that star is flagged saturated and not masked; a BAD pixel in another
    star's aperture flags it masked only. The same flags from an array with
    ``saturated=``, and on a copy measured with the first one's detections."""
    stars = [(40.0, 40.0, 2e5, 1.8, 0, 0), (120.0, 120.0, 5e4, 1.8, 0, 0),
             (60.0, 110.0, 5e4, 1.8, 0, 0), (120.0, 40.0, 5e4, 1.8, 0, 0)]
    arr = _gauss_field(stars)
    planes = {"BAD": 0, "SAT": 1, "INTRP": 2}
    mask = np.zeros(arr.shape, np.int32)
    mask[39:42, 39:42] |= (1 << 1) | (1 << 2)
    mask[122, 123] |= 1 << 0
    path = _lsst_file(tmp_path / "exp.fits", arr, mask, planes)
    sat = (mask & (1 << 1)) != 0
    bad = (mask & 1) != 0
    from lsst_bfdrift.catalogs.catalog import detect_stars

    det = detect_stars(arr, mask=bad | sat, saturated=sat)
    cats = {"file": measure_stars(path),
            "array": measure_stars(arr, mask=bad | sat, saturated=sat),
            "reused": measure_stars(arr * 1.001, mask=bad | sat, detections=det)}
    for name, cat in cats.items():
        k, _ = _nearest(cat, 40, 40)
        assert cat["flags"][k] & FLAG_SATURATED and not cat["flags"][k] & FLAG_MASKED, name
        k, _ = _nearest(cat, 120, 120)
        assert cat["flags"][k] & FLAG_MASKED and not cat["flags"][k] & FLAG_SATURATED, name
        for x, y in ((60, 110), (120, 40)):
            k, _ = _nearest(cat, x, y)
            assert cat["flags"][k] == 0, name
    # without the plane's meaning the star is only masked
    cat = measure_stars(arr, mask=bad | sat)
    k, _ = _nearest(cat, 40, 40)
    assert cat["flags"][k] & FLAG_MASKED and not cat["flags"][k] & FLAG_SATURATED
    with pytest.raises(ValueError, match=r"saturated shape \(3, 3\) does not match"):
        measure_stars(arr, saturated=np.zeros((3, 3), bool))
    # the plane itself, as to_electrons gives it (None for a plain array)
    from lsst_bfdrift.images.electrons import to_electrons

    image = to_electrons(path)
    assert_allclose(image.data, arr)
    assert image.gain == 1.0
    assert np.array_equal(image.sat_plane, sat) and np.array_equal(image.bad, bad | sat)
    assert to_electrons(arr).sat_plane is None


def test_adu_with_gain_equals_electrons(tmp_path):
    arr = _gauss_field([(80.0, 80.0, 1e5, 2.0, 0.05, 0.0)])
    cat_e = measure_stars(arr)
    path = tmp_path / "adu.fits"
    hdr = fits.Header()
    hdr["BUNIT"] = "ADU"
    hdr["GAIN"] = 2.0
    fits.PrimaryHDU(arr / 2.0, header=hdr).writeto(path)
    cat_adu = measure_stars(str(path))
    assert_allclose(cat_adu["flux"].value, cat_e["flux"].value, rtol=1e-6)
    assert_allclose(cat_adu["T"].value, cat_e["T"].value, rtol=1e-5)
    cat_arr = measure_stars(arr / 2.0, gain=2.0)
    assert_allclose(cat_arr["flux"].value, cat_e["flux"].value, rtol=1e-6)
    plain = tmp_path / "plain.fits"  # no BUNIT: an explicit gain still applies
    fits.PrimaryHDU(arr / 2.0).writeto(plain)
    assert_allclose(measure_stars(str(plain), gain=2.0)["flux"].value, cat_e["flux"].value,
                    rtol=1e-6)
    assert cat_adu.meta["gain"] == 2.0
    before = arr.copy()
    measure_stars(arr)
    assert np.array_equal(arr, before)  # input untouched


def test_bad_images_get_clear_errors(tmp_path):
    rng = np.random.default_rng(5)
    with pytest.raises(ValueError, match="blank"):
        measure_stars(np.full((64, 64), 100.0))
    with pytest.raises(ValueError, match="no usable pixel"):
        measure_stars(np.full((64, 64), np.nan))
    with pytest.raises(ValueError, match="no sources detected"):
        measure_stars(rng.normal(SKY, np.sqrt(SKY), (96, 96)))
    with pytest.raises(ValueError, match="2-d"):
        measure_stars(np.zeros((4, 64, 64)))
    with pytest.raises(ValueError, match="too small"):
        measure_stars(rng.normal(0, 1, (8, 8)))
    with pytest.raises(ValueError, match="gain -1.0 is not positive"):
        measure_stars(rng.normal(0, 1, (64, 64)), gain=-1.0)
    hdr = fits.Header()
    hdr["BUNIT"] = "ADU"
    path = tmp_path / "nogain.fits"
    fits.PrimaryHDU(rng.normal(0, 1, (64, 64)), header=hdr).writeto(path)
    with pytest.raises(ValueError, match="GAIN"):
        measure_stars(str(path))


def test_hsm_moments_of_an_elliptical_gaussian():
    """Independent reference: adaptive moments of a noise-free elliptical Gaussian are
    its own second moments; both size definitions follow (t = Mxx + Myy,
    t_det = 2 sqrt(det M))."""
    from numpy.testing import assert_allclose

    from lsst_bfdrift.catalogs.catalog import hsm_moments
    from lsst_bfdrift.validation.stars import star_moments
    mxx, myy, mxy = 5.0, 3.0, 0.8
    inv = np.linalg.inv([[mxx, mxy], [mxy, myy]])
    yy, xx = np.mgrid[:61, :61] - 30.0
    img = 1e5 * np.exp(-0.5 * (inv[0, 0] * xx**2 + 2 * inv[0, 1] * xx * yy + inv[1, 1] * yy**2))
    m = hsm_moments(img, origin=(0, 0))
    assert_allclose([m["mxx"], m["myy"], m["mxy"]], [mxx, myy, mxy], rtol=2e-3)
    assert_allclose(m["t"], mxx + myy, rtol=2e-3)
    det = mxx * myy - mxy**2
    assert_allclose(m["t_det"], 2 * np.sqrt(det), rtol=2e-3)
    assert_allclose([m["x"], m["y"]], [30.0, 30.0], atol=1e-6)
    # the validation's star measure is the same call (t_det, e1, e2)
    t_det, e1, e2 = star_moments(img + 7.0, 7.0)
    assert_allclose([t_det, e1, e2], [m["t_det"], m["e1"], m["e2"]], rtol=1e-6, atol=1e-9)
    assert hsm_moments(np.zeros((20, 20))) is None
