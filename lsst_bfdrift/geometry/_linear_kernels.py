"""Compiled (numba) kernels of :mod:`lsst_bfdrift.geometry.linear`.

One pass over the charge image per call: numpy needs two full-size
temporaries for ``abs(q - qbar)`` and a reshape for the bin sums (about
five times the time on a 4k x 4k image).
"""

import numba
import numpy as np

__all__ = ["abs_dev_bins", "store_tile"]


@numba.njit(parallel=True, cache=True)
def abs_dev_bins(q, qbar, b, outside, out):
    """Sums of ``abs(q - qbar)`` over ``b`` x ``b`` bins of ``q``.

    Parameters
    ----------
    q : (ny, nx) float64, charge (e)
    qbar : float, reference level (e)
    b : int, bin side (px)
    outside : float, the value counted for each pixel of a partial bin
        beyond the image
    out : (ceil(ny / b), ceil(nx / b)) float64, written
    """
    ny, nx = q.shape
    nby, nbx = out.shape
    aq = outside
    for by in numba.prange(nby):
        row = np.zeros(nbx)
        j0 = by * b
        for j in range(j0, j0 + b):
            if j >= ny:
                for bx in range(nbx):
                    row[bx] += aq * b
                continue
            for bx in range(nbx):
                s = 0.0
                i0 = bx * b
                for i in range(i0, i0 + b):
                    if i < nx:
                        s += abs(q[j, i] - qbar)
                    else:
                        s += aq
                row[bx] += s
        out[by, :] = row


@numba.njit(cache=True)
def store_tile(res, r, y0, x0, h, w, nominal, slot, outs, smax):
    """Copy a tile's convolutions into the float64 maps and track their signal.

    Serial: it runs between the FFTs' threads (a parallel loop here
    competed with them and took ten times longer).

    Parameters
    ----------
    res : (m, fy, fx) float32 or float64, the tile's convolutions; tile pixel
        (j, i) is ``res[:, r + j, r + i]``
    r : int, halo (px)
    y0, x0 : int, the tile's first pixel in the image
    h, w : int, tile size (px)
    nominal : (m,) float64, the undistorted value of each map (added)
    slot : (m,) int64, index in ``outs`` of each map, -1 when not stored
        (every map is tracked in ``smax``)
    outs : (k, ny, nx) float64, the stored maps
    smax : (m,) float64, updated with max abs(res) over the tile
    """
    for k in range(res.shape[0]):
        s = slot[k]
        nom = nominal[k]
        v = smax[k]
        for j in range(h):
            src = res[k, r + j, r:r + w]
            if s >= 0:
                dst = outs[s, y0 + j, x0:x0 + w]
                for i in range(w):
                    dst[i] = nom + src[i]
            for i in range(w):
                a = abs(np.float64(src[i]))
                v = a if a > v else v
        smax[k] = v
