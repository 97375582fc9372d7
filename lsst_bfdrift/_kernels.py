"""Compiled (numba) kernels for the hot loops.

numba is used here because the benchmark showed numpy cannot reach the
needed speed: the exact shoelace moments of a 4k x 4k CCD's 36-vertex pixels
took 55-100 s with numpy temporaries (4-6 us per pixel) against a few
seconds compiled. The numpy implementation in :mod:`lsst_bfdrift.geometry`
remains the reference the tests compare against.
"""

import numba
import numpy as np

__all__ = ["grid_moments"]


@numba.njit(cache=True, inline="always")
def _acc(xa, ya, xb, yb, s):
    """Add segment (a -> b) to the shoelace sums s[0..5] (paper eqs. 3.12-3.17)."""
    dx = xb - xa
    dy = yb - ya
    s[0] += 0.5 * (xb * ya - xa * yb)
    s[1] += -dy * (xa * xa + xb * xb) * (xa + xb) / 12.0
    s[2] += dx * (ya * ya + yb * yb) * (ya + yb) / 12.0
    s[3] += (dx * xa * (ya * ya + yb * yb + ya * yb) / 6.0
             + dx * dx * (ya * ya + 3.0 * yb * yb + 2.0 * ya * yb) / 24.0)
    s[4] += -dy * (xa * xa + xb * xb + xa * xb) / 6.0
    s[5] += dx * (ya * ya + yb * yb + ya * yb) / 6.0


@numba.njit(parallel=True, cache=True)
def grid_moments(corners, vedge, hedge, fr, vt, ht, has_t, j0, out):
    """Moments of every pixel of a block from its shared boundaries.

    Parameters
    ----------
    corners : (ny + 1, nx + 1, 2) absolute corner positions (pixel units)
    vedge : (ny, nx + 1, ns) x of column-boundary samples
    hedge : (ny + 1, nx, ns) y of row-boundary samples
    fr : (ns,) sample fractions
    vt, ht : tangential displacements (same shapes as vedge, hedge)
    has_t : bool, whether vt and ht are used
    j0 : int, row index of the block's first pixel (pixel (i, j) centred on (i, j))
    out : (8, ny, nx) output: area, dx, dy, ixx, iyy, ixy, e1, e2
    """
    ny = vedge.shape[0]
    nx = hedge.shape[1]
    ns = fr.shape[0]
    for J in numba.prange(ny):
        s = np.empty(6)
        for I in range(nx):
            ox = float(I)
            oy = float(J + j0)
            s[:] = 0.0
            # clockwise: LL, up the left edge, UL, along the top, UR, down the
            # right edge, LR, back along the bottom
            px = corners[J, I, 0] - ox
            py = corners[J, I, 1] - oy
            x0, y0 = px, py
            for k in range(ns):
                qx = vedge[J, I, k] - ox
                qy = -0.5 + fr[k] + (vt[J, I, k] if has_t else 0.0)
                _acc(px, py, qx, qy, s)
                px, py = qx, qy
            qx = corners[J + 1, I, 0] - ox
            qy = corners[J + 1, I, 1] - oy
            _acc(px, py, qx, qy, s)
            px, py = qx, qy
            for k in range(ns):
                qx = -0.5 + fr[k] + (ht[J + 1, I, k] if has_t else 0.0)
                qy = hedge[J + 1, I, k] - oy
                _acc(px, py, qx, qy, s)
                px, py = qx, qy
            qx = corners[J + 1, I + 1, 0] - ox
            qy = corners[J + 1, I + 1, 1] - oy
            _acc(px, py, qx, qy, s)
            px, py = qx, qy
            for k in range(ns - 1, -1, -1):
                qx = vedge[J, I + 1, k] - ox
                qy = -0.5 + fr[k] + (vt[J, I + 1, k] if has_t else 0.0)
                _acc(px, py, qx, qy, s)
                px, py = qx, qy
            qx = corners[J, I + 1, 0] - ox
            qy = corners[J, I + 1, 1] - oy
            _acc(px, py, qx, qy, s)
            px, py = qx, qy
            for k in range(ns - 1, -1, -1):
                qx = -0.5 + fr[k] + (ht[J, I, k] if has_t else 0.0)
                qy = hedge[J, I, k] - oy
                _acc(px, py, qx, qy, s)
                px, py = qx, qy
            _acc(px, py, x0, y0, s)
            a = s[0]
            cx = s[4] / a
            cy = s[5] / a
            ixx = s[1] / a - cx * cx
            iyy = s[2] / a - cy * cy
            ixy = s[3] / a - cx * cy
            out[0, J, I] = a
            out[1, J, I] = cx
            out[2, J, I] = cy
            out[3, J, I] = ixx
            out[4, J, I] = iyy
            out[5, J, I] = ixy
            out[6, J, I] = (ixx - iyy) / (ixx + iyy)
            out[7, J, I] = 2.0 * ixy / (ixx + iyy)
