"""Exact moments in boxes: the fallback of
:func:`~lsst_bfdrift.geometry.linear.linear_moment_maps`.

The flagged bins of the a-priori bound become boxes (:func:`exact_boxes`); the
boundaries are convolved on the boxes with the template's reach of charge
around them (one packed canvas, or the image itself for the strips along
its border) and the polygons' moments taken only in the boxes
(:func:`exact_windows`).
"""

import math

import numpy as np
from scipy import ndimage

from lsst_bfdrift.geometry._convolve import Convolver, block_stack
from lsst_bfdrift.geometry._moment_kernels import moment_kernel
from lsst_bfdrift.geometry.superpose import MomentMaps, resample_template

__all__ = ["exact_boxes", "exact_windows", "packed_canvas"]


def exact_boxes(flag, b, shape, *, band, block=32):
    """Pixel boxes (y0, y1, x0, x1) covering the flagged bins.

    Flagged bins within ``band`` bins of the image border (where the
    uniform level's displacements are) make strips along each side: one per
    run of flagged bins along the side (runs less than ``2 band + 1`` bins
    apart merged), each as deep as its deepest flagged bin, so that a source
    near one end of a side does not make a strip of the whole side; the
    others, the bounding box of every connected group of flagged bins
    within each ``block`` x ``block`` block of bins.
    """
    ny, nx = shape
    nby, nbx = flag.shape
    flag = flag.copy()
    out = []
    band = min(band, nby // 2, nbx // 2)
    if band > 0:
        sides = ((flag[:band], False, False), (flag[nby - band:][::-1], False, True),
                 (flag[:, :band].T, True, False), (flag[:, nbx - band:][:, ::-1].T, True, True))
        for f, transposed, far in sides:
            cols = np.flatnonzero(f.any(axis=0))
            if not cols.size:
                continue
            n_along, n_across = (ny, nx) if transposed else (nx, ny)
            bins_across = nbx if transposed else nby
            cuts = np.flatnonzero(np.diff(cols) > 2 * band + 1) + 1
            for run in np.split(cols, cuts):
                c0, c1 = int(run[0]), int(run[-1]) + 1
                depth = int(np.flatnonzero(f[:, c0:c1].any(axis=1))[-1]) + 1
                a, z = c0 * b, min(c1 * b, n_along)
                lo, hi = (((bins_across - depth) * b, n_across) if far
                          else (0, min(depth * b, n_across)))
                out.append((a, z, lo, hi) if transposed else (lo, hi, a, z))
        flag[:band] = flag[nby - band:] = False
        flag[:, :band] = flag[:, nbx - band:] = False
    labels, _ = ndimage.label(flag, structure=np.ones((3, 3), int))
    for sl in ndimage.find_objects(labels):
        for by in range(sl[0].start, sl[0].stop, block):
            for bx in range(sl[1].start, sl[1].stop, block):
                f = flag[by:min(by + block, sl[0].stop), bx:min(bx + block, sl[1].stop)]
                if not f.any():
                    continue
                rows = np.flatnonzero(f.any(axis=1))
                cols = np.flatnonzero(f.any(axis=0))
                out.append(((by + rows[0]) * b, min((by + rows[-1] + 1) * b, ny),
                            (bx + cols[0]) * b, min((bx + cols[-1] + 1) * b, nx)))
    return out


def exact_windows(template, q, boxes, r, outs, names, *, samples, workers, dtype, strip,
                   progress=None):
    """Exact moments of the pixels in ``boxes``; returns the area (px) whose
    boundaries were convolved. ``progress`` is called with the fraction of
    that area done (by blocks of rows).

    Each box, with ``r`` pixels of its charge around it, is a slot on one
    canvas, on shelves, apart from the others by their margins (no pixel of
    a box sees another slot's charge); beyond the image border a margin
    holds no charge, as the transforms' zero padding of the image would
    give. Only the boxes' own pixels get their polygons' moments
    (:func:`_box_moments`).
    """
    if not boxes:
        return 0
    canvas, place = packed_canvas(q, boxes, r)
    tick = None
    if progress is not None:
        done = [0]
        size = canvas.size

        def report(n):
            done[0] += n
            progress(min(done[0] / max(size, 1), 1.0))
        tick = report
    return _box_moments(template, canvas, place, outs, names, samples=samples,
                        workers=workers, dtype=dtype, strip=strip, progress=tick)


def packed_canvas(q, boxes, r):
    """One canvas holding every box of ``q`` with ``r`` pixels of its charge
    around it, on shelves (no pixel of a box within ``r`` of another slot's
    charge; beyond the image border a margin holds no charge).

    Returns
    -------
    canvas : ndarray, float64
    place : list of (int, int, tuple)
        (row, col, box): the box's first pixel at (row, col) of the canvas.
    """
    ny, nx = q.shape
    slots = sorted(((y1 - y0 + 2 * r, x1 - x0 + 2 * r, (y0, y1, x0, x1))
                    for y0, y1, x0, x1 in boxes), reverse=True)
    total = sum(h * w for h, w, _ in slots)
    width = max(max(w for _, w, _ in slots), int(math.sqrt(total) * 1.1))
    place, x, y, shelf = [], 0, 0, 0
    for h, w, box in slots:
        if x + w > width:
            y, x, shelf = y + shelf, 0, 0
        place.append((y + r, x + r, box))
        x += w
        shelf = max(shelf, h)
    canvas = np.zeros((y + shelf, width))
    for cy, cx, (y0, y1, x0, x1) in place:
        a0, a1, b0, b1 = max(y0 - r, 0), min(y1 + r, ny), max(x0 - r, 0), min(x1 + r, nx)
        canvas[cy + a0 - y0:cy + a1 - y0, cx + b0 - x0:cx + b1 - x0] = q[a0:a1, b0:b1]
    return canvas, place


def _box_moments(template, canvas, place, outs, names, *, samples, workers, dtype, strip,
                 progress=None):
    """Exact moments of boxes of ``canvas``: ``place`` lists (row, col, box)
    with the box's first pixel at (row, col) of the canvas and ``box`` = (y0,
    y1, x0, x1) where its maps go in ``outs``. The boundaries are convolved
    over the whole canvas in blocks of about ``strip`` rows of equal height
    (one kernel transform), the polygons' moments taken only in the boxes.
    ``progress`` is called with the pixels (rows x width) of each block done.
    Returns the canvas's area (px)."""
    t = template if samples is None else resample_template(template, samples)
    conv = Convolver(t, dtype=dtype)
    fr = np.ascontiguousarray(t.fractions)
    ns, has_t, c = t.edge_samples, t.vedge_t is not None, t.center
    h = canvas.shape[0]
    nblocks = -(-h // max(int(strip), 1))
    rows = -(-h // nblocks)
    if rows * nblocks > h:  # equal blocks: the last one padded with empty rows
        canvas = np.concatenate([canvas, np.zeros((rows * nblocks - h, canvas.shape[1]))])
    keep = [MomentMaps._names.index(name) for name in names]
    for r0 in range(0, h, rows):
        r1 = r0 + rows
        st, ro = block_stack(conv, canvas, r0, r1, workers)
        for cy, cx, (y0, y1, x0, x1) in place:
            j0, j1 = max(cy, r0), min(cy + y1 - y0, r1)
            if j0 >= j1:
                continue
            part = np.empty((8, j1 - j0, x1 - x0))
            moment_kernel(part[0].size)(st, ns, has_t, ro + j0 - r0, c + cx, fr, part)
            for k, m in zip(range(len(names)), keep):
                outs[k][y0 + j0 - cy:y0 + j1 - cy, x0:x1] = part[m]
        del st
        if progress is not None:
            progress((min(r1, h) - r0) * canvas.shape[1])
    return canvas.shape[0] * canvas.shape[1]
