"""Compiled (numba) kernels of :mod:`lsst_bfdrift.geometry.linear`.

One pass over the charge image per call: numpy needs two full-size
temporaries for ``abs(q - qbar)`` and a reshape for the bin sums (about
five times the time on a 4k x 4k image).
"""

import numba
import numpy as np

__all__ = ["abs_dev_bins", "pixel_abs_dev_sums", "store_tile", "combine_rows"]


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


@numba.njit(parallel=True, cache=True)
def pixel_abs_dev_sums(q, qbar, disp, outside, rows, cols, out):
    """``sum over offsets d of disp[d] g(p - d)`` at pixels p = (rows[k], cols[k]),
    ``g = abs(q - qbar)`` inside the image and ``outside`` beyond it.

    Parameters
    ----------
    q : (ny, nx) float64, charge (e)
    qbar : float, reference level (e)
    disp : (m, m) float64, kernel per offset (dj, di) = (j - m // 2, i - m // 2)
        from the aggressor to the pixel (px per e)
    outside : float (e)
    rows, cols : (k,) int64
    out : (k,) float64, written (px)
    """
    ny, nx = q.shape
    r = disp.shape[0] // 2
    for k in numba.prange(rows.size):
        j = rows[k]
        i = cols[k]
        s = 0.0
        for dj in range(-r, r + 1):
            a = j - dj
            for di in range(-r, r + 1):
                c = i - di
                if 0 <= a < ny and 0 <= c < nx:
                    s += disp[dj + r, di + r] * abs(q[a, c] - qbar)
                else:
                    s += disp[dj + r, di + r] * outside
        out[k] = s


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


@numba.njit(parallel=True, cache=True)
def combine_rows(sv, sh, m1v, m1h, p3, off, r0, r1, slot, outs, smax):
    """First-order maps of image rows r0..r1-1 from edge fields of a block.

    Block row ``j - r0 + off`` holds image row j. Pixel (j, i) has left
    and right edges ``[., i]`` and ``[., i + 1]`` of the vertical-edge fields,
    bottom and top edges ``[j, .]`` and ``[j + 1, .]`` of the horizontal ones.

    Parameters
    ----------
    sv, sh : (rows, nx + 1), (rows + 1, nx), swept areas of the edges (px^2)
    m1v, m1h : same shapes, first moments (about the edge's middle) of the
        edges' normal displacement (px^3)
    p3 : (rows, nx), the second-moment part of e1 (px^4)
    off, r0, r1 : int
    slot : (5,) int64, index in ``outs`` of area, dx, dy, e1, e2 (-1: not
        stored; every map is tracked in ``smax``)
    outs : (k, ny, nx) float64, written (area with its nominal 1)
    smax : (5,) float64, updated with max abs(map - nominal) over the rows
    """
    nx = outs.shape[2]
    h = r1 - r0
    part = np.zeros((h, 5))
    for t in numba.prange(h):
        j = r0 + t
        jj = t + off
        m0 = 0.0
        m1 = 0.0
        m2 = 0.0
        m3 = 0.0
        m4 = 0.0
        for i in range(nx):
            svl = np.float64(sv[jj, i])
            svr = np.float64(sv[jj, i + 1])
            shb = np.float64(sh[jj, i])
            sht = np.float64(sh[jj + 1, i])
            vl = np.float64(m1v[jj, i])
            vr = np.float64(m1v[jj, i + 1])
            hb = np.float64(m1h[jj, i])
            ht = np.float64(m1h[jj + 1, i])
            dv = svr - svl
            dh = sht - shb
            v0 = dv + dh
            v1 = 0.5 * (svl + svr) + ht - hb
            v2 = 0.5 * (shb + sht) + vr - vl
            v3 = 6.0 * (0.25 * (dv - dh) + np.float64(p3[jj, i]))
            v4 = 6.0 * (vl + vr + hb + ht)
            m0 = max(m0, abs(v0))
            m1 = max(m1, abs(v1))
            m2 = max(m2, abs(v2))
            m3 = max(m3, abs(v3))
            m4 = max(m4, abs(v4))
            if slot[0] >= 0:
                outs[slot[0], j, i] = 1.0 + v0
            if slot[1] >= 0:
                outs[slot[1], j, i] = v1
            if slot[2] >= 0:
                outs[slot[2], j, i] = v2
            if slot[3] >= 0:
                outs[slot[3], j, i] = v3
            if slot[4] >= 0:
                outs[slot[4], j, i] = v4
        part[t, 0] = m0
        part[t, 1] = m1
        part[t, 2] = m2
        part[t, 3] = m3
        part[t, 4] = m4
    for t in range(h):
        for k in range(5):
            smax[k] = max(smax[k], part[t, k])
