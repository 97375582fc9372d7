"""Tests of lsst_bfdrift.physics.absorption (silicon's absorption length and its temperature).

Kinds:

* correctness against an independent table: the Rajkanan, Singh & Shewchun
  (1979) model at 300 K against GalSim's measured table (Green 2008), within
  the model's known level (a factor 1.6 from 450 to 1050 nm);
* correctness of the model's form: an absorption edge at the indirect gap
  less a phonon (the gap of 1.12 eV at 300 K, Varshni's law), and its
  terms against a direct evaluation of the published formula at one point;
* physics the scaling must keep: exactly the table at 300 K; cooling
  lengthens every absorption length, most near the gap (red), and the
  change grows monotonically with the wavelength in the red;
* bad input refused with its reason.
"""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.absorption import (RAJKANAN, absorption_length,
                                             absorption_table_range, rajkanan_alpha)
from lsst_bfdrift.physics.depth import depth_distribution
from lsst_bfdrift.utils.errors import InputError


def test_the_model_at_300k_is_near_the_measured_table():
    wl = np.arange(450.0, 1051.0, 50.0)
    ratio = 1e4 / rajkanan_alpha(wl, 300.0) / absorption_length(wl)
    print("model / table absorption length at 300 K:", np.round(ratio, 2))
    assert np.all((ratio > 0.6) & (ratio < 1.6))


def test_one_point_against_the_published_formula_written_out():
    """1000 nm at 300 K: only the first indirect gap absorbs (E = 1.2398 eV)."""
    e, t, k = 1239.841984 / 1000.0, 300.0, 8.617333262e-5
    eg = 1.1557 - 7.021e-4 * t * t / (t + 1108.0)
    total = 0.0
    for ep, c in ((1.827e-2, 5.5), (5.773e-2, 4.0)):
        total += c * 3.231e2 * ((e - eg + ep) ** 2 / (np.exp(ep / (k * t)) - 1)
                                + (e - eg - ep) ** 2 / (1 - np.exp(-ep / (k * t))))
    # the package takes h c and k_B from astropy.constants: they agree with the
    # literals above to 3e-10, which moves alpha by ~5e-9 (a formula error moves it by far more)
    assert_allclose(rajkanan_alpha(1000.0, 300.0), total, rtol=1e-8)
    assert RAJKANAN["E_g"][0] == 1.1557


def test_the_absorption_edge_is_the_indirect_gap_less_a_phonon():
    t = 300.0
    eg = 1.1557 - 7.021e-4 * t * t / (t + 1108.0)
    edge = 1239.841984 / (eg - 5.773e-2)                 # nm: the last photon absorbed
    assert_allclose(eg, 1.1108, atol=1e-4)              # silicon's gap at room temperature
    assert rajkanan_alpha(edge * 0.999, t) > 0 and rajkanan_alpha(edge * 1.001, t) == 0


def test_cooling_lengthens_absorption_most_in_the_red():
    wl = np.array([500.0, 700.0, 900.0, 950.0, 1000.0, 1050.0])
    base = absorption_length(wl)
    assert_allclose(absorption_length(wl, temperature=300.0), base, rtol=0)
    assert_allclose(absorption_length(wl, temperature=None), base, rtol=0)
    cold = absorption_length(wl, temperature=173.0) / base
    warm = absorption_length(wl, temperature=330.0) / base
    print("L(173 K) / L(300 K):", np.round(cold, 2))
    assert np.all(cold > 1.0) and np.all(warm < 1.0)
    assert np.all(np.diff(cold[1:]) > 0)                 # the red grows with the wavelength
    # a Quantity of temperature is the same temperature
    from astropy import units as u
    assert_allclose(absorption_length(wl, temperature=-100.15 * u.deg_C),
                    absorption_length(wl, temperature=173.0), rtol=1e-9)
    assert cold[-1] > 2 * cold[0]


def test_a_cold_sensor_converts_z_and_y_photons_deeper():
    """At 173 K a 100 um sensor's y-band photons convert lower (nearer the gates)
    and fewer of them convert; u-band photons still convert at the window."""
    for band in ("z", "y"):
        warm, cold = depth_distribution(band, 100.0), depth_distribution(band, 100.0,
                                                                       temperature=173.0)
        assert cold.mean_height < warm.mean_height - 2.0
        assert cold.converted_fraction < warm.converted_fraction
        assert cold.temperature == 173.0 and warm.temperature is None
    u = depth_distribution("u", 100.0, temperature=173.0)
    assert u.mean_height > 99.5


def test_bad_input_is_refused():
    with pytest.raises(InputError, match=r"temperature must lie in \[20, 500\] K"):
        absorption_length(700.0, temperature=5.0)
    with pytest.raises(InputError, match=r"temperature must lie in"):
        absorption_length(700.0, temperature=float("nan"))
    with pytest.raises(InputError, match=r"no absorption model at 173 K beyond"):
        absorption_length([1000.0, 1200.0], temperature=173.0)
    lo, hi = absorption_table_range()
    with pytest.raises(InputError, match=r"wavelength must lie in"):
        absorption_length(hi + 1.0, temperature=173.0)
    with pytest.raises(InputError, match="a number of K or a Quantity of temperature"):
        absorption_length(700.0, temperature="cold")
    with pytest.raises(InputError, match="finite and positive"):
        rajkanan_alpha(-5.0, 300.0)
