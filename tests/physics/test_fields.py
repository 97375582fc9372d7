"""Tests of the electrostatic field terms in :mod:`lsst_bfdrift.physics.fields`.

Every term is compared with an independent reference: direct sums of line
dipoles, numerical integrals (``scipy.integrate.quad``) of point or line
dipoles, textbook formulas written out here, Coulomb's law for point charges,
or physical properties (periodicity, image planes being equipotentials,
Gauss's law for the backdrop).  Units: um, V/um, e (line-dipole moments per
unit length) and e um (point dipoles).
"""

import numpy as np
import pytest
import scipy.constants as sc
from numpy.testing import assert_allclose
from scipy import integrate

from lsst_bfdrift.physics import constants
from lsst_bfdrift.physics.constants import COULOMB_UM, SPACE_CHARGE_UM
from lsst_bfdrift.physics.fields import (
    BackdropField,
    HalfPeriodicDipoleGrid,
    LineDipole,
    PeriodicDipoleGrid,
    PointDipoles,
    TabulatedBackdrop,
    TruncatedLineDipole,
    dipole_sheet_field_2d,
    line_dipole_field_2d,
    periodic_grid_field_2d,
)

PITCH = 10.0


# ---------------------------------------------------------------------------
# Independent reference formulas
# ---------------------------------------------------------------------------

def point_dipole_field(p, r):
    """C (3 (p.r) r / r^5 - p / r^3) for moment p (e um) at separation r (um).

    ``p`` has shape (3,), ``r`` shape (..., 3).
    """
    r = np.asarray(r, float)
    p = np.asarray(p, float)
    rn = np.linalg.norm(r, axis=-1)[..., None]
    pr = np.sum(r * p, axis=-1)[..., None]
    return COULOMB_UM * (3.0 * pr * r / rn**5 - p / rn**3)


def point_charge_field(q, pos, r):
    """Coulomb field (V/um) at points ``r`` of a charge ``q`` (e) at ``pos``."""
    d = np.asarray(r, float) - np.asarray(pos, float)
    return COULOMB_UM * q * d / np.linalg.norm(d, axis=-1)[..., None] ** 3


def paper_line_dipole(u, w, m_perp, m_z):
    """Rasmussen's line dipole, E = (2 (xi.rhat) rhat - xi) / (2 pi eps r^2).

    1 / (2 pi eps) = 2 e / (4 pi eps), i.e. 2 COULOMB_UM per e of moment.
    """
    r = np.hypot(u, w)
    ru, rw = u / r, w / r
    xdot = m_perp * ru + m_z * rw
    k = 2.0 * COULOMB_UM / r**2
    return k * (2.0 * xdot * ru - m_perp), k * (2.0 * xdot * rw - m_z)


def line_sum(u, w, offsets, m_perp, m_z):
    """Direct sum of line dipoles at perpendicular coordinates ``offsets``.

    ``u``, ``w`` are 1-d arrays of field points; returns summed (eu, ew).
    """
    eu, ew = line_dipole_field_2d(np.asarray(u)[:, None] - offsets[None, :],
                                  np.asarray(w)[:, None], m_perp, m_z)
    return eu.sum(axis=1), ew.sum(axis=1)


def half_line_tail(u, w, start, direction, pitch, m_perp, m_z):
    """Lines at start + direction * s for s >= 0 smeared to a continuum.

    Integral of :func:`line_dipole_field_2d` over the half line, divided by
    the pitch, done by ``scipy.integrate.quad``.  Used as the analytic tail of
    a direct sum (midpoint rule: ``start`` is half a pitch beyond the last
    summed line), whose error is then O((pitch / start)^3).
    """
    # Substitute s = L (1 - v) / v, v in (0, 1], L = |start|: the integrand
    # ~ 1 / s^2 becomes smooth and bounded on a finite interval.
    big_l = abs(start)
    out = np.empty((2, len(u)))
    for i, (ui, wi) in enumerate(zip(u, w)):
        for k in range(2):
            def f(v, k=k, ui=ui, wi=wi):
                s = big_l * (1.0 - v) / v
                e = line_dipole_field_2d(ui - (start + direction * s), wi, m_perp, m_z)[k]
                return e * big_l / (v * v) / pitch
            out[k, i] = integrate.quad(f, 0.0, 1.0, epsabs=0.0, epsrel=1e-10,
                                       limit=200)[0]
    return out


def assert_vec_close(got, ref, rtol, atol=0.0):
    """|got - ref| <= rtol * |ref| + atol pointwise for vector fields."""
    got = np.asarray(got, float)
    ref = np.asarray(ref, float)
    err = np.sqrt(np.sum((got - ref) ** 2, axis=0))
    mag = np.sqrt(np.sum(ref**2, axis=0))
    bad = err > rtol * mag + atol
    assert not np.any(bad), (
        f"max relative error {np.max(err / np.where(mag > 0, mag, 1.0)):.3g} "
        f"> {rtol} at {np.flatnonzero(bad)}")


# ---------------------------------------------------------------------------
# Constants
# ---------------------------------------------------------------------------

class TestConstants:
    def test_coulomb_um(self):
        # e / (4 pi eps0 eps_Si) in V m, converted to V um.
        ref = sc.e / (4 * np.pi * sc.epsilon_0 * 11.7) * 1e6
        assert_allclose(COULOMB_UM, ref, rtol=1e-9)
        assert constants.EPS_SI == 11.7

    def test_space_charge_um(self):
        # e * (1 cm^-3 = 1e6 m^-3) / (eps0 eps_Si) in V/m^2, to V/um^2.
        ref = sc.e * 1e6 / (sc.epsilon_0 * 11.7) * 1e-12
        assert_allclose(SPACE_CHARGE_UM, ref, rtol=1e-9)


# ---------------------------------------------------------------------------
# line_dipole_field_2d and LineDipole
# ---------------------------------------------------------------------------

class TestLineDipole:
    def test_2d_kernel_matches_paper_formula(self):
        rng = np.random.default_rng(101)
        u = rng.uniform(-20, 20, 50)
        w = rng.uniform(-20, 20, 50)
        mp, mz = rng.normal(size=2) * 1e3
        assert_allclose(line_dipole_field_2d(u, w, mp, mz),
                        paper_line_dipole(u, w, mp, mz), rtol=1e-12)

    def test_2d_kernel_is_integral_of_point_dipoles(self):
        # An infinite line of point dipoles xi per unit length: integrate the
        # 3-d point-dipole field along the line (independent of the 2 C factor).
        rng = np.random.default_rng(102)
        for _ in range(4):
            u, w = rng.uniform(0.5, 5.0, 2) * rng.choice([-1, 1], 2)
            mp, mz = rng.normal(size=2)
            p = np.array([mp, 0.0, mz])  # line along y: perp = x

            def comp(t, k):
                return point_dipole_field(p, np.array([u, -t, w]))[k]

            ref = [integrate.quad(comp, -np.inf, np.inf, args=(k,), epsabs=0,
                                  epsrel=1e-11)[0] for k in (0, 2)]
            assert_allclose(line_dipole_field_2d(u, w, mp, mz), ref, rtol=1e-8)

    @pytest.mark.parametrize("axis", ["x", "y"])
    def test_class_matches_paper_formula(self, axis):
        rng = np.random.default_rng(103)
        pos, h = 3.7, 1.5
        mp, mz = 2.0e3, -7.0e2
        x = rng.uniform(-10, 10, 40)
        y = rng.uniform(-10, 10, 40)
        z = rng.uniform(-5, 10, 40)
        line = LineDipole(axis, pos, height=h, m_perp=mp, m_z=mz)
        ex, ey, ez = line.field(x, y, z)
        u = (x if axis == "y" else y) - pos
        eu, ew = paper_line_dipole(u, z - h, mp, mz)
        if axis == "y":
            assert_allclose(ex, eu, rtol=1e-12)
            assert_allclose(ey, 0.0, atol=0)
        else:
            assert_allclose(ey, eu, rtol=1e-12)
            assert_allclose(ex, 0.0, atol=0)
        assert_allclose(ez, ew, rtol=1e-12)

    def test_broadcasting(self):
        line = LineDipole("y", 0.0, m_perp=1.0, m_z=1.0)
        ex, ey, ez = line.field(np.linspace(1, 2, 3)[:, None], 0.0, np.array([1.0, 2.0]))
        assert ex.shape == ey.shape == ez.shape == (3, 2)

    def test_mirrored_image_rule(self):
        line = LineDipole("x", 2.0, height=3.0, m_perp=5.0, m_z=-4.0)
        img = line.mirrored(100.0)
        assert isinstance(img, LineDipole)
        # xi' = 2 (xi.k) k - xi: in-plane flips, z kept; at 2 z_plane - height.
        assert (img.axis, img.position) == ("x", 2.0)
        assert_allclose([img.height, img.m_perp, img.m_z], [197.0, -5.0, -4.0])

    @pytest.mark.parametrize("axis", ["x", "y"])
    @pytest.mark.parametrize("moment", [(1.0e3, 0.0), (0.0, 1.0e3), (6e2, -8e2)])
    def test_image_makes_plane_equipotential(self, axis, moment):
        # Line + image: the mirror plane is an equipotential, i.e. the field
        # has no in-plane (tangential) component there.
        z_plane = 100.0
        line = LineDipole(axis, 1.0, height=2.0, m_perp=moment[0], m_z=moment[1])
        img = line.mirrored(z_plane)
        s = np.linspace(-300, 300, 61)
        x, y = (s, 0.3) if axis == "y" else (0.3, s)
        e = np.add(line.field(x, y, z_plane), img.field(x, y, z_plane))
        ref = np.abs(line.field(x, y, z_plane)).max()
        tangential = e[0] if axis == "y" else e[1]
        assert_allclose(tangential, 0.0, atol=1e-12 * ref)
        assert_allclose(e[1] if axis == "y" else e[0], 0.0, atol=0)


# ---------------------------------------------------------------------------
# periodic_grid_field_2d and PeriodicDipoleGrid
# ---------------------------------------------------------------------------

class TestPeriodicGrid2d:
    @pytest.mark.parametrize("seed", [201, 202])
    def test_matches_direct_sum(self, seed):
        # Direct sum over m = -M..M (2M + 1 >= 1e5 lines), plus the two
        # half-line tails beyond (M + 1/2) pitch integrated numerically (the
        # truncation tail alone is ~1/M, far above the tolerance where the
        # grid field is exponentially small).
        rng = np.random.default_rng(seed)
        n = 12
        u = rng.uniform(-1.0, 1.0, n) * PITCH
        w = rng.uniform(0.2, 1.5, n) * PITCH * np.where(np.arange(n) % 2, 1.0, -1.0)
        mp, mz = rng.normal(size=2) * 1e3
        M = 50_000
        m = np.arange(-M, M + 1) * PITCH
        eu, ew = line_sum(u, w, m, mp, mz)
        right = half_line_tail(u, w, (M + 0.5) * PITCH, +1, PITCH, mp, mz)
        left = half_line_tail(u, w, -(M + 0.5) * PITCH, -1, PITCH, mp, mz)
        ref = np.array([eu, ew]) + right + left
        got = periodic_grid_field_2d(u, w, PITCH, mp, mz)
        assert_vec_close(got, ref, rtol=1e-5)

    def test_periodic_in_u(self):
        rng = np.random.default_rng(203)
        u = rng.uniform(-PITCH, PITCH, 30)
        w = rng.uniform(0.1, 2.0, 30) * PITCH * rng.choice([-1, 1], 30)
        base = np.array(periodic_grid_field_2d(u, w, PITCH, 3.0, -2.0))
        scale = np.abs(base).max()
        for k in (-3, -1, 1, 2, 7):
            shifted = periodic_grid_field_2d(u + k * PITCH, w, PITCH, 3.0, -2.0)
            assert_allclose(shifted, base, rtol=1e-9, atol=1e-12 * scale)

    def test_far_from_plane_decays_without_overflow(self):
        u = np.linspace(-PITCH, PITCH, 21)
        mp, mz = 1e3, -2e3
        near = np.array(periodic_grid_field_2d(u, 1.0 * PITCH, PITCH, mp, mz))
        for w in (100 * PITCH, -100 * PITCH, 1000 * PITCH):
            e = np.array(periodic_grid_field_2d(u, w, PITCH, mp, mz))
            assert np.all(np.isfinite(e))
            assert np.abs(e).max() < 1e-200 * np.abs(near).max()
        # Decay rate exp(-2 pi |w| / p) per the leading Fourier harmonic:
        # |E| is independent of u to relative O(exp(-2 pi |w| / p)).
        e3 = np.hypot(*periodic_grid_field_2d(u, 3 * PITCH, PITCH, mp, mz))
        e4 = np.hypot(*periodic_grid_field_2d(u, 4 * PITCH, PITCH, mp, mz))
        assert_allclose(e4 / e3, np.exp(-2 * np.pi), rtol=1e-7)

    def test_field_symmetry_of_m_z_grid(self):
        # A grid of z dipoles: E_u is odd in u, E_w even in u.
        u = np.linspace(0.05, 0.45, 9) * PITCH
        w = 0.3 * PITCH
        eu_p, ew_p = periodic_grid_field_2d(u, w, PITCH, 0.0, 1.0)
        eu_m, ew_m = periodic_grid_field_2d(-u, w, PITCH, 0.0, 1.0)
        assert_allclose(eu_m, -eu_p, rtol=1e-12)
        assert_allclose(ew_m, ew_p, rtol=1e-12)


class TestPeriodicDipoleGrid:
    @pytest.mark.parametrize("axis", ["x", "y"])
    def test_axis_mapping(self, axis):
        rng = np.random.default_rng(211)
        pos, h = 2.5, 4.0
        mp, mz = 1.2e3, 3.4e2
        grid = PeriodicDipoleGrid(axis, PITCH, pos, height=h, m_perp=mp, m_z=mz)
        x = rng.uniform(-30, 30, 50)
        y = rng.uniform(-30, 30, 50)
        z = h + rng.uniform(-3, 3, 50) * PITCH
        ex, ey, ez = grid.field(x, y, z)
        perp = x if axis == "y" else y
        eu, ew = periodic_grid_field_2d(perp - pos, z - h, PITCH, mp, mz)
        along = ey if axis == "y" else ex
        across = ex if axis == "y" else ey
        assert_allclose(across, eu, rtol=1e-12, atol=0)
        assert_allclose(ez, ew, rtol=1e-12, atol=0)
        assert np.all(along == 0.0)

    def test_cutoff_gives_exact_zeros(self):
        cutoff = 2.5
        grid = PeriodicDipoleGrid("y", PITCH, 0.0, height=10.0, m_perp=1e3, m_z=1e3,
                                  cutoff=cutoff)
        x = np.linspace(-7, 7, 15)
        for dz in (cutoff * PITCH * 1.0001, -cutoff * PITCH * 1.01, 5 * cutoff * PITCH):
            e = grid.field(x, 0.0, 10.0 + dz)
            assert all(np.all(c == 0.0) for c in e)
        inside = grid.field(x, 0.0, 10.0 + 0.9 * cutoff * PITCH)
        assert np.all(inside[0] != 0.0)

    def test_mirrored(self):
        grid = PeriodicDipoleGrid("x", PITCH, 1.0, height=2.0, m_perp=3.0, m_z=4.0,
                                  cutoff=3.0)
        img = grid.mirrored(50.0)
        assert isinstance(img, PeriodicDipoleGrid)
        assert_allclose([img.pitch, img.position, img.height, img.m_perp, img.m_z,
                         img.cutoff], [PITCH, 1.0, 98.0, -3.0, 4.0, 3.0])


# ---------------------------------------------------------------------------
# HalfPeriodicDipoleGrid
# ---------------------------------------------------------------------------

class TestHalfPeriodicDipoleGrid:
    @pytest.mark.parametrize("side", [1, -1])
    @pytest.mark.parametrize("axis", ["x", "y"])
    def test_matches_direct_sum(self, side, axis):
        # Reference: lines at position + side * m * pitch for m = 0..M summed
        # directly (no mirroring of the point: the moments are not mirror
        # symmetric), plus the half-line tail beyond (M + 1/2) pitch by quad.
        rng = np.random.default_rng(301 + side + (axis == "x"))
        pos, h = 3.0, 1.0
        mp, mz = rng.normal(size=2) * 1e3
        n = 16
        # Points on the grid side and near the edge (both sides of it).
        du = rng.uniform(-2.0, 8.0, n) * PITCH
        dw = rng.uniform(0.2, 2.0, n) * PITCH * np.where(np.arange(n) % 2, 1.0, -1.0)
        M = 200_000
        offsets = side * np.arange(M + 1) * PITCH
        uu = side * du
        eu, ew = line_sum(uu, dw, offsets, mp, mz)
        tail = half_line_tail(uu, dw, side * (M + 0.5) * PITCH, side, PITCH, mp, mz)
        ref_u, ref_w = np.array([eu, ew]) + tail

        grid = HalfPeriodicDipoleGrid(axis, PITCH, pos, side=side, height=h,
                                      m_perp=mp, m_z=mz)
        along = rng.uniform(-50, 50, n)
        if axis == "y":
            ex, ey, ez = grid.field(pos + uu, along, h + dw)
            got_u, got_s = ex, ey
        else:
            ex, ey, ez = grid.field(along, pos + uu, h + dw)
            got_u, got_s = ey, ex
        assert np.all(got_s == 0.0)
        assert_vec_close([got_u, ez], [ref_u, ref_w], rtol=1e-4)

    def test_documented_range_beyond_edge(self):
        # The docstring promises relative error < 1e-3 up to n_direct / 2
        # pitches beyond the edge (default n_direct = 64 -> 32 pitches).
        mp, mz = 0.0, 1e3
        uu = np.array([-32.0, -20.0, -5.0]) * PITCH
        dw = np.array([0.3, 0.3, 2.0]) * PITCH
        M = 200_000
        eu, ew = line_sum(uu, dw, np.arange(M + 1) * PITCH, mp, mz)
        ref = np.array([eu, ew]) + half_line_tail(uu, dw, (M + 0.5) * PITCH, 1, PITCH,
                                                  mp, mz)
        grid = HalfPeriodicDipoleGrid("y", PITCH, 0.0, side=1, m_perp=mp, m_z=mz)
        ex, _, ez = grid.field(uu, 0.0, dw)
        assert_vec_close([ex, ez], ref, rtol=1e-3)

    def test_rejects_bad_side(self):
        with pytest.raises(ValueError, match="side"):
            HalfPeriodicDipoleGrid("x", PITCH, side=0)

    def test_mirrored(self):
        g = HalfPeriodicDipoleGrid("y", PITCH, 1.0, side=-1, height=2.0, m_perp=3.0,
                                   m_z=4.0, n_direct=10)
        img = g.mirrored(50.0)
        assert isinstance(img, HalfPeriodicDipoleGrid)
        assert (img.side, img.n_direct, img.position) == (-1, 10, 1.0)
        assert_allclose([img.height, img.m_perp, img.m_z], [98.0, -3.0, 4.0])


# ---------------------------------------------------------------------------
# dipole_sheet_field_2d
# ---------------------------------------------------------------------------

class TestDipoleSheet:
    def test_matches_quad_of_line_dipoles(self):
        # Sheet over u' >= U, U - u = big_w: integrate line dipoles at offset
        # u - u' = -s for s from big_w to infinity, divided by the pitch.
        rng = np.random.default_rng(401)
        for _ in range(8):
            big_w = rng.uniform(-50, 50)
            w = rng.uniform(0.5, 20) * rng.choice([-1, 1])
            mp, mz = rng.normal(size=2) * 1e3
            ref = [integrate.quad(lambda s, k=k: line_dipole_field_2d(-s, w, mp, mz)[k],
                                  big_w, np.inf, epsabs=0, epsrel=1e-11, limit=200)[0]
                   / PITCH for k in (0, 1)]
            got = dipole_sheet_field_2d(big_w, w, PITCH, mp, mz)
            assert_vec_close(np.array(got)[:, None], np.array(ref)[:, None], rtol=1e-8)

    def test_vectorised(self):
        bw = np.linspace(-5, 5, 7)
        eu, ew = dipole_sheet_field_2d(bw, 2.0, PITCH, 1.0, 1.0)
        assert eu.shape == ew.shape == (7,)


# ---------------------------------------------------------------------------
# TruncatedLineDipole
# ---------------------------------------------------------------------------

def truncated_reference(axis, position, end, extends, height, mp, mz, point):
    """Integral over t in [0, inf) of point dipoles at end + extends * t."""
    px, py, pz = point
    if axis == "y":
        p = np.array([mp, 0.0, mz])

        def sep(t):
            return np.array([px - position, py - (end + extends * t), pz - height])
        closest = extends * (py - end)
    else:
        p = np.array([0.0, mp, mz])

        def sep(t):
            return np.array([px - (end + extends * t), py - position, pz - height])
        closest = extends * (px - end)
    breaks = sorted({0.0, max(closest, 0.0), max(closest, 0.0) + 100.0})
    out = np.zeros(3)
    for k in range(3):
        def f(t, k=k):
            return point_dipole_field(p, sep(t))[k]
        total = 0.0
        for a, b in zip(breaks[:-1], breaks[1:]):
            if b > a:
                total += integrate.quad(f, a, b, epsabs=0, epsrel=1e-12, limit=200)[0]
        total += integrate.quad(f, breaks[-1], np.inf, epsabs=0, epsrel=1e-12,
                                limit=200)[0]
        out[k] = total
    return out


class TestTruncatedLineDipole:
    @pytest.mark.parametrize("extends", [1, -1])
    @pytest.mark.parametrize("axis", ["x", "y"])
    def test_matches_integral_of_point_dipoles(self, axis, extends):
        rng = np.random.default_rng(501 + extends + 2 * (axis == "x"))
        position, end, height = 1.5, -2.0, 0.5
        mp, mz = 1.3e3, -0.8e3
        line = TruncatedLineDipole(axis, position, end, extends=extends, height=height,
                                   m_perp=mp, m_z=mz)
        for _ in range(6):
            perp = position + rng.uniform(0.5, 6.0) * rng.choice([-1, 1])
            along = end + rng.uniform(-20, 20)
            z = height + rng.uniform(0.5, 6.0) * rng.choice([-1, 1])
            pt = (perp, along, z) if axis == "y" else (along, perp, z)
            ref = truncated_reference(axis, position, end, extends, height, mp, mz, pt)
            got = np.array(line.field(*pt), float)
            assert_vec_close(got[:, None], ref[:, None], rtol=1e-8)

    @pytest.mark.parametrize("extends", [1, -1])
    @pytest.mark.parametrize("axis", ["x", "y"])
    def test_limits(self, axis, extends):
        rng = np.random.default_rng(511)
        position, end, height = 0.5, 3.0, 1.0
        mp, mz = 2e3, 1e3
        trunc = TruncatedLineDipole(axis, position, end, extends=extends, height=height,
                                    m_perp=mp, m_z=mz)
        full = LineDipole(axis, position, height=height, m_perp=mp, m_z=mz)
        perp = position + rng.uniform(-5, 5, 10)
        z = height + rng.uniform(1, 5, 10) * rng.choice([-1, 1], 10)

        def pts(along):
            return (perp, along, z) if axis == "y" else (along, perp, z)

        deep = pts(end + extends * 1e6)
        assert_vec_close(trunc.field(*deep), full.field(*deep), rtol=1e-8)
        beyond = pts(end - extends * 1e6)
        scale = np.sqrt(np.sum(np.square(full.field(*beyond)), axis=0))
        assert_vec_close(trunc.field(*beyond), np.zeros((3, 10)), rtol=0,
                         atol=1e-8 * scale.min())

    def test_half_plus_half_is_full_line(self):
        # Two truncated lines from the same end point, extending both ways.
        rng = np.random.default_rng(521)
        x, y, z = rng.uniform(-5, 5, (3, 20))
        kw = dict(height=-1.0, m_perp=1e3, m_z=-2e3)
        a = TruncatedLineDipole("x", 0.7, 0.3, extends=1, **kw)
        b = TruncatedLineDipole("x", 0.7, 0.3, extends=-1, **kw)
        full = LineDipole("x", 0.7, **kw)
        assert_vec_close(np.add(a.field(x, y, z), b.field(x, y, z)),
                         full.field(x, y, z), rtol=1e-10)

    @pytest.mark.parametrize("moment", [(1e3, 0.0), (0.0, 1e3)])
    def test_image_makes_plane_equipotential(self, moment):
        line = TruncatedLineDipole("y", 0.0, 0.0, extends=1, height=2.0,
                                   m_perp=moment[0], m_z=moment[1])
        img = line.mirrored(20.0)
        x, y = np.meshgrid(np.linspace(-30, 30, 13), np.linspace(-30, 30, 13))
        e = np.add(line.field(x, y, 20.0), img.field(x, y, 20.0))
        scale = np.abs(line.field(x, y, 20.0)).max()
        assert_allclose(e[0], 0.0, atol=1e-12 * scale)
        assert_allclose(e[1], 0.0, atol=1e-12 * scale)

    def test_on_axis_beyond_end(self):
        # Beyond the end, on the line's axis at distance a: every dipole is
        # perpendicular to the separation, E = -C xi / t^3 integrated from a to
        # infinity, i.e. E = -C xi / (2 a^2).
        a = 5.0
        mp, mz = 1e3, -2e3
        line = TruncatedLineDipole("y", 0.0, 0.0, extends=1, m_perp=mp, m_z=mz)
        got = np.array(line.field(0.0, -a, 0.0), float)
        ref = -COULOMB_UM * np.array([mp, 0.0, mz]) / (2 * a * a)
        assert_vec_close(got[:, None], ref[:, None], rtol=1e-10)

    def test_near_axis_beyond_end(self):
        a, rp = 5.0, 1e-6
        mp, mz = 1e3, -2e3
        line = TruncatedLineDipole("y", 0.0, 0.0, extends=1, m_perp=mp, m_z=mz)
        got = np.array(line.field(rp, -a, 0.0), float)
        # Leading order in r_perp / a of the same integral as above.
        ref = -COULOMB_UM * np.array([mp, 0.0, mz]) / (2 * a * a)
        assert_vec_close(got[:, None], ref[:, None], rtol=1e-6)

    def test_rejects_bad_extends(self):
        with pytest.raises(ValueError, match="extends"):
            TruncatedLineDipole("x", 0.0, 0.0, extends=0)


# ---------------------------------------------------------------------------
# PointDipoles
# ---------------------------------------------------------------------------

class TestPointDipoles:
    def test_single_dipole_direct_formula(self):
        rng = np.random.default_rng(601)
        x0, y0, h, pz = 1.0, -2.0, 3.0, -2.0e5
        pts = rng.uniform(-20, 20, (40, 3))
        got = PointDipoles(x0, y0, pz, height=h).field(pts[:, 0], pts[:, 1], pts[:, 2])
        ref = point_dipole_field([0, 0, pz], pts - [x0, y0, h]).T
        assert_allclose(got, ref, rtol=1e-12)

    def test_superposition_and_chunking(self):
        rng = np.random.default_rng(602)
        xs, ys = rng.uniform(-10, 10, (2, 7))
        ps = rng.normal(size=7) * 1e4
        pts = rng.uniform(-15, 15, (3, 5, 4))
        many = PointDipoles(xs, ys, ps, height=1.0, chunk=3).field(*pts)
        singles = sum(np.array(PointDipoles(a, b, c, height=1.0).field(*pts))
                      for a, b, c in zip(xs, ys, ps))
        assert np.shape(many) == (3, 5, 4)
        assert_allclose(many, singles, rtol=1e-10, atol=1e-14 * np.abs(singles).max())

    def test_mirrored_keeps_moment(self):
        d = PointDipoles([1.0, 2.0], [3.0, 4.0], [-5.0, 6.0], height=1.0, chunk=7)
        img = d.mirrored(100.0)
        assert_allclose(img.p_z, d.p_z)
        assert_allclose([img.x, img.y], [d.x, d.y])
        assert img.height == 199.0
        # Dipole + image: the mirror plane is an equipotential.
        x, y = np.meshgrid(np.linspace(-200, 200, 9), np.linspace(-200, 200, 9))
        e = np.add(d.field(x, y, 100.0), img.field(x, y, 100.0))
        scale = np.abs(d.field(x, y, 100.0)).max()
        assert_allclose(e[:2], 0.0, atol=1e-12 * scale)

    def test_far_field_of_charge_and_image(self):
        # Collected charge -Q at depth d plus image +Q at -d: p_z = -2 Q d.
        rng = np.random.default_rng(603)
        Q, d = 1.0e4, 2.0
        x0, y0 = 3.0, -1.0
        v = rng.normal(size=(200, 3))
        r = 50 * d * v / np.linalg.norm(v, axis=1)[:, None] + [x0, y0, 0.0]
        ref = (point_charge_field(-Q, [x0, y0, d], r)
               + point_charge_field(Q, [x0, y0, -d], r)).T
        got = PointDipoles(x0, y0, -2 * Q * d).field(r[:, 0], r[:, 1], r[:, 2])
        assert_vec_close(got, ref, rtol=1e-3)

    def test_bad_input(self):
        with pytest.raises(ValueError, match="same length"):
            PointDipoles([0.0, 1.0], [0.0], [1.0, 1.0])
        with pytest.raises(ValueError, match="finite"):
            PointDipoles([np.nan], [0.0], [1.0])


# ---------------------------------------------------------------------------
# Backdrop fields
# ---------------------------------------------------------------------------

class TestBackdropField:
    V_BSS, N_A, T = -50.0, 1.0e12, 100.0

    def test_linear_with_space_charge_slope(self):
        bd = BackdropField(self.V_BSS, self.N_A, self.T, front_potential=2.0)
        z = np.linspace(0, self.T, 11)
        ex, ey, ez = bd.field(0.3, -0.2, z)
        assert np.all(ex == 0) and np.all(ey == 0)
        slope = -SPACE_CHARGE_UM * self.N_A
        assert_allclose(np.diff(ez) / np.diff(z), slope, rtol=1e-9)
        assert np.all(ez > 0)

    def test_gauss_law_mean_field(self):
        # Integral of E_z over the bulk is the potential drop V_front - V_BSS.
        for front in (0.0, 3.0):
            bd = BackdropField(self.V_BSS, self.N_A, self.T, front_potential=front)
            integral = integrate.quad(lambda z: float(bd.field(0.0, 0.0, z)[2]),
                                      0.0, self.T, epsabs=0, epsrel=1e-12)[0]
            assert_allclose(integral / self.T, (front - self.V_BSS) / self.T, rtol=1e-10)

    def test_broadcast_shape(self):
        bd = BackdropField(self.V_BSS, self.N_A, self.T)
        e = bd.field(np.zeros((2, 1)), np.zeros(3), 5.0)
        assert all(c.shape == (2, 3) for c in e)

    def test_not_fully_depleted(self):
        # E_z(t) = dV / t - q N_a t / (2 eps) <= 0 for N_a >= 2 dV / (t^2 q / eps).
        n_crit = 2 * 50.0 / (self.T**2 * SPACE_CHARGE_UM)
        BackdropField(self.V_BSS, 0.99 * n_crit, self.T)
        with pytest.raises(ValueError, match="not fully depleted"):
            BackdropField(self.V_BSS, 1.01 * n_crit, self.T)

    def test_bad_parameters(self):
        with pytest.raises(ValueError, match="thickness must be positive"):
            BackdropField(self.V_BSS, self.N_A, -100.0)
        with pytest.raises(ValueError, match="finite"):
            BackdropField(np.nan, self.N_A, self.T)
        with pytest.raises(ValueError, match="finite"):
            BackdropField(self.V_BSS, self.N_A, np.nan)
        with pytest.raises(ValueError, match="acceptor_density"):
            BackdropField(self.V_BSS, -1.0, self.T)


class TestTabulatedBackdrop:
    def test_interpolates(self):
        z = np.array([0.0, 10.0, 40.0, 100.0])
        ez = np.array([1.0, 0.8, 0.6, 0.1])
        bd = TabulatedBackdrop(z, ez)
        zq = np.array([0.0, 5.0, 25.0, 70.0, 100.0])
        ref = np.array([1.0, 0.9, 0.7, 0.35, 0.1])
        ex, ey, got = bd.field(1.0, 2.0, zq)
        assert_allclose(got, ref, rtol=1e-12)
        assert np.all(ex == 0) and np.all(ey == 0)

    def test_rejects_bad_tables(self):
        with pytest.raises(ValueError, match="strictly increasing"):
            TabulatedBackdrop([0.0, 2.0, 2.0], [1.0, 1.0, 1.0])
        with pytest.raises(ValueError, match="strictly increasing"):
            TabulatedBackdrop([0.0, 3.0, 2.0], [1.0, 1.0, 1.0])
        with pytest.raises(ValueError, match="positive"):
            TabulatedBackdrop([0.0, 1.0, 2.0], [1.0, 0.0, 1.0])
        with pytest.raises(ValueError, match="positive"):
            TabulatedBackdrop([0.0, 1.0, 2.0], [1.0, -0.5, 1.0])
        with pytest.raises(ValueError, match="finite"):
            TabulatedBackdrop([0.0, np.nan], [1.0, 1.0])
        with pytest.raises(ValueError, match="equal length"):
            TabulatedBackdrop([0.0, 1.0, 2.0], [1.0, 1.0])


# ---------------------------------------------------------------------------
# Bad input shared by the line terms
# ---------------------------------------------------------------------------

_LINE_FACTORIES = {
    "LineDipole": lambda axis, pos: LineDipole(axis, pos, m_z=1.0),
    "PeriodicDipoleGrid": lambda axis, pos: PeriodicDipoleGrid(axis, PITCH, pos, m_z=1.0),
    "HalfPeriodicDipoleGrid": lambda axis, pos: HalfPeriodicDipoleGrid(axis, PITCH, pos,
                                                                       m_z=1.0),
    "TruncatedLineDipole": lambda axis, pos: TruncatedLineDipole(axis, pos, 0.0, m_z=1.0),
}


@pytest.mark.parametrize("name", sorted(_LINE_FACTORIES))
class TestBadInput:
    def test_axis_z(self, name):
        with pytest.raises(ValueError, match="axis"):
            _LINE_FACTORIES[name]("z", 0.0)

    def test_nan_position(self, name):
        with pytest.raises(ValueError, match="finite"):
            _LINE_FACTORIES[name]("x", np.nan)


@pytest.mark.parametrize("cls", [PeriodicDipoleGrid, HalfPeriodicDipoleGrid])
@pytest.mark.parametrize("pitch", [0.0, -1.0])
def test_nonpositive_pitch(cls, pitch):
    with pytest.raises(ValueError, match="pitch must be positive"):
        cls("x", pitch)


def test_nan_moment_rejected():
    with pytest.raises(ValueError, match="finite"):
        LineDipole("x", 0.0, m_perp=np.nan)
    with pytest.raises(ValueError, match="finite"):
        TruncatedLineDipole("y", 0.0, np.inf)
