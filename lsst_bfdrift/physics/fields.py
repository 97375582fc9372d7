"""Electrostatic field terms of the drift model (Rasmussen 2015, sections 2-3).

Every term is a small class with one vectorised method,
``field(x, y, z) -> (ex, ey, ez)``, that broadcasts over arrays of points.
Units (see :mod:`lsst_bfdrift.physics.constants`): positions in um, fields in V/um,
line-dipole moments per unit length in e, point-dipole moments in e um.

Frame: z = 0 is the gate plane (front side), z = ``thickness`` the backside
entrance window. x is the serial axis, y the parallel axis. Electrons drift
along -E, so the backdrop field points to +z.

Line dipoles are straight lines parallel to the x or y axis lying in a plane
z = const. Their moment per unit length is perpendicular to the line and is
given by two components: ``m_perp`` along the in-plane perpendicular
direction (+y for a line along x, +x for a line along y) and ``m_z`` along +z.
"""

import numpy as np

from lsst_bfdrift.physics.constants import COULOMB_UM, SPACE_CHARGE_UM
from lsst_bfdrift.utils.errors import InputError

__all__ = [
    "FieldTerm",
    "BackdropField",
    "TabulatedBackdrop",
    "LineDipole",
    "PeriodicDipoleGrid",
    "HalfPeriodicDipoleGrid",
    "TruncatedLineDipole",
    "PointDipoles",
    "line_dipole_field_2d",
    "periodic_grid_field_2d",
    "dipole_sheet_field_2d",
]

_AXES = ("x", "y")


def _check_axis(axis):
    if axis not in _AXES:
        raise InputError(f"axis must be 'x' or 'y', got {axis!r}")
    return axis


def _check_finite(name, value):
    arr = np.asarray(value, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite, got {value!r}")
    return arr


def line_dipole_field_2d(u, w, m_perp, m_z):
    """In-plane field of an infinite line dipole at the origin.

    Implements E = (1 / 2 pi eps) (2 (xi . r_hat) r_hat - xi) / r^2.

    Parameters
    ----------
    u, w : array_like
        Perpendicular offsets of the field points from the line (um): ``u``
        in the plane of the line, ``w`` along z.
    m_perp, m_z : float
        Moment per unit length (e) along ``u`` and ``w``.

    Returns
    -------
    eu, ew : ndarray
        Field components (V/um) along ``u`` and ``w``.
    """
    r2 = u * u + w * w
    dot = (m_perp * u + m_z * w) / r2
    scale = 2.0 * COULOMB_UM / r2
    return scale * (2.0 * dot * u - m_perp), scale * (2.0 * dot * w - m_z)


def periodic_grid_field_2d(u, w, pitch, m_perp, m_z):
    """Field of an infinite periodic grid of parallel line dipoles.

    The closed form of Rasmussen 2015 eq. (3.4) with a = 2 pi u / p and
    b = 2 pi w / p (the paper's ``|e_perp|`` is read as ``r . e_perp``). The
    grid has one line at u = 0 and one every ``pitch`` along u.

    Parameters
    ----------
    u, w : array_like
        Offsets of the field points (um) from one line of the grid.
    pitch : float
        Grid spacing (um).
    m_perp, m_z : float
        Moment per unit length (e) of every line, along u and w.

    Returns
    -------
    eu, ew : ndarray
        Field components (V/um).
    """
    k = 2.0 * np.pi / pitch
    a = k * u
    b = k * w
    # Far from the plane the grid field decays like exp(-|b|): evaluate with
    # exp(-|b|) so that cosh/sinh never overflow.
    absb = np.abs(b)
    q = np.exp(-absb)
    ca, sa = np.cos(a), np.sin(a)
    # cosh b = (1 + q^2) / (2 q), sinh b = sign(b) (1 - q^2) / (2 q)
    # Multiply numerator and denominator by (2 q)^2 to stay finite.
    den = (2.0 * q * ca - (1.0 + q * q)) ** 2
    f1 = (4.0 * q * q - 2.0 * q * ca * (1.0 + q * q)) / den
    f2 = 2.0 * q * sa * np.sign(b) * (1.0 - q * q) / den
    pref = 2.0 * COULOMB_UM * 2.0 * np.pi**2 / pitch**2
    eu = pref * (f1 * m_perp + f2 * m_z)
    ew = pref * (-f1 * m_z + f2 * m_perp)
    return eu, ew


def dipole_sheet_field_2d(big_w, w, pitch, m_perp, m_z):
    """Field of a semi-infinite sheet of line dipoles (continuum limit).

    Lines of moment (m_perp, m_z) per unit length, ``1 / pitch`` per unit
    length along u, filling u' >= U. This is the integral of
    :func:`line_dipole_field_2d` over the half line, used for the far tail of
    a truncated grid.

    Parameters
    ----------
    big_w : array_like
        ``U - u`` (um): position of the start of the sheet relative to the
        field points.
    w : array_like
        Offset of the field points along z from the plane of the sheet (um).
    pitch : float
        Line spacing (um).
    m_perp, m_z : float
        Moment per unit length (e) of each line.

    Returns
    -------
    eu, ew : ndarray
        Field components (V/um).
    """
    r2 = big_w * big_w + w * w
    pref = 2.0 * COULOMB_UM / pitch / r2
    return pref * (m_perp * big_w - m_z * w), -pref * (m_perp * w + m_z * big_w)


class FieldTerm:
    """Base class of field terms: a vectorised ``field(x, y, z)``."""

    def field(self, x, y, z):  # pragma: no cover - abstract
        """Field (ex, ey, ez) in V/um at points (x, y, z) in um."""
        raise NotImplementedError

    def mirrored(self, z_plane):
        """Image of this term across the equipotential plane z = ``z_plane``.

        A dipole xi maps to xi' = 2 (xi . k) k - xi at the mirrored position
        (Rasmussen 2015, eq. 3.2).
        """
        raise NotImplementedError(f"{type(self).__name__} has no image")


class BackdropField(FieldTerm):
    """One-dimensional backdrop field of a fully depleted p-type bulk.

    E_z(z) = dV / t + (q N_a / eps)(t / 2 - z), with dV = V_front - V_BSS the
    potential drop across the bulk: linear in z, strongest at the front.

    Parameters
    ----------
    v_bss : float
        Backside bias (V), negative for LSST sensors (e.g. -50).
    acceptor_density : float
        Acceptor density N_a of the bulk (cm^-3).
    thickness : float
        Silicon thickness (um).
    front_potential : float, optional
        Effective potential of the front (gate) plane (V).
    """

    def __init__(self, v_bss, acceptor_density, thickness, *, front_potential=0.0):
        self.v_bss = float(_check_finite("v_bss", v_bss))
        self.acceptor_density = float(_check_finite("acceptor_density", acceptor_density))
        self.thickness = float(_check_finite("thickness", thickness))
        self.front_potential = float(_check_finite("front_potential", front_potential))
        if self.thickness <= 0:
            raise InputError(f"thickness must be positive, got {self.thickness}")
        if self.acceptor_density < 0:
            raise InputError(
                f"acceptor_density must be >= 0 cm^-3, got {self.acceptor_density}")
        self.gradient = SPACE_CHARGE_UM * self.acceptor_density  # V/um^2
        self.mean_field = (self.front_potential - self.v_bss) / self.thickness
        if self.ez(self.thickness) <= 0:
            raise InputError(
                "backdrop field does not reach the backside: E_z(t) = "
                f"{self.ez(self.thickness):.4g} V/um <= 0 (bulk not fully depleted; "
                "raise |v_bss| or lower acceptor_density)")

    def ez(self, z):
        """E_z(z) in V/um."""
        return self.mean_field + self.gradient * (0.5 * self.thickness - np.asarray(z))

    def field(self, x, y, z):
        ez = self.ez(z)
        zero = np.zeros(np.broadcast(x, y, z).shape)
        return zero, zero.copy(), ez + zero


class TabulatedBackdrop(FieldTerm):
    """Backdrop field interpolated from a tabulated profile E_z(z).

    Parameters
    ----------
    z : array_like
        Increasing heights (um).
    ez : array_like
        E_z at those heights (V/um); must be positive (fully depleted).
    """

    def __init__(self, z, ez):
        self.z = _check_finite("z", z)
        self.ez_table = _check_finite("ez", ez)
        if self.z.ndim != 1 or self.z.shape != self.ez_table.shape or self.z.size < 2:
            raise InputError("z and ez must be 1-d arrays of equal length >= 2")
        if np.any(np.diff(self.z) <= 0):
            raise InputError("z must be strictly increasing")
        if np.any(self.ez_table <= 0):
            raise InputError("tabulated backdrop E_z must be positive everywhere")

    def field(self, x, y, z):
        ez = np.interp(z, self.z, self.ez_table)
        zero = np.zeros(np.broadcast(x, y, z).shape)
        return zero, zero.copy(), ez + zero


class _AxisLine(FieldTerm):
    """Shared bookkeeping of terms built from lines along x or y."""

    def __init__(self, axis, position, height, m_perp, m_z):
        self.axis = _check_axis(axis)
        self.position = float(_check_finite("position", position))
        self.height = float(_check_finite("height", height))
        self.m_perp = float(_check_finite("m_perp", m_perp))
        self.m_z = float(_check_finite("m_z", m_z))

    def _perp(self, x, y, z):
        u = (np.asarray(x) if self.axis == "y" else np.asarray(y)) - self.position
        return u, np.asarray(z) - self.height

    def _assemble(self, x, y, z, eu, ew, es=None):
        zero = np.zeros(np.broadcast(x, y, z).shape)
        eu = eu + zero
        ew = ew + zero
        es = zero if es is None else es + zero
        if self.axis == "y":
            return eu, es, ew
        return es, eu, ew

    def _mirror_args(self, z_plane):
        # xi' = 2 (xi . k) k - xi: the z component is kept, in-plane flips.
        return dict(height=2.0 * z_plane - self.height, m_perp=-self.m_perp, m_z=self.m_z)


class LineDipole(_AxisLine):
    """Infinite line dipole parallel to ``axis``.

    Parameters
    ----------
    axis : {'x', 'y'}
        Direction of the line.
    position : float
        Its coordinate along the in-plane perpendicular axis (um): x for a
        line along y, y for a line along x.
    height : float
        Its z (um).
    m_perp, m_z : float
        Moment per unit length (e).
    """

    def __init__(self, axis, position, *, height=0.0, m_perp=0.0, m_z=0.0):
        super().__init__(axis, position, height, m_perp, m_z)

    def field(self, x, y, z):
        u, w = self._perp(x, y, z)
        eu, ew = line_dipole_field_2d(u, w, self.m_perp, self.m_z)
        return self._assemble(x, y, z, eu, ew)

    def mirrored(self, z_plane):
        return LineDipole(self.axis, self.position, **self._mirror_args(z_plane))


class PeriodicDipoleGrid(_AxisLine):
    """Infinite periodic grid of line dipoles (Rasmussen 2015, eq. 3.4).

    Lines parallel to ``axis`` at ``position + m * pitch`` for every integer m.

    Parameters
    ----------
    axis : {'x', 'y'}
        Direction of the lines.
    pitch : float
        Spacing (um).
    position : float
        Perpendicular coordinate of one line (um).
    height : float
        z of the grid plane (um).
    m_perp, m_z : float
        Moment per unit length of each line (e).
    cutoff : float, optional
        Beyond ``|z - height| > cutoff * pitch`` the field, which decays as
        ``exp(-2 pi |z - height| / pitch)``, is not evaluated (set to 0).
    """

    def __init__(self, axis, pitch, position=0.0, *, height=0.0, m_perp=0.0, m_z=0.0,
                 cutoff=6.0):
        super().__init__(axis, position, height, m_perp, m_z)
        self.pitch = float(_check_finite("pitch", pitch))
        if self.pitch <= 0:
            raise InputError(f"pitch must be positive, got {self.pitch}")
        self.cutoff = float(cutoff)

    def field(self, x, y, z):
        u, w = self._perp(x, y, z)
        u, w = np.broadcast_arrays(u, w)
        eu = np.zeros(u.shape)
        ew = np.zeros(u.shape)
        near = np.abs(w) < self.cutoff * self.pitch
        if np.any(near):
            eu[near], ew[near] = periodic_grid_field_2d(
                u[near], w[near], self.pitch, self.m_perp, self.m_z)
        return self._assemble(x, y, z, eu, ew)

    def mirrored(self, z_plane):
        return PeriodicDipoleGrid(self.axis, self.pitch, self.position,
                                  cutoff=self.cutoff, **self._mirror_args(z_plane))


class HalfPeriodicDipoleGrid(_AxisLine):
    """Periodic grid of line dipoles that stops at an edge.

    Lines at ``position + m * pitch`` for m >= 0 (``side=+1``) or m <= 0
    (``side=-1``). Evaluated as the full closed-form grid minus the missing
    lines: the first ``n_direct`` missing lines are summed directly, the rest
    as a continuous dipole sheet (midpoint rule). Valid where the silicon is:
    on the grid side of the edge and up to about ``n_direct / 2`` pitches
    beyond it (relative error < 1e-3 there, ~1e-6 on the grid side); further
    beyond the edge the field point enters the smeared sheet and the result is
    meaningless.

    Parameters
    ----------
    axis : {'x', 'y'}
        Direction of the lines.
    pitch : float
        Spacing (um).
    position : float
        Perpendicular coordinate of the last line before the edge (um).
    side : {+1, -1}
        Side of ``position`` on which the grid continues.
    height, m_perp, m_z : float
        As for :class:`PeriodicDipoleGrid`.
    n_direct : int, optional
        Number of missing lines summed directly.
    """

    def __init__(self, axis, pitch, position=0.0, *, side=1, height=0.0, m_perp=0.0,
                 m_z=0.0, n_direct=64):
        super().__init__(axis, position, height, m_perp, m_z)
        if side not in (1, -1):
            raise InputError(f"side must be +1 or -1, got {side!r}")
        self.side = int(side)
        self.pitch = float(_check_finite("pitch", pitch))
        if self.pitch <= 0:
            raise InputError(f"pitch must be positive, got {self.pitch}")
        self.n_direct = int(n_direct)
        self._full = PeriodicDipoleGrid(axis, self.pitch, self.position, height=self.height,
                                        m_perp=self.m_perp, m_z=self.m_z, cutoff=np.inf)

    def field(self, x, y, z):
        u, w = self._perp(x, y, z)
        u, w = np.broadcast_arrays(u, w)
        eu, ew = periodic_grid_field_2d(u, w, self.pitch, self.m_perp, self.m_z)
        s = self.side
        for m in range(1, self.n_direct + 1):
            du, dw = line_dipole_field_2d(u + s * m * self.pitch, w, self.m_perp, self.m_z)
            eu = eu - du
            ew = ew - dw
        # Missing sheet: lines at -s*m*pitch for m > n_direct, i.e. the half
        # line beyond start = -s (n_direct + 1/2) pitch, away from the grid.
        start = -s * (self.n_direct + 0.5) * self.pitch
        if s == 1:
            # sheet over u' <= start  =  -(sheet over u' >= start)
            su, sw = dipole_sheet_field_2d(start - u, w, self.pitch, self.m_perp, self.m_z)
            eu, ew = eu + su, ew + sw
        else:
            su, sw = dipole_sheet_field_2d(start - u, w, self.pitch, self.m_perp, self.m_z)
            eu, ew = eu - su, ew - sw
        return self._assemble(x, y, z, eu, ew)

    def mirrored(self, z_plane):
        return HalfPeriodicDipoleGrid(self.axis, self.pitch, self.position, side=self.side,
                                      n_direct=self.n_direct, **self._mirror_args(z_plane))


class TruncatedLineDipole(_AxisLine):
    """Semi-infinite line dipole (Rasmussen 2015, eq. 3.10).

    The line runs parallel to ``axis`` from the truncation point ``end``
    (coordinate along the axis, um) towards ``extends`` (+1: increasing
    coordinate, -1: decreasing). With s the unit vector from the truncation
    point away from the dipoles and c = cos(theta0) = s . r_hat::

        4 pi eps r_perp^2 E = (2 - 3 c + c^3)(xi . r_perp_hat) r_perp_hat
                              + sin^3(theta0) (xi . r_perp_hat) s - (1 - c) xi.

    It is evaluated with (1 - c) / r_perp^2 in a cancellation-free form, so the
    field is finite on the axis beyond the truncation point.

    Parameters
    ----------
    axis : {'x', 'y'}
        Direction of the line.
    position : float
        Perpendicular in-plane coordinate (um).
    end : float
        Coordinate of the truncation point along the axis (um).
    extends : {+1, -1}
        Direction in which the dipoles extend from ``end``.
    height, m_perp, m_z : float
        As for :class:`LineDipole`.
    """

    def __init__(self, axis, position, end, *, extends=1, height=0.0, m_perp=0.0, m_z=0.0):
        super().__init__(axis, position, height, m_perp, m_z)
        if extends not in (1, -1):
            raise InputError(f"extends must be +1 or -1, got {extends!r}")
        self.extends = int(extends)
        self.end = float(_check_finite("end", end))

    def field(self, x, y, z):
        u, w = self._perp(x, y, z)
        along = (np.asarray(y) if self.axis == "y" else np.asarray(x)) - self.end
        sdir = -self.extends  # s points away from the dipoles
        u, w, along = np.broadcast_arrays(u, w, along)
        rp2 = u * u + w * w
        r = np.sqrt(rp2 + along * along)
        c = sdir * along / r
        # g = (1 - c) / r_perp^2 without cancellation: beyond the end (c > 0)
        # 1 - c = r_perp^2 / (r (r + |along|)), finite on the axis itself.
        with np.errstate(divide="ignore", invalid="ignore"):
            g = np.where(c > 0, 1.0 / (r * (r + np.abs(along))), (1.0 - c) / rp2)
        dot = self.m_perp * u + self.m_z * w  # xi . r_perp
        # (2 - 3c + c^3) = (1 - c)^2 (2 + c)
        f_r = g * g * (2.0 + c) * dot
        eu = COULOMB_UM * (f_r * u - g * self.m_perp)
        ew = COULOMB_UM * (f_r * w - g * self.m_z)
        es = COULOMB_UM * dot * sdir / r**3
        return self._assemble(x, y, z, eu, ew, es)

    def mirrored(self, z_plane):
        return TruncatedLineDipole(self.axis, self.position, self.end, extends=self.extends,
                                   **self._mirror_args(z_plane))


class PointDipoles(FieldTerm):
    """Point dipoles along z, e.g. collected charge and its gate-plane image.

    E = (1 / 4 pi eps)(3 (p . r_hat) r_hat - p) / r^3 for each dipole
    p = p_z k at (x_i, y_i, height).

    Parameters
    ----------
    x, y : array_like
        Dipole positions (um).
    p_z : array_like
        z components of the moments (e um); collected electrons Q at channel
        depth d give p_z = -2 Q d.
    height : float, optional
        z of the dipoles (um).
    chunk : int, optional
        Number of dipoles summed at once (memory bound).
    """

    def __init__(self, x, y, p_z, *, height=0.0, chunk=256):
        self.x = np.atleast_1d(_check_finite("x", x)).ravel()
        self.y = np.atleast_1d(_check_finite("y", y)).ravel()
        self.p_z = np.atleast_1d(_check_finite("p_z", p_z)).ravel()
        if not (self.x.shape == self.y.shape == self.p_z.shape):
            raise InputError("x, y and p_z must have the same length")
        self.height = float(_check_finite("height", height))
        self.chunk = int(chunk)

    def field(self, x, y, z):
        x, y, z = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float),
                                      np.asarray(z, float))
        shape = x.shape
        xf, yf, zf = x.ravel(), y.ravel(), z.ravel() - self.height
        ex = np.zeros(xf.size)
        ey = np.zeros(xf.size)
        ez = np.zeros(xf.size)
        for s in range(0, self.x.size, self.chunk):
            px = self.x[s:s + self.chunk, None]
            py = self.y[s:s + self.chunk, None]
            pz = self.p_z[s:s + self.chunk, None]
            dx = xf[None, :] - px
            dy = yf[None, :] - py
            r2 = dx * dx + dy * dy + zf[None, :] ** 2
            inv_r5 = r2 ** -2.5
            pdotr = pz * zf[None, :]
            ex += (3.0 * pdotr * dx * inv_r5).sum(axis=0)
            ey += (3.0 * pdotr * dy * inv_r5).sum(axis=0)
            ez += (3.0 * pdotr * zf[None, :] * inv_r5 - pz * r2 * inv_r5).sum(axis=0)
        k = COULOMB_UM
        return (k * ex).reshape(shape), (k * ey).reshape(shape), (k * ez).reshape(shape)

    def mirrored(self, z_plane):
        # z dipoles keep their moment in a mirror image across a plane.
        return PointDipoles(self.x, self.y, self.p_z, height=2.0 * z_plane - self.height,
                            chunk=self.chunk)
