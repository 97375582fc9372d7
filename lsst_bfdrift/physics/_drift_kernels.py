"""Compiled (numba) field and drift-line integrator of
:func:`lsst_bfdrift.physics.drift.drift_lines`.

The same algorithm as :mod:`lsst_bfdrift.physics.fields` and
:mod:`lsst_bfdrift.physics.drift`, which remain the references the tests
compare against.
"""

import numba
import numpy as np

__all__ = ["drift_batch", "bisect_batch"]


# ---------------------------------------------------------------------------
# Compiled field and drift (same algorithm as lsst_bfdrift.physics.fields / drift)
# ---------------------------------------------------------------------------
# Line-type terms are rows of a float array ``lines``:
#   [kind, axis, pitch, position, height, m_perp, m_z, extra1, extra2, extra3]
# kind 0 line dipole, 1 periodic grid (extra1 = cutoff), 2 half periodic grid
# (extra1 = side, extra2 = n_direct), 3 truncated line (extra1 = end,
# extra2 = extends); axis 0 = lines along x, 1 = along y.
# Backdrop: bd_kind 0 linear (bd = [mean_field, gradient, thickness]),
# 1 tabulated (bd_z, bd_ez).

@numba.njit(cache=True, inline="always")
def _line2d(u, w, mp, mz, c2):
    r2 = u * u + w * w
    dot = (mp * u + mz * w) / r2
    sc = c2 / r2
    return sc * (2.0 * dot * u - mp), sc * (2.0 * dot * w - mz)


@numba.njit(cache=True)
def _periodic2d(u, w, pitch, mp, mz, c2):
    k = 2.0 * np.pi / pitch
    a = k * u
    b = k * w
    q = np.exp(-abs(b))
    ca = np.cos(a)
    sa = np.sin(a)
    den = (2.0 * q * ca - (1.0 + q * q)) ** 2
    f1 = (4.0 * q * q - 2.0 * q * ca * (1.0 + q * q)) / den
    sb = 1.0 if b > 0 else (-1.0 if b < 0 else 0.0)
    f2 = 2.0 * q * sa * sb * (1.0 - q * q) / den
    pref = c2 * 2.0 * np.pi * np.pi / (pitch * pitch)
    return pref * (f1 * mp + f2 * mz), pref * (-f1 * mz + f2 * mp)


@numba.njit(cache=True)
def _field(x, y, z, lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c):
    c2 = 2.0 * c
    ex = 0.0
    ey = 0.0
    if bd_kind == 0:
        ez = bd[0] + bd[1] * (0.5 * bd[2] - z)
    else:
        ez = np.interp(z, bd_z, bd_ez)
    for r in range(lines.shape[0]):
        kind = int(lines[r, 0])
        axis = int(lines[r, 1])
        pitch = lines[r, 2]
        u = (x if axis == 1 else y) - lines[r, 3]
        along = y if axis == 1 else x
        w = z - lines[r, 4]
        mp = lines[r, 5]
        mz = lines[r, 6]
        eu = 0.0
        ew = 0.0
        es = 0.0
        if kind == 0:
            eu, ew = _line2d(u, w, mp, mz, c2)
        elif kind == 1:
            if abs(w) < lines[r, 7] * pitch:
                eu, ew = _periodic2d(u, w, pitch, mp, mz, c2)
        elif kind == 2:
            side = lines[r, 7]
            nd = int(lines[r, 8])
            eu, ew = _periodic2d(u, w, pitch, mp, mz, c2)
            for m in range(1, nd + 1):
                du, dw = _line2d(u + side * m * pitch, w, mp, mz, c2)
                eu -= du
                ew -= dw
            start = -side * (nd + 0.5) * pitch
            bw = start - u
            r2 = bw * bw + w * w
            pref = c2 / pitch / r2
            su = pref * (mp * bw - mz * w)
            sw = -pref * (mp * w + mz * bw)
            if side > 0:
                eu += su
                ew += sw
            else:
                eu -= su
                ew -= sw
        else:
            sdir = -lines[r, 8]
            al = along - lines[r, 7]
            rp2 = u * u + w * w
            rr = np.sqrt(rp2 + al * al)
            cc = sdir * al / rr
            if cc > 0:
                g = 1.0 / (rr * (rr + abs(al)))
            else:
                g = (1.0 - cc) / rp2
            dot = mp * u + mz * w
            f_r = g * g * (2.0 + cc) * dot
            eu = c * (f_r * u - g * mp)
            ew = c * (f_r * w - g * mz)
            es = c * dot * sdir / rr ** 3
        if axis == 1:
            ex += eu
            ey += es
        else:
            ey += eu
            ex += es
        ez += ew
    for d in range(px.shape[0]):
        dx = x - px[d]
        dy = y - py[d]
        dz = z - ph[d]
        r2 = dx * dx + dy * dy + dz * dz
        inv5 = r2 ** -2.5
        pdr = pz[d] * dz
        ex += c * 3.0 * pdr * dx * inv5
        ey += c * 3.0 * pdr * dy * inv5
        ez += c * (3.0 * pdr * dz * inv5 - pz[d] * r2 * inv5)
    return ex, ey, ez


@numba.njit(cache=True, inline="always")
def _dir(x, y, z, lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c):
    ex, ey, ez = _field(x, y, z, lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c)
    n = np.sqrt(ex * ex + ey * ey + ez * ez) + 1e-300
    return -ex / n, -ey / n, -ez / n, n


@numba.njit(cache=True, inline="always")
def _trace(x, y, z, z_stop, step_scale, min_step, max_step, max_steps, cos_max,
           lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c):
    """One drift line from (x, y, z) down to ``z_stop``: (x, y, z, steps, finished, stalled)."""
    steps = 0
    fin = z <= z_stop
    stall = False
    idle = 0
    h = min(max(step_scale * (z - z_stop) + min_step, min_step), max_step)
    while not fin and steps < max_steps:
        steps += 1
        a1, b1, c1, n1 = _dir(x, y, z, lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c)
        a2, b2, c2_, n2 = _dir(x + 0.5 * h * a1, y + 0.5 * h * b1, z + 0.5 * h * c1, lines,
                               bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c)
        a3, b3, c3, n3 = _dir(x + 0.5 * h * a2, y + 0.5 * h * b2, z + 0.5 * h * c2_, lines,
                              bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c)
        a4, b4, c4, n4 = _dir(x + h * a3, y + h * b3, z + h * c3, lines,
                              bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c)
        turn_ok = (a1 * a4 + b1 * b4 + c1 * c4 >= cos_max) or (h <= 1e-7)
        null = n1 < 1e-12 * (1.0 + abs(n4))
        nx = x + h / 6.0 * (a1 + 2 * a2 + 2 * a3 + a4)
        ny = y + h / 6.0 * (b1 + 2 * b2 + 2 * b3 + b4)
        nz = z + h / 6.0 * (c1 + 2 * c2_ + 2 * c3 + c4)
        descending = turn_ok and (nz < z - 1e-6 * h)
        idle = 0 if descending else idle + 1
        stuck = null or idle > 40
        done = turn_ok and nz <= z_stop
        if done:
            f = (z - z_stop) / (z - nz)
            nx = x + f * (nx - x)
            ny = y + f * (ny - y)
            nz = z_stop
        if turn_ok:
            hb = min(max(step_scale * (nz - z_stop) + min_step, min_step), max_step)
            x, y, z = nx, ny, nz
            h = min(hb, 2.0 * h)
        else:
            h = 0.25 * h
        if stuck and not done:
            stall = True
        if done or stuck:
            fin = True
    return x, y, z, steps, fin, stall


@numba.njit(parallel=True, cache=True)
def drift_batch(x0, y0, z0, z_stop, step_scale, min_step, max_step, max_steps, cos_max,
                lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph, c,
                ox, oy, oz, osteps, ofin, ostall):
    """Integrate drift lines one by one (in parallel); see lsst_bfdrift.physics.drift."""
    for n in numba.prange(x0.shape[0]):
        x, y, z, steps, fin, stall = _trace(x0[n], y0[n], z0[n], z_stop, step_scale, min_step,
                                            max_step, max_steps, cos_max, lines, bd_kind, bd,
                                            bd_z, bd_ez, px, py, pz, ph, c)
        ox[n] = x
        oy[n] = y
        oz[n] = z
        osteps[n] = steps
        ofin[n] = fin
        ostall[n] = stall


@numba.njit(parallel=True, cache=True)
def bisect_batch(lo, hi, along, index, axis, pitch, n_iter, z0, z_stop, step_scale, min_step,
                 max_step, max_steps, cos_max, lines, bd_kind, bd, bd_z, bd_ez, px, py, pz, ph,
                 c):
    """``n_iter[n]`` bisection steps of pixel boundary n, brackets ``lo``/``hi`` updated in place.

    The loop of :func:`lsst_bfdrift.physics.boundaries.bisect_boundary`, compiled: the
    line from the bracket's middle (pixel units; ``axis`` 0: across x at
    ``along`` in y, 1: across y) lands at or below pixel ``index`` or above it.
    """
    for n in numba.prange(lo.shape[0]):
        a = lo[n]
        b = hi[n]
        for _ in range(n_iter[n]):
            mid = 0.5 * (a + b)
            if axis == 0:
                xs = (mid + 0.5) * pitch
                ys = (along[n] + 0.5) * pitch
            else:
                xs = (along[n] + 0.5) * pitch
                ys = (mid + 0.5) * pitch
            x, y, z, steps, fin, stall = _trace(xs, ys, z0, z_stop, step_scale, min_step,
                                                max_step, max_steps, cos_max, lines, bd_kind, bd,
                                                bd_z, bd_ez, px, py, pz, ph, c)
            landed = np.floor((x if axis == 0 else y) / pitch)
            if landed <= index[n]:
                a = mid
            else:
                b = mid
        lo[n] = a
        hi[n] = b
