"""Compiled (numba) kernels of the first-order maps and their bounds
(:mod:`lsst_bfdrift.geometry.first_order`, :mod:`lsst_bfdrift.geometry.bounds`).

One pass over the charge image per call: numpy needs two full-size
temporaries for ``abs(q - qbar)`` and a reshape for the bin sums (about
five times the time on a 4k x 4k image).
"""

import numba
import numpy as np

__all__ = ["abs_dev_bins", "abs_dev_cell_max", "pixel_abs_dev_sums", "store_tile",
           "combine_rows"]


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
def abs_dev_cell_max(q, qbar, c, out):
    """Largest ``abs(q - qbar)`` over each ``c`` x ``c`` cell of ``q``.

    Parameters
    ----------
    q : (ny, nx) float64, charge (e)
    qbar : float, reference level (e)
    c : int, cell side (px)
    out : (ceil(ny / c), ceil(nx / c)) float64, written
    """
    ny, nx = q.shape
    ncy, ncx = out.shape
    for cy in numba.prange(ncy):
        row = np.zeros(ncx)
        for j in range(cy * c, min(cy * c + c, ny)):
            qj = q[j]
            for cx in range(ncx):
                m = row[cx]
                for i in range(cx * c, min(cx * c + c, nx)):
                    m = max(m, abs(qj[i] - qbar))
                row[cx] = m
        out[cy, :] = row


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
    m = disp.shape[0]
    r = m // 2
    for k in numba.prange(rows.size):
        j = rows[k]
        i = cols[k]
        s = 0.0
        if r <= j < ny - r and r <= i < nx - r:
            # inside: no bounds tests (kernel row t meets image row j + r - t)
            for t in range(m):
                qa = q[j + r - t]
                kt = disp[t]
                for u in range(m):
                    s += kt[u] * abs(qa[i + r - u] - qbar)
        else:
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
def store_tile(res, r, y0, x0, h, w, nominal, slot, outs, area, smax):
    """Copy a tile's convolutions into the maps and track their signal.

    Serial: it runs between the FFTs' threads (a parallel loop here
    competed with them and took ten times longer).

    Parameters
    ----------
    res : (m, fy, fx) float32 or float64, the tile's convolutions; tile pixel
        (j, i) is ``res[:, r + j, r + i]``; map 0 is the area
    r : int, halo (px)
    y0, x0 : int, the tile's first pixel in the image
    h, w : int, tile size (px)
    nominal : (m,) float64, the undistorted value of each map (added)
    slot : (m,) int64, index in ``outs`` of each map, -1 when not stored
        (every map is tracked in ``smax``); map 0 goes to ``area`` when its
        slot is not -1
    outs : (k, ny, nx) float32 or float64, the stored maps but the area
    area : (ny, nx) float64, the area map
    smax : (m,) float64, updated with max abs(res) over the tile
    """
    for k in range(res.shape[0]):
        s = slot[k]
        nom = nominal[k]
        v = smax[k]
        for j in range(h):
            src = res[k, r + j, r:r + w]
            if s >= 0:
                if k == 0:
                    dst = area[y0 + j, x0:x0 + w]
                    for i in range(w):
                        dst[i] = nom + src[i]
                else:
                    dsto = outs[s, y0 + j, x0:x0 + w]
                    for i in range(w):
                        dsto[i] = nom + src[i]
            for i in range(w):
                a = abs(np.float64(src[i]))
                v = a if a > v else v
        smax[k] = v


@numba.njit(cache=True)
def combine_rows(sv, sh, m1v, m1h, p3, c, off, r0, r1, slot, outs, area, smax):
    """First-order maps of image rows r0..r1-1 from the edge fields of a block.

    Serial: it runs between the FFTs' threads, and the arrays are read once
    (a parallel loop took twice as long on a shared machine).

    Parameters
    ----------
    sv, sh, m1v, m1h, p3 : (fy, fx) float32 or float64, C-contiguous
        The whole padded convolutions of the block (the swept-area
        operator's frame): swept areas of the vertical and horizontal edges
        (px^2), first moments (about the edge's middle) of their normal
        displacement (px^3), and the second-moment part of e1 (px^4).
        Block row ``t`` and column ``i`` are at ``[t + c, i + c]``; pixel
        (j, i) has left and right edges at columns i and i + 1 of the
        vertical-edge fields, bottom and top edges at rows t and t + 1 of
        the horizontal ones (t = j - r0 + off).
    c : int, the operator's offset (the template's centre)
    off, r0, r1 : int, block row of image row r0, and the rows to fill
    slot : (5,) int64, index in ``outs`` of dx, dy, e1, e2 (-1: not
        stored; every map is tracked in ``smax``); the area is stored in
        ``area`` when its slot is not -1
    outs : (k, ny, nx) float32 or float64, written
    area : (ny, nx) float64, written with its nominal 1
    smax : (5,) float64, updated with max abs(map - nominal) over the rows
    """
    nx = outs.shape[2]
    s0, s1, s2, s3, s4 = slot[0], slot[1], slot[2], slot[3], slot[4]
    m0 = smax[0]
    m1 = smax[1]
    m2 = smax[2]
    m3 = smax[3]
    m4 = smax[4]
    for j in range(r0, r1):
        a = j - r0 + off + c
        for i in range(nx):
            b = i + c
            svl = np.float64(sv[a, b])
            svr = np.float64(sv[a, b + 1])
            shb = np.float64(sh[a, b])
            sht = np.float64(sh[a + 1, b])
            vl = np.float64(m1v[a, b])
            vr = np.float64(m1v[a, b + 1])
            hb = np.float64(m1h[a, b])
            ht = np.float64(m1h[a + 1, b])
            dv = svr - svl
            dh = sht - shb
            v0 = dv + dh
            v1 = 0.5 * (svl + svr) + ht - hb
            v2 = 0.5 * (shb + sht) + vr - vl
            v3 = 6.0 * (0.25 * (dv - dh) + np.float64(p3[a, b]))
            v4 = 6.0 * (vl + vr + hb + ht)
            m0 = max(m0, abs(v0))
            m1 = max(m1, abs(v1))
            m2 = max(m2, abs(v2))
            m3 = max(m3, abs(v3))
            m4 = max(m4, abs(v4))
            if s0 >= 0:
                area[j, i] = 1.0 + v0
            if s1 >= 0:
                outs[s1, j, i] = v1
            if s2 >= 0:
                outs[s2, j, i] = v2
            if s3 >= 0:
                outs[s3, j, i] = v3
            if s4 >= 0:
                outs[s4, j, i] = v4
    smax[0] = m0
    smax[1] = m1
    smax[2] = m2
    smax[3] = m3
    smax[4] = m4
