"""Compiled edge transfers for :mod:`lsst_bfdrift.correction.solvers` (numba).

One pass over the image computes, for every pixel, the flux gained through
its four edges, f_e S_e, with the edge flux density f_e evaluated on the fly
from the flux image (two-pixel mean or four-point interpolation, no flux
through blocked pixels or the border). Same arithmetic as
``edge_transfer(sv, sh, *edge_flux_density(flux, ...))`` without the five
full-size temporaries.
"""

import types

import numba
import numpy as np
from lsst_bfdrift.utils.errors import InputError

__all__ = ["fused_transfer", "fused_parallel", "fused_serial", "density_weight",
           "DENSITY_WEIGHTS", "SERIAL_BELOW"]


@numba.njit(cache=True, inline="always")
def _density(a0, a1, a2, a3, b0, b1, b2, b3, has_outer, wo):
    """Density between pixels 1 and 2 of the line a0 a1 | a2 a3 (b: blocked);
    four-point weights (wo, 1/2 - wo, 1/2 - wo, wo), two-point mean if wo = 0."""
    if b1 or b2:
        return 0.0
    if wo != 0.0 and has_outer and not (b0 or b3):
        return wo * (a0 + a3) + (0.5 - wo) * (a1 + a2)
    return 0.5 * (a1 + a2)


@numba.njit(cache=True, inline="always")
def _dv(f, blk, j, k, nx, cubic):
    """Density at the vertical edge k (left edge of column k) of row j."""
    if k <= 0 or k >= nx:
        return 0.0
    outer = k >= 2 and k <= nx - 2
    if outer:
        return _density(f[j, k - 2], f[j, k - 1], f[j, k], f[j, k + 1], blk[j, k - 2],
                        blk[j, k - 1], blk[j, k], blk[j, k + 1], True, cubic)
    return _density(0.0, f[j, k - 1], f[j, k], 0.0, False, blk[j, k - 1], blk[j, k], False,
                    False, cubic)


@numba.njit(cache=True, inline="always")
def _dh(f, blk, k, i, ny, cubic):
    """Density at the horizontal edge k (bottom edge of row k) of column i."""
    if k <= 0 or k >= ny:
        return 0.0
    outer = k >= 2 and k <= ny - 2
    if outer:
        return _density(f[k - 2, i], f[k - 1, i], f[k, i], f[k + 1, i], blk[k - 2, i],
                        blk[k - 1, i], blk[k, i], blk[k + 1, i], True, cubic)
    return _density(0.0, f[k - 1, i], f[k, i], 0.0, False, blk[k - 1, i], blk[k, i], False,
                    False, cubic)


@numba.njit(cache=True, inline="always")
def _fused_row_generic(sv, sh, f, blk, cubic, out, j):
    """Row j, pixel by pixel (rows near blocked pixels)."""
    ny, nx = f.shape
    for i in range(nx):
        tvl = _dv(f, blk, j, i, nx, cubic) * sv[j, i]
        tvr = _dv(f, blk, j, i + 1, nx, cubic) * sv[j, i + 1]
        thb = _dh(f, blk, j, i, ny, cubic) * sh[j, i]
        tht = _dh(f, blk, j + 1, i, ny, cubic) * sh[j + 1, i]
        out[j, i] = (tvr - tvl) + (tht - thb)


@numba.njit(cache=True, inline="always")
def _hrow(f, sh, k, ny, nx, cubic, th):
    """th[i] = density x swept area of the horizontal edge k (no blocked pixels)."""
    if k <= 0 or k >= ny:
        for i in range(nx):
            th[i] = 0.0
    elif cubic != 0.0 and k >= 2 and k <= ny - 2:
        wi = 0.5 - cubic
        for i in range(nx):
            th[i] = ((cubic * (f[k - 2, i] + f[k + 1, i]) + wi * (f[k - 1, i] + f[k, i]))
                     * sh[k, i])
    else:
        for i in range(nx):
            th[i] = 0.5 * (f[k - 1, i] + f[k, i]) * sh[k, i]


def _fused_py(sv, sh, f, blk, rowblk, cubic, out):
    """``out`` = the charge gained by every pixel through its edges, as
    :func:`fused_transfer` (``f`` float64 and ``blk`` bool, contiguous;
    ``rowblk`` the rows with a blocked pixel; ``cubic`` the outer weight of
    :func:`density_weight`); no check of the inputs."""
    ny, nx = f.shape
    for j in numba.prange(ny):
        near = False
        for r in range(max(j - 2, 0), min(j + 3, ny)):
            near = near or rowblk[r]
        if near:
            _fused_row_generic(sv, sh, f, blk, cubic, out, j)
            continue
        # No blocked pixel within reach: straight loops over the row (vectorised).
        tv = np.empty(nx + 1)
        tv[0] = 0.0
        tv[nx] = 0.0
        for k in range(1, nx):
            tv[k] = 0.5 * (f[j, k - 1] + f[j, k]) * sv[j, k]
        if cubic != 0.0 and nx >= 4:
            wi = 0.5 - cubic
            for k in range(2, nx - 1):
                tv[k] = ((cubic * (f[j, k - 2] + f[j, k + 1]) + wi * (f[j, k - 1] + f[j, k]))
                         * sv[j, k])
        tb = np.empty(nx)
        tt = np.empty(nx)
        _hrow(f, sh, j, ny, nx, cubic, tb)
        _hrow(f, sh, j + 1, ny, nx, cubic, tt)
        for i in range(nx):
            out[j, i] = (tv[i + 1] - tv[i]) + (tt[i] - tb[i])


def _named(fn, name):
    """A copy of ``fn`` under another name (numba's on-disk cache is keyed by
    the qualified name, so two compilations of one function would collide)."""
    g = types.FunctionType(fn.__code__, fn.__globals__, name, fn.__defaults__, fn.__closure__)
    g.__qualname__ = name
    return g


#: The kernel of :func:`fused_transfer` on all threads (arguments: see ``_fused_py``).
fused_parallel = numba.njit(parallel=True, cache=True)(_named(_fused_py, "_fused_parallel"))
# One thread for small arrays (the windows of the windowed series): a parallel
# region needs the other thread awake, which on a busy machine can take a
# scheduler time slice, far more than the work (on a quiet one the two are
# alike: benchmarks/performance/profile_drift_results.txt).
#: The kernel of :func:`fused_transfer` on one thread (the same arithmetic).
fused_serial = numba.njit(cache=True)(_named(_fused_py, "_fused_serial"))

#: Outer weight w of the four-point densities (w, 1/2 - w, 1/2 - w, w).
DENSITY_WEIGHTS = {"mean2": 0.0, "cubic4": -1.0 / 16.0, "fv4": -1.0 / 12.0}


def density_weight(density):
    """Outer weight of a density mode (name, or bool for cubic4 / mean2)."""
    if isinstance(density, (bool, np.bool_)):
        return DENSITY_WEIGHTS["cubic4" if density else "mean2"]
    if density not in DENSITY_WEIGHTS:
        raise InputError(f"flux density mode must be one of {sorted(DENSITY_WEIGHTS)}, "
                         f"got {density!r}")
    return DENSITY_WEIGHTS[density]


#: Pixels below which :func:`fused_transfer` runs on one thread (it does on any
#: image when numba has one thread: the parallel kernel is then never compiled).
SERIAL_BELOW = 1 << 18


def fused_transfer(sv, sh, flux, blocked, *, cubic=False, out=None):
    """Charge gained by every pixel through its edges (e); sums to zero.

    Parameters
    ----------
    sv : ndarray, shape (ny, nx + 1)
        Swept areas of the vertical edges (px^2), float32 or float64.
    sh : ndarray, shape (ny + 1, nx)
        Swept areas of the horizontal edges (px^2).
    flux : ndarray, shape (ny, nx), float64
        Image from which the edge flux densities are taken (e).
    blocked : ndarray of bool, shape (ny, nx)
        Pixels that neither give nor receive flux.
    cubic : bool or str, optional
        Edge flux density: ``'mean2'`` (or False), the two-pixel mean;
        ``'cubic4'`` (or True), the four-point interpolation of point values
        (-1, 9, 9, -1) / 16; ``'fv4'``, the fourth-order finite-volume
        reconstruction from pixel averages (-1, 7, 7, -1) / 12 (exact for
        cubic profiles, see :data:`DENSITY_WEIGHTS`).
    out : ndarray, optional
        float64 output array.

    Returns
    -------
    ndarray, float64
    """
    f = np.ascontiguousarray(flux, dtype=np.float64)
    b = np.ascontiguousarray(blocked, dtype=np.bool_)
    ny, nx = f.shape
    if sv.shape != (ny, nx + 1) or sh.shape != (ny + 1, nx) or b.shape != f.shape:
        raise InputError(f"shapes do not match: sv {sv.shape}, sh {sh.shape}, flux {f.shape}, "
                         f"blocked {b.shape}")
    if out is None:
        out = np.empty((ny, nx))
    serial = ny * nx < SERIAL_BELOW or numba.get_num_threads() == 1
    kernel = fused_serial if serial else fused_parallel
    kernel(sv, sh, f, b, b.any(axis=1), density_weight(cubic), out)
    return out
