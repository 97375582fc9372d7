"""Tests of lsst_bfdrift.simulation.spots (galsim.SiliconSensor spot series with twins).

Each test says whether it checks against an independent reference (GalSim's
own brighter-fatter effect against its BF-free twin, an analytic profile) or
the module's consistency (files, seeds, refusals).
"""

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose
from scipy.special import erf

from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.catalogs.spot_slopes import fit_spot_slope
from lsst_bfdrift.catalogs.spots import read_spot_images
from lsst_bfdrift.simulation.spots import (peak_fraction, simulate_spot_series, spot_profile,
                                           write_spot_series)


def _column(cat, name):
    return np.asarray(getattr(cat[name], "value", cat[name]), float)


def test_galsim_spots_grow_with_flux_and_their_twins_do_not():
    """Independent reference (GalSim's own BF): spots drawn by
    galsim.SiliconSensor get larger with flux (size slope detected at z > 4,
    sigma_x and sigma_y both), their BF-free twins (same photons and noise)
    do not (|z| < 3), and the slope of the paired difference, BF minus twin,
    agrees with the BF spots' own slope within its error."""
    sim = simulate_spot_series(grid=(3, 3), n_images=4, peak_max=5e4, twin=True, seed=3,
                               full_well=1e5)
    bf = SpotSeries(sim["images"], exptimes=sim["exptimes"], saturation=1e5)
    twin = SpotSeries(sim["twins"], exptimes=sim["exptimes"], grid=bf.grid, saturation=1e5)
    a, b = bf.fit(), twin.fit()
    assert a["size"]["z"] > 4 and a["sigma_x"]["slope"] > 0 and a["sigma_y"]["slope"] > 0
    for name in ("size", "sigma_x", "sigma_y", "e1", "e2"):
        assert abs(b[name]["z"]) < 3, (name, b[name]["slope"], b[name]["slope_err"])
    c1, c2 = bf.catalog, twin.catalog
    use = np.asarray(c1["use"]) & np.asarray(c2["use"])
    paired = fit_spot_slope(np.asarray(c1["spot"])[use], np.asarray(c1["image"])[use],
                            _column(c1, "flux")[use],
                            (_column(c1, "size") - _column(c2, "size"))[use],
                            _column(c1, "size_err")[use], scale_errors=True)
    assert paired["z"] > 30  # the paired difference has no pixel noise of its own
    assert abs(a["size"]["slope"] - paired["slope"]) < 3 * a["size"]["slope_err"]
    assert paired["slope"] > 0 and b["n_points"] == a["n_points"] == 36


def test_profiles_and_peak_fraction():
    """Independent reference: a pixel-centred Gaussian's peak pixel holds
    erf(1 / (2 sqrt(2) sigma))^2 of its flux; a Moffat spot has the FWHM of
    the Gaussian of the same sigma."""
    for sigma in (1.0, 1.5, 3.0):
        expected = erf(0.5 / (np.sqrt(2) * sigma)) ** 2
        # GalSim draws to its default accuracy (a few 1e-4)
        assert_allclose(peak_fraction(spot_profile("gaussian", sigma)), expected, rtol=1e-3)
    moffat = spot_profile("moffat", 2.0, beta_moffat=3.5)
    assert_allclose(moffat.calculateFWHM(), 2.0 * 2 * np.sqrt(2 * np.log(2)), rtol=1e-6)
    with pytest.raises(ValueError, match="profile must be one of"):
        spot_profile("airy", 1.5)
    with pytest.raises(ValueError, match="sigma must be a positive"):
        spot_profile("gaussian", 0.0)


def test_files_carry_exptime_unit_saturation_and_read_back(tmp_path):
    """Consistency: the files hold EXPTIME, BUNIT (adu with GAIN), SATURATE
    in ADU and the bias level; read back they are the simulated electrons;
    the twins say they are truth only; the same seed gives the same series
    and another seed another one."""
    kw = dict(grid=(2, 2), n_images=2, flux_min=2e3, peak_max=500.0, twin=True, bias=300.0,
              full_well=8e4, pitch=30.0, updates=50)
    sim = simulate_spot_series(seed=5, **kw)
    again = simulate_spot_series(seed=5, **kw)
    other = simulate_spot_series(seed=6, **kw)
    assert all(np.array_equal(a, b) for a, b in zip(sim["images"], again["images"]))
    assert all(np.array_equal(a, b) for a, b in zip(sim["twins"], again["twins"]))
    assert not np.array_equal(sim["images"][1], other["images"][1])
    assert_allclose(sim["levels"].value, [2e3, 500.0 / peak_fraction(spot_profile("gaussian",
                                                                                   1.5))])
    paths = write_spot_series(sim, tmp_path / "s", gain=2.0)
    hdr = fits.getheader(paths["images"][1])
    assert hdr["BUNIT"] == "adu" and hdr["GAIN"] == 2.0 and hdr["SATURATE"] == 4.015e4
    assert_allclose(hdr["EXPTIME"], sim["exptimes"].value[1])
    assert hdr["BIASLVL"] == 300.0 and hdr["SENSOR"] == "lsst_itl_50_8"
    assert fits.getheader(paths["twins"][0])["IMAGETYP"] == "SPOT NOBF TRUTH"
    ex = read_spot_images(paths["images"])
    # read back in electrons less the stated pedestal (BIASLVL), saturation likewise
    assert ex[1].bias == 300.0
    assert_allclose(ex[1].data, sim["images"][1] - 300.0, rtol=1e-6, atol=1e-3)
    assert_allclose(ex[1].saturation, 8.03e4 - 300.0)
    assert [e.exptime for e in ex] == pytest.approx(sim["exptimes"].value.tolist())
    with pytest.raises(FileExistsError, match="exists"):
        write_spot_series(sim, tmp_path / "s")


@pytest.mark.parametrize("kw, match", [({"grid": (0, 3)}, "grid must be"),
                                       ({"n_images": 1}, "n_images must be at least 2"),
                                       ({"full_well": -1.0}, "full_well must be positive"),
                                       ({"read_noise": np.nan}, "read_noise must be finite"),
                                       ({"profile": "airy"}, "profile must be one of"),
                                       ({"peak_max": 10.0}, "below flux_min")])
def test_bad_settings_are_refused(kw, match):
    """Bad input: settings out of range are clear errors before GalSim runs."""
    with pytest.raises(ValueError, match=match):
        simulate_spot_series(**kw)
