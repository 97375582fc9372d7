"""Tests of lsst_bfdrift.simulation.chromatic (photon wavelengths for galsim.SiliconSensor)."""

import os

import galsim
import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.simulation.chromatic import (detected_fraction, draw_chromatic_star_pairs,
                                               flat_area_response, galsim_thickness,
                                               sample_wavelengths, star_list)
from lsst_bfdrift.simulation.galsim_twins import accumulate_twins, galsim_acoeffs

SHARE = galsim.meta_data.share_dir
SENSOR = "lsst_itl_50_8"


def _table(*parts, skip=0):
    return np.loadtxt(os.path.join(SHARE, *parts), skiprows=skip)


def _abs_length(wl):
    t = _table("sensors", "abs_length.dat", skip=1)
    return np.interp(wl, t[:, 0], t[:, 1])


@pytest.mark.parametrize("band, sed", [("r", "blackbody"), ("y", "vega"), ("u", "flat")])
def test_sampled_wavelengths_follow_band_times_sed(band, sed):
    """CORRECTNESS: the mean and spread of galsim.WavelengthSampler's wavelengths
    equal the photon-weighted ones of throughput x SED, integrated with numpy from
    GalSim's files directly (the black body from Planck's law, Vega's flambda
    turned into photons by lambda f_lambda)."""
    thr = _table("bandpasses", f"LSST_{band}.dat")
    wl = np.linspace(thr[0, 0], thr[-1, 0], 20001)
    t = np.interp(wl, thr[:, 0], thr[:, 1])
    if sed == "blackbody":
        given = 5000.0
        photons = wl ** -4 / np.expm1(1.438777e7 / (wl * 5000.0))
    elif sed == "vega":
        given = "vega"
        v = _table("SEDs", "vega.txt")
        photons = wl * np.interp(wl, v[:, 0], v[:, 1])
    else:
        given, photons = None, np.ones_like(wl)
    w = t * photons
    mean = np.sum(wl * w) / np.sum(w)
    sd = np.sqrt(np.sum((wl - mean) ** 2 * w) / np.sum(w))
    n = 20000
    lam = sample_wavelengths(n, band, given, seed=11)
    assert lam.shape == (n,)
    assert_allclose(lam.mean(), mean, atol=5 * sd / np.sqrt(n))
    assert_allclose(lam.std(), sd, rtol=0.03)


def test_detected_fraction_matches_siliconsensor():
    """CORRECTNESS: the fraction of 1000 nm photons galsim.SiliconSensor collects
    (it drops those crossing the silicon) is 1 - exp(-t / L), L from GalSim's
    table read here with numpy, t the sensor file's thickness (binomial error)."""
    n, wl = 40000, 1000.0
    t = galsim_thickness(SENSOR)
    assert t == 100.0
    expect = 1.0 - np.exp(-t / _abs_length(wl))
    assert_allclose(detected_fraction(wl, t), expect, rtol=1e-12)
    sens = galsim.SiliconSensor(SENSOR, strength=1e-9, rng=galsim.BaseDeviate(3))
    im = galsim.ImageD(15, 15)
    got = sens.accumulate(galsim.PhotonArray(n, x=np.full(n, 8.0), y=np.full(n, 8.0),
                                             flux=np.ones(n), wavelength=np.full(n, wl)), im)
    assert_allclose(im.array.sum(), got)
    assert 0.3 < expect < 0.7  # the test has resolving power at this wavelength
    assert_allclose(got / n, expect, atol=4 * np.sqrt(expect * (1 - expect) / n))


def test_flat_area_response_achromatic_matches_galsim_areas():
    """CORRECTNESS: a00 counted from photons of a flat over a charged pixel (no
    wavelengths) equals GalSim's own a00 from its polygon areas
    (calculate_pixel_areas, galsim_acoeffs), within the counts' error."""
    a = galsim_acoeffs(SENSOR, 0)[0, 0]
    r = flat_area_response(SENSOR, None, charge=2e5, photons=2e4, seed=4)
    assert r["a00_err"] < 0.08 * abs(a)
    assert_allclose(r["a00"], a, atol=4 * r["a00_err"])


def test_chromatic_star_collects_the_requested_detected_flux():
    """CORRECTNESS: a y-band star (a third of its photons cross the silicon) is
    shot with flux / f incident photons, so GalSim collects `flux` electrons
    (Poisson); both twins hold the same charge (brighter-fatter moves it, the
    conversion depths are the same)."""
    stars = star_list(1, flux=(3e4, 3e4), seed=5)
    (p,) = draw_chromatic_star_pairs(stars, "y", sed="vega", sky=0.0, stamp=25, updates=20)
    assert_allclose(p["flux"], 3e4, atol=4 * np.sqrt(3e4))
    assert 1.3 < p["flux_incident"] / p["flux"] < 1.8
    assert_allclose(p["truth"].sum(), p["flux"], atol=4 * np.sqrt(3e4) + 0.005 * 3e4)
    assert_allclose(p["bf"].sum(), p["truth"].sum(), rtol=2e-3)
    assert not np.array_equal(p["bf"], p["truth"])


def test_chromatic_sky_is_collected_at_its_detected_level():
    """CORRECTNESS: in y the sky photons, collected through the sensor around the
    star with the band's wavelengths, are shot at sky / f incident photons, so the
    stamp holds the star's flux plus `sky` electrons per pixel (Poisson; a third
    of y photons cross the silicon, so a sky not divided by f would be nearly 40000 e
    short here)."""
    stars = star_list(1, flux=(1e4, 1e4), seed=8)
    (p,) = draw_chromatic_star_pairs(stars, "y", sky=200.0, stamp=25, updates=20)
    expect = p["flux"] + 200.0 * 25 * 25
    assert_allclose(p["truth"].sum(), expect, atol=5 * np.sqrt(expect))
    assert_allclose(p["bf"].sum(), p["truth"].sum(), rtol=1e-3)


def test_bad_input():
    with pytest.raises(ValueError, match="unknown band"):
        sample_wavelengths(10, "w", seed=1)
    with pytest.raises(ValueError, match="n must be"):
        sample_wavelengths(-1, "r", seed=1)
    with pytest.raises(ValueError, match="no GalSim sensor"):
        galsim_thickness("lsst_nope")
    with pytest.raises(ValueError, match="n_stars"):
        star_list(0, seed=1)
    with pytest.raises(ValueError, match="charge and photons"):
        flat_area_response(SENSOR, "r", charge=0, seed=1)
    with pytest.raises(ValueError, match="a band or a wavelength, not both"):
        flat_area_response(SENSOR, "r", wavelength=900.0, seed=1)
    with pytest.raises(ValueError, match="wavelength must lie"):
        flat_area_response(SENSOR, None, wavelength=2000.0, seed=1)
    with pytest.raises(ValueError, match="one value per photon"):
        accumulate_twins(np.zeros(3), np.zeros(3), np.ones(3), (1.0,), sensor=SENSOR, seed=1,
                         stamp=9, pixel_scale=0.2, rng=np.random.default_rng(1),
                         wavelength=np.ones(2))
