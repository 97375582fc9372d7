"""Tests of lsst_bfdrift.physics.depth: where the photons of a band or a wavelength convert."""

import os

import astropy.units as u
import galsim
import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.absorption import absorption_length, absorption_table_range
from lsst_bfdrift.physics.depth import (BANDS, GALSIM_ZFIT, DepthDistribution, bandpass,
                                        conversion_nodes, depth_distribution,
                                        galsim_depth_factor, normalize_band, sed_photons)
from lsst_bfdrift.utils.errors import InputError, InputTypeError

T = 100.0  # um, the default silicon thickness


def _abs_table():
    """GalSim's silicon absorption table, read directly: (nm, um)."""
    path = os.path.join(galsim.meta_data.share_dir, "sensors", "abs_length.dat")
    return np.loadtxt(path, skiprows=1).T


def _depth_grid(t=T, n=200001):
    """Heights z (um) dense near the entrance window (depths from 1e-7 um)."""
    d = np.concatenate([[0.0], np.geomspace(1e-7, t, n)])
    return t - d, d


class TestAbsorption:
    def test_absorption_length_is_galsims_table(self):
        """CORRECTNESS: at the table's wavelengths, the absorption length is abs_length.dat's."""
        wl, length = _abs_table()
        assert_allclose(absorption_length(wl), length, rtol=1e-12)
        assert absorption_table_range() == (wl[0], wl[-1])

    def test_single_wavelength_converted_fraction_and_mean(self):
        """CORRECTNESS: one wavelength: fraction 1 - exp(-t/L); mean height by direct quadrature."""
        wl, length = _abs_table()
        k = np.argmin(np.abs(wl - 900.0))  # a table node: L read from the file
        L = length[k]
        d = depth_distribution(wl[k], T)
        assert_allclose(d.converted_fraction, -np.expm1(-T / L), rtol=1e-12)
        z, dep = _depth_grid()
        p = np.exp(-dep / L) / L / -np.expm1(-T / L)
        assert_allclose(np.trapezoid(p, dep), 1.0, rtol=1e-6)
        assert_allclose(d.mean_height, np.trapezoid(z * p, dep), rtol=1e-6)
        assert_allclose(d.pdf(z[::1000]), p[::1000], rtol=1e-10)

    def test_wavelength_quantity_equals_number(self):
        """CONSISTENCY: a Quantity (nm or um) gives the number's distribution."""
        a = depth_distribution(700.0, T)
        b = depth_distribution(0.7 * u.um, 100 * u.um)
        assert_allclose(b.mean_height, a.mean_height, rtol=1e-12)
        assert b.label == "700nm"


class TestBandpassAndSed:
    @pytest.mark.parametrize("band", BANDS)
    def test_bandpass_is_galsims(self, band):
        """CORRECTNESS: the throughput equals galsim.Bandpass of the same shipped file."""
        wl, thr = bandpass(band)
        ref = galsim.Bandpass(f"LSST_{band}.dat", wave_type="nm")
        inside = (wl > ref.blue_limit) & (wl < ref.red_limit)
        assert_allclose(thr[inside], ref(wl[inside]), rtol=1e-10, atol=1e-12)
        assert thr.max() > 0.05

    def test_blackbody_photons_follow_planck(self):
        """CORRECTNESS: photons per nm of a black body equal astropy's B_lambda * lambda / hc."""
        from astropy.modeling.models import BlackBody

        wl = np.linspace(320.0, 1050.0, 30)
        bb = BlackBody(temperature=5800 * u.K)
        blam = bb(wl * u.nm).to(u.erg / u.s / u.cm ** 2 / u.nm / u.sr,
                                equivalencies=u.spectral_density(wl * u.nm)).value
        ref = blam * wl
        got = sed_photons("5800K", wl)
        assert_allclose(got / got[10], ref / ref[10], rtol=1e-8)
        assert_allclose(sed_photons("blackbody:5800", wl), got, rtol=1e-14)
        assert_allclose(sed_photons(5800.0, wl), got, rtol=1e-14)
        assert_allclose(sed_photons(None, wl), 1.0)

    def test_galsim_sed_by_name(self):
        """CORRECTNESS: a named SED's photon density is galsim.SED's of that file."""
        path = os.path.join(galsim.meta_data.share_dir, "SEDs", "CWW_E_ext.sed")
        ref = galsim.SED(path, wave_type="Angstrom", flux_type="flambda")
        wl = np.linspace(400.0, 1000.0, 13)
        assert_allclose(sed_photons("CWW_E_ext", wl), ref(wl), rtol=1e-12)

    def test_band_mean_height_is_direct_sum(self):
        """CORRECTNESS: a band's mean height is the photon-weighted sum of per-wavelength means.

        The reference reads the throughput and absorption tables itself and
        sums ``T(l) (t - L (1 - e^{-t/L}))`` over a 1 nm grid.
        """
        wl, length = _abs_table()
        d = depth_distribution("z", T)
        path = os.path.join(galsim.meta_data.share_dir, "bandpasses", "LSST_z.dat")
        bw, bt = np.loadtxt(path).T
        grid = np.arange(bw[0], bw[-1], 1.0)
        thr = np.interp(grid, bw, bt)
        L = np.interp(grid, wl, length)
        det = thr * -np.expm1(-T / L)
        mean = np.sum(thr * (T - L * (1 - np.exp(-T / L)))) / det.sum()
        assert_allclose(d.mean_height, mean, rtol=2e-3)
        assert_allclose(d.converted_fraction, det.sum() / thr.sum(), rtol=2e-3)

    def test_red_converts_deeper_than_blue(self):
        """CORRECTNESS (physics): u converts at the window, y spreads; a red SED converts deeper."""
        h = {b: depth_distribution(b, T).mean_height for b in BANDS}
        assert h["u"] > 99.9 and h["y"] < 65.0
        assert all(h[a] > h[b] for a, b in zip(BANDS, BANDS[1:]))
        red = depth_distribution("z", T, sed="CWW_E_ext").mean_height
        blue = depth_distribution("z", T, sed=15000.0).mean_height
        assert red < blue


class TestNodeWeights:
    def _hat(self, nodes, k, z):
        """Hat function k of the nodes (phi_0 = 1 below the first node)."""
        y = np.zeros(nodes.size)
        y[k] = 1.0
        out = np.interp(z, nodes, y)
        if k == 0:
            out = np.where(z < nodes[0], 1.0, out)
        return out

    @pytest.mark.parametrize("source", ["u", "r", "y", 1000.0])
    def test_weights_equal_numerical_integral(self, source):
        """CORRECTNESS: closed-form weights equal numpy quadrature of the exponential profile.

        The density is rebuilt here from the absorption lengths and
        coefficients (``sum c_k exp(-(t - z)/L_k)/L_k``) and integrated
        against the hat functions on a depth grid geometric from 1e-7 um.
        """
        d = depth_distribution(source, T)
        nodes = conversion_nodes(T, 0.5, 6)
        z, dep = _depth_grid(n=40001)
        p = (d.coefficients[:, None] / d.absorption[:, None] *
             np.exp(-dep[None, :] / d.absorption[:, None])).sum(axis=0)
        ref = np.array([np.trapezoid(p * self._hat(nodes, k, z), dep)
                        for k in range(nodes.size)])
        w = d.node_weights(nodes)
        assert_allclose(w.sum(), 1.0, rtol=1e-12)
        assert_allclose(w, ref, atol=2e-6)

    def test_weights_reproduce_linear_function(self):
        """CORRECTNESS: hat weights integrate a linear function of z exactly (the mean height)."""
        d = depth_distribution("i", T)
        nodes = conversion_nodes(T, 0.0, 5)
        assert_allclose(np.dot(d.node_weights(nodes), nodes), d.mean_height, rtol=1e-10)

    def test_cdf_and_pdf_agree(self):
        """CONSISTENCY: the cdf is the integral of the pdf, 0 at the gates and 1 at the window."""
        d = depth_distribution("y", T)
        assert_allclose(d.cdf([0.0, T]), [0.0, 1.0], atol=1e-12)
        z, dep = _depth_grid(50.0, n=20001)  # depths 0 .. 50 um: heights t .. t - 50
        assert_allclose(1 - d.cdf(50.0)[0], np.trapezoid(d.pdf(T - dep), dep), rtol=1e-6)
        assert d.pdf([-1.0, T + 1.0]).tolist() == [0.0, 0.0]


class TestGalsimFactor:
    def test_factor_is_mean_tanh(self):
        """CORRECTNESS: E[tanh(z/12)] by direct quadrature of one wavelength's profile."""
        L = float(absorption_length(950.0))
        z, dep = _depth_grid()
        p = np.exp(-dep / L) / L / -np.expm1(-T / L)
        ref = np.trapezoid(p * np.tanh(z / GALSIM_ZFIT), dep)
        assert_allclose(galsim_depth_factor(depth_distribution(950.0, T)), ref, rtol=1e-5)
        u = galsim_depth_factor(depth_distribution("u", T))
        assert 1.0 - 1e-6 < u <= 1.0  # tanh <= 1: a mean above 1 is a quadrature error


class TestBadInput:
    @pytest.mark.parametrize("name", ["v", "lsst_q", "red", ""])
    def test_unknown_band(self, name):
        with pytest.raises(InputError, match="unknown band"):
            depth_distribution(name, T)

    @pytest.mark.parametrize("wl", [200.0, 1500.0])
    def test_wavelength_outside_table(self, wl):
        with pytest.raises(InputError, match="outside the silicon absorption table"):
            depth_distribution(wl, T)

    def test_band_spellings(self):
        assert [normalize_band(s) for s in ("R", "r_57", "LSST_r", "lsst r", " y ")] == \
            ["r", "r", "r", "r", "y"]
        with pytest.raises(InputTypeError, match="band must be a string"):
            normalize_band(3)

    def test_bad_nodes_thickness_sed(self):
        d = depth_distribution("r", T)
        with pytest.raises(InputError, match="conversion nodes must increase"):
            d.node_weights([0.0, 50.0, 40.0, T])
        with pytest.raises(InputError, match="conversion nodes must increase"):
            d.node_weights([0.0, 50.0])
        with pytest.raises(InputError, match="thickness must be a positive"):
            depth_distribution("r", -1.0)
        with pytest.raises(InputError, match="unknown sed"):
            depth_distribution("r", T, sed="nonesuch")
        with pytest.raises(InputError, match="temperature must be a positive"):
            depth_distribution("r", T, sed=-5.0)
        with pytest.raises(InputError, match="photon weights"):
            DepthDistribution([500.0], [0.0], T)
        with pytest.raises(InputError, match="number of conversion nodes"):
            conversion_nodes(T, 0.5, 1)

    def test_inputs_not_modified(self):
        wl = np.array([500.0, 700.0])
        ph = np.array([1.0, 2.0])
        DepthDistribution(wl, ph, T)
        assert wl.tolist() == [500.0, 700.0] and ph.tolist() == [1.0, 2.0]
