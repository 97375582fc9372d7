"""Tests of lsst_bfdrift.physics.sensor: parameters, validation, model assembly."""

import numpy as np
import pytest
from astropy import units as u
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.fields import BackdropField, PointDipoles
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters


class TestSensorParameters:
    def test_paper_values_and_defaults(self):
        p = SensorParameters.paper()
        assert (p.pixel_pitch, p.thickness, p.v_bss) == (10.0, 100.0, -50.0)
        assert (p.xi_cs, p.xi_ck, p.xi0, p.channel_depth) == (-14.3, 5.0, 1000.0, 2.0)
        assert p.z_collect == p.channel_depth
        d = SensorParameters()  # the calibrated ITL sensor: the paper's geometry
        assert (d.pixel_pitch, d.thickness, d.xi_cs, d.xi_ck) == (10.0, 100.0, -14.3, 5.0)
        assert d.z_collect == d.collection_height == 0.5

    def test_quantities_are_converted(self):
        p = SensorParameters(thickness=0.1 * u.mm, v_bss=-40000 * u.mV,
                             acceptor_density=1e18 * u.m**-3, xi0=1.602176634e-16 * u.C)
        assert_allclose([p.thickness, p.v_bss, p.acceptor_density, p.xi0],
                        [100.0, -40.0, 1e12, 1000.0])

    def test_wrong_units_raise(self):
        with pytest.raises(u.UnitConversionError):
            SensorParameters(thickness=3 * u.V)

    def test_unknown_key(self):
        with pytest.raises(KeyError, match="unknown sensor parameter.*thicknes"):
            SensorParameters.from_dict({"thicknes": 100})

    @pytest.mark.parametrize("kw, match", [
        ({"thickness": -100.0}, "thickness"),
        ({"pixel_pitch": 0.0}, "pixel_pitch"),
        ({"channel_depth": float("nan")}, "finite"),
        ({"v_bss": "abc"}, "number"),
        ({"acceptor_density": 1e14}, "not fully depleted"),
        ({"collection_height": 150.0}, "collection height"),
        ({"clock_separation": 12.0}, "clock_separation"),
        ({"edge_side": 0}, "edge_side"),
        ({"charge_images": -1}, "charge_images"),
        ({"backside_images": 1}, "True or False"),
        ({"truncations": [(0, 1.0, 2, 1.0)]}, "extends"),
        ({"row_overrides": [(1, 2, 3)]}, "2 numbers"),
    ])
    def test_bad_values_name_the_problem(self, kw, match):
        with pytest.raises((ValueError, TypeError), match=match):
            SensorParameters(**kw)

    def test_round_trip_dict(self):
        p = SensorParameters(bloom_stop=3, row_overrides={2: 1.5}, truncations=[(1, 2, -1, 3)])
        q = SensorParameters.from_dict(p.to_dict())
        assert p == q
        assert p.to_json() == q.to_json()


class TestSensorModel:
    def test_terms_of_default_model(self):
        m = SensorModel(SensorParameters.paper())
        assert isinstance(m.terms[0], BackdropField)
        # CS grid and 2 clock grids; their backside images are ~1e-27 and dropped
        assert len(m.terms) == 1 + 3
        thin = SensorModel(SensorParameters(thickness=40.0, acceptor_density=1e11))
        assert len(thin.terms) == 1 + 3 + 3

    def test_field_is_sum_of_terms(self, rng):
        m = SensorModel(SensorParameters(bloom_stop=2, edge=-3, xi_guard=2.0,
                                         truncations=[(1, 0.5, 1, 3.0)]),
                        charge={(0, 0): 1e4, (1, 2): 5e3})
        x, y, z = rng.uniform(-20, 20, 50), rng.uniform(-20, 20, 50), rng.uniform(3, 100, 50)
        tot = np.array(m.field(x, y, z))
        ref = sum(np.array(t.field(x, y, z)) for t in m.terms)
        assert_allclose(tot, ref, rtol=1e-12, atol=1e-15)

    def test_charge_dipoles_and_images(self):
        p = SensorParameters(channel_depth=3.0, charge_images=3)
        m = SensorModel(p, charge={(2, -1): 1e4})
        dip = [t for t in m.terms if isinstance(t, PointDipoles)]
        assert [d.height for d in dip] == [0.0, 200.0, -200.0, 400.0]
        for d in dip:
            assert_allclose([d.x[0], d.y[0], d.p_z[0]], [25.0, -5.0, -2 * 1e4 * 3.0])

    def test_charge_must_be_finite(self):
        with pytest.raises(ValueError, match="finite.*pixel"):
            SensorModel(charge={(0, 0): float("nan")})

    def test_symmetry_of_default_field(self, rng):
        """Mirror symmetry about a pixel's centre lines (x -> p - x, y -> p - y)."""
        m = SensorModel(charge={(0, 0): 1e4})
        x, y, z = rng.uniform(0, 10, 30), rng.uniform(0, 10, 30), rng.uniform(2, 60, 30)
        ex, ey, ez = m.field(x, y, z)
        mx, my, mz = m.field(10 - x, y, z)
        assert_allclose([mx, my, mz], [-ex, ey, ez], rtol=1e-9, atol=1e-12)
        mx, my, mz = m.field(x, 10 - y, z)
        assert_allclose([mx, my, mz], [ex, -ey, ez], rtol=1e-9, atol=1e-12)

    def test_channel_stops_repel_electrons(self):
        """Near a channel stop the lateral field pushes electrons (along -E) away."""
        m = SensorModel(SensorParameters(xi_ck=0.0))
        ex, _, _ = m.field(np.array([1.0, -1.0]), 5.0, 3.0)
        assert -ex[0] > 0 and -ex[1] < 0

    def test_clock_barrier_repels_electrons(self):
        m = SensorModel(SensorParameters.paper(xi_cs=0.0))
        _, ey, _ = m.field(5.0, np.array([2.5, -2.5]), 1.0)
        assert -ey[0] > 0 and -ey[1] < 0


class TestChargeCloud:
    def test_cloud_keeps_the_dipole_and_has_the_stated_size(self):
        """The 3 x 3 Gauss-Hermite cloud: total dipole and centre unchanged,
        rms lateral offset = charge_cloud per axis."""
        p = SensorParameters(charge_cloud=1.5)
        pt = SensorModel(p.replace(charge_cloud=0.0)).with_charge({(0, 0): 1e4}).charge_terms()[0]
        cl = SensorModel(p).with_charge({(0, 0): 1e4}).charge_terms()[0]
        assert cl.x.size == 9 * pt.x.size
        assert_allclose(cl.p_z.sum(), pt.p_z.sum())
        w = cl.p_z / cl.p_z.sum()
        assert_allclose((w * cl.x).sum(), pt.x[0])
        assert_allclose(np.sqrt((w * (cl.x - pt.x[0]) ** 2).sum()), 1.5)
        assert_allclose(np.sqrt((w * (cl.y - pt.y[0]) ** 2).sum()), 1.5)

    def test_far_field_equals_the_point_charge(self):
        """At 5 pixels the cloud's field equals the point dipole's to its
        quadrupole order (relative (s / r)^2 ~ 1e-3); right above its centre
        the spread charge's field is weaker."""
        p = SensorParameters(charge_cloud=1.0)
        near, far = (5.0, 5.0, 3.0), (55.0, 5.0, 3.0)
        pt = SensorModel(p.replace(charge_cloud=0.0)).with_charge({(0, 0): 1e4})
        cl = SensorModel(p).with_charge({(0, 0): 1e4})
        ref = np.array(pt.charge_terms()[0].field(*far))
        got = np.array(cl.charge_terms()[0].field(*far))
        assert_allclose(got, ref, rtol=3e-3, atol=1e-3 * np.abs(ref).max())
        e_pt = np.abs(np.array(pt.charge_terms()[0].field(5.0, 5.0, 1.5))).max()
        e_cl = np.abs(np.array(cl.charge_terms()[0].field(5.0, 5.0, 1.5))).max()
        assert e_cl < e_pt
        with pytest.raises(ValueError, match="charge_cloud"):
            SensorParameters(charge_cloud=-1.0)

    def test_parallel_variance_elongates_the_cloud_along_y_only(self):
        """charge_variance_parallel adds its variance along y: rms extents
        charge_cloud along x and sqrt(charge_cloud^2 + variance) along y,
        total dipole and centre unchanged; without charge_cloud the rule
        needs 3 dipoles (one per y offset), not 9 (consistency of the rule
        against its stated moments)."""
        pt = SensorModel(SensorParameters()).with_charge({(0, 0): 1e4}).charge_terms()[0]
        for sx, var, n in ((0.0, 2.25, 3), (1.0, 3.0, 9)):
            cl = SensorModel(SensorParameters(charge_cloud=sx, charge_variance_parallel=var)
                             ).with_charge({(0, 0): 1e4}).charge_terms()[0]
            assert cl.x.size == n * pt.x.size
            w = cl.p_z / cl.p_z.sum()
            assert_allclose(cl.p_z.sum(), pt.p_z.sum())
            assert_allclose([(w * cl.x).sum(), (w * cl.y).sum()], [pt.x[0], pt.y[0]])
            assert_allclose(np.sqrt((w * (cl.x - pt.x[0]) ** 2).sum()), sx, atol=1e-12)
            assert_allclose((w * (cl.y - pt.y[0]) ** 2).sum(), sx ** 2 + var)
        with pytest.raises(ValueError, match="charge_variance_parallel"):
            SensorParameters(charge_variance_parallel=-0.1)

    def test_cloud_must_stay_inside_its_pixel(self):
        """The rule's outer dipoles lie sqrt(3) rms from the centre: beyond the
        half pitch they would be another pixel's charge."""
        SensorParameters(charge_cloud=2.8, charge_variance_parallel=0.0)
        with pytest.raises(ValueError, match="inside the pixel"):
            SensorParameters(charge_cloud=2.9)
        with pytest.raises(ValueError, match="inside the pixel"):
            SensorParameters(charge_variance_parallel=8.4)

    def test_elongated_cloud_moves_area_to_its_parallel_neighbours(self):
        """Independent physical check on the drift model: a packet longer
        along the column puts its charge nearer the row boundaries, so the
        neighbours along y gain area relative to those along x (a01 / a10
        grows) and the total area is conserved as for the point packet (sum
        rule over lags 0-9 within 3 % of a00: the rest lies beyond lag 9)."""
        from lsst_bfdrift.calibration.acoeff_model import electrostatic_acoeffs
        from lsst_bfdrift.templates.refine import lag_multiplicity
        base = SensorParameters()
        kw = dict(max_lag=9, charge=1e4, near_samples=16, far_samples=6, tol=2e-6)
        a0 = electrostatic_acoeffs(base, **kw)
        a1 = electrostatic_acoeffs(base.replace(charge_variance_parallel=4.0), **kw)
        assert a1[0, 1] / a1[1, 0] > 1.2 * a0[0, 1] / a0[1, 0]
        w = lag_multiplicity(9)
        for a in (a0, a1):
            assert abs(np.sum(w * a)) < 0.03 * abs(a[0, 0])
