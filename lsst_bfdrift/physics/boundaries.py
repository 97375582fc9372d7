"""Pixel boundaries at the conversion height, found by bisection of drift lines.

For an edge between two pixels, points on a short segment crossing the
nominal edge are traced to the channel; the landing pixel changes where the
segment crosses the boundary, which is located by bisection to ``tol``
(pixel units). Edge samples lie at uniformly spaced fractions along each
nominal edge; corners (where four pixels meet) are solved by alternating
one-dimensional bisections across the column boundary and the row boundary,
which converges at once because boundaries are nearly axis-parallel.

All positions returned are in pixel units in the image frame: pixel (i, j) is
centred on (i, j) and its nominal corners are at half-integers.
"""

import numpy as np

from lsst_bfdrift.physics._drift_kernels import bisect_batch
from lsst_bfdrift.physics.drift import compile_model, compiled_line_arguments, drift_lines
from lsst_bfdrift.utils.errors import ComputationError, InputError

#: Times :func:`locate_corners` reads a corner that does not converge 4 times
#: farther either side of it (2 tol, then 8, 32, 128 tol).
WIDER_READINGS = 3

__all__ = ["BoundaryGrid", "bisect_boundary", "locate_corners", "pixel_boundaries",
           "centred_boundaries",
           "uniform_fractions", "edge_fractions"]


def uniform_fractions(n):
    """``n`` uniformly spaced sample fractions strictly inside an edge."""
    if int(n) != n or n < 1:
        raise InputError(f"number of edge samples must be a positive integer, got {n!r}")
    return (np.arange(n) + 1.0) / (n + 1.0)


def edge_fractions(n, spacing="uniform"):
    """Sample fractions along an edge.

    * ``'uniform'`` (the paper's choice): k / (n + 1), k = 1..n;
    * ``'tan'``: rays from the pixel centre at equal angles, (tan(theta_k) +
      1) / 2 with theta_k = -pi/4 + k pi / (2 (n + 1)) (GalSim's vertices),
      slightly denser at the edge's middle than at its ends;
    * ``'ends'``: Chebyshev nodes, (1 - cos(pi (k - 1/2) / n)) / 2, dense at
      both ends (the first about 0.62 / n^2 from the corner), where the boundaries
      next to an aggressor bend sharply into its corners.
    """
    if spacing == "uniform":
        return uniform_fractions(n)
    if spacing == "tan":
        uniform_fractions(n)  # validates n
        theta = -np.pi / 4 + (np.arange(n) + 1.0) * np.pi / (2.0 * (n + 1.0))
        return (np.tan(theta) + 1.0) / 2.0
    if spacing == "ends":
        uniform_fractions(n)  # validates n
        return (1.0 - np.cos(np.pi * (np.arange(n) + 0.5) / n)) / 2.0
    raise InputError(f"edge spacing must be 'uniform', 'tan' or 'ends', got {spacing!r}")


def bisect_boundary(model, along, across, axis, index, *, tol=1e-4, half_width=0.45,
                    max_half_width=2.0, z0=None, drift_kwargs=None, progress=None):
    """Locate boundaries between pixel index ``index`` and ``index + 1``.

    Parameters
    ----------
    model : SensorModel
        The field model.
    along : array_like
        Coordinate (pixel units, image frame) along the edge of each sample.
    across : array_like
        Initial guess of the boundary coordinate across the edge (pixel units).
    axis : {'x', 'y'}
        'x': column boundaries (search along x); 'y': row boundaries.
    index : array_like of int
        Pixel index on the lower side of each boundary.
    tol : float, optional
        Bisection tolerance (pixel units).
    half_width : float or array_like, optional
        Initial half width of the bracket (pixel units), one or one per
        sample; a bracket that does not hold the boundary is doubled.
    max_half_width : float, optional
        Largest bracket tried when the boundary lies outside the first one.
    z0 : float, optional
        Conversion height (um); default the entrance window.
    drift_kwargs : dict, optional
        Passed to :func:`~lsst_bfdrift.physics.drift.drift_lines`.
    progress : callable, optional
        Called with the number of line batches done after each trace.

    Returns
    -------
    ndarray
        Boundary coordinates across the edge (pixel units).
    """
    drift_kwargs = drift_kwargs or {}
    p = model.params.pixel_pitch
    compiled = compiled_line_arguments(model, z0, **drift_kwargs)
    along, guess, index, width = np.broadcast_arrays(
        np.asarray(along, float), np.asarray(across, float), np.asarray(index),
        np.asarray(half_width, float))
    along, guess, index = along.ravel(), guess.ravel().copy(), index.ravel()
    width = np.minimum(width.ravel(), max_half_width)
    if not (np.all(np.isfinite(along)) and np.all(np.isfinite(guess))):
        raise InputError("drift starting points must be finite")
    if not np.all(width > 0):
        raise InputError("half_width must be positive")
    result = np.empty(along.size)
    todo = np.arange(along.size)
    while todo.size:
        hw = width[todo]
        lo = guess[todo] - hw
        hi = guess[todo] + hw
        n_iter = np.maximum(np.ceil(np.log2(2 * hw / tol)), 0).astype(np.int64)
        along_t, index_t = along[todo], index[todo]
        for step in range(int(n_iter.max(initial=0))):
            going = n_iter > step  # samples whose bracket is still wider than tol
            if compiled is not None:
                # the lines integrated in a compiled loop (one call per step, so
                # that progress keeps its pace)
                bisect_batch(lo, hi, along_t, index_t, 0 if axis == "x" else 1, p,
                             going.astype(np.int64), *compiled)
            else:
                mid = 0.5 * (lo[going] + hi[going])
                if axis == "x":
                    res = drift_lines(model, (mid + 0.5) * p, (along_t[going] + 0.5) * p, z0,
                                      **drift_kwargs)
                    landed = np.floor(res.x / p)
                else:
                    res = drift_lines(model, (along_t[going] + 0.5) * p, (mid + 0.5) * p, z0,
                                      **drift_kwargs)
                    landed = np.floor(res.y / p)
                lower = landed <= index_t[going]
                lo[going] = np.where(lower, mid, lo[going])
                hi[going] = np.where(lower, hi[going], mid)
            if progress is not None:
                progress(1)
        est = 0.5 * (lo + hi)
        # A bracket end that never moved means the boundary may lie outside it.
        at_end = ((np.abs(est - (guess[todo] - hw)) < tol)
                  | (np.abs(est - (guess[todo] + hw)) < tol))
        result[todo] = est
        if not np.any(at_end):
            break
        widest = at_end & (hw >= max_half_width)
        if np.any(widest):
            bad = todo[widest]
            raise ComputationError(
                f"no boundary found within {max_half_width} px of the nominal edge for "
                f"{bad.size} sample(s), e.g. along={along[bad[0]]:.3f}, axis={axis!r}, "
                f"index={index[bad[0]]}")
        todo = todo[at_end]
        width[todo] = np.minimum(2 * hw[at_end], max_half_width)
    return result


def _bracket(move, tol, floor=8.0):
    """Half widths (pixel units) of brackets a few times the last ``move``:
    4 move, at least ``floor`` tol, at most 0.45."""
    return np.clip(4.0 * move, floor * tol, 0.45)


def locate_corners(model, xc, yc, col_index, row_index, *, tol=1e-4, max_passes=12, **kwargs):
    """Locate pixel corners (meeting points of four pixels) by alternation.

    The corner solves x = X(y), y = Y(x), with X the column boundary and Y
    the row boundary. Starting from the nominal corner, the two are bisected
    in turn (the contraction per round is ``|X'(y) Y'(x)|``: ~1e-4 far from any
    charge, up to ~0.2 at the cusps next to an aggressor) until both
    coordinates move by less than ``2 tol`` (each bisection itself scatters by
    up to ``tol``, and with contraction <= 0.25 the remaining error is then
    below ``tol``); later passes use brackets a few times the last change
    wide (the first: the first round's move from the nominal corner),
    centred on each reading's last value, so they cost few traces. Each
    boundary is read a small step to either side of the other one and
    averaged; next to an aggressor the two readings differ by up to a few
    1e-4 px, which is why each starts from its own last value.

    Parameters
    ----------
    model : SensorModel
        The field model.
    xc, yc : array_like
        Nominal corner positions (pixel units).
    col_index, row_index : array_like of int
        Column and row indices below/left of each corner.
    tol : float, optional
        Tolerance (pixel units).
    max_passes : int, optional
        Largest number of (column, row) bisection rounds.
    **kwargs
        Passed to :func:`bisect_boundary` (not ``half_width``).

    Returns
    -------
    x, y : ndarray
        Corner positions (pixel units).

    Corners where a round does not halve the move (slow or oscillating
    alternation, contraction near 1) are finished by Steffensen's method on
    y -> Y(X(y)), with brackets likewise a few times the last move wide.
    Where that too cycles (a boundary that jumps at the corner: next to a
    strong aggressor the row boundary left and right of the column boundary
    can lie a few 1e-4 px apart, so readings 2 tol either side of the corner
    straddle the jump in turn), the corner is read 4 times farther either
    side, up to :data:`WIDER_READINGS` times (at most 128 tol).

    Raises
    ------
    RuntimeError
        If some corner has not converged after all that.
    """
    x = np.asarray(xc, float).ravel().copy()
    y = np.asarray(yc, float).ravel().copy()
    col_index = np.broadcast_to(np.asarray(col_index), np.shape(xc)).ravel()
    row_index = np.broadcast_to(np.asarray(row_index), np.shape(xc)).ravel()
    # Each boundary is read a small step to either side of the other one and
    # averaged: exactly on a barrier's symmetry plane, lines stall on its
    # saddle and the crossing boundary there is not the limit of its neighbours.
    delta = [2.0 * tol]  # bias at a kink ~ delta * (slope jump) / 2; jumps: see below

    # the readings on either side start from the last ones (they differ by
    # up to a few 1e-4 px at an aggressor's corners, whose boundaries bend
    # sharply there), so that narrow brackets hold them
    guess = {"x": [x.copy(), x.copy()], "y": [y.copy(), y.copy()]}

    def read(axis, along, idx, first=False, **kw):
        index = (col_index if axis == "x" else row_index)[idx]
        g = guess[axis]
        for k, side in enumerate((-delta[0], delta[0])):
            if first and k == 1:
                # the first reading of the far side starts from the near side's,
                # in a bracket a few times that one's move wide
                nominal = g[1][idx]
                g[1][idx] = g[0][idx]
                kw = dict(kw, half_width=_bracket(np.abs(g[0][idx] - nominal), tol))
            g[k][idx] = bisect_boundary(model, along + side, g[k][idx], axis, index, tol=tol, **kw)
        return 0.5 * (g[0][idx] + g[1][idx])

    def solve(todo):
        """Alternation, then Steffensen where it stalls; the corners left."""
        slow = np.zeros(0, dtype=int)
        for _ in range(max_passes):
            if todo.size == 0:
                break
            hw = _bracket(step[todo], tol, floor=4.0)
            xn = read("x", y[todo], todo, half_width=hw, **kwargs)
            yn = read("y", xn, todo, half_width=hw, **kwargs)
            change = np.maximum(np.abs(xn - x[todo]), np.abs(yn - y[todo]))
            x[todo], y[todo] = xn, yn
            going = change >= 2.0 * tol
            # a round that does not halve the move: alternation is slow or
            # oscillates there (|X'Y'| near 1 at strong cusps)
            stuck = going & (change > 0.5 * step[todo])
            step[todo] = change
            slow = np.concatenate([slow, todo[stuck]])
            todo = todo[going & ~stuck]
        todo = np.sort(np.concatenate([slow, todo]))

        def g_of(yy, idx, kw):  # G(y) = Y(X(y))
            xn = read("x", yy, idx, **kw)
            return read("y", xn, idx, **kw)

        cycling = np.zeros(0, dtype=int)
        for it in range(max_passes if todo.size else 0):
            if todo.size == 0:
                break
            kw = dict(half_width=_bracket(step[todo], tol, floor=4.0), **kwargs)
            y0 = y[todo]
            g0 = g_of(y0, todo, kw)
            g1 = g_of(g0, todo, kw)
            den = g1 - 2.0 * g0 + y0
            with np.errstate(divide="ignore", invalid="ignore"):
                ynew = np.where(np.abs(den) > 1e-12, y0 - (g0 - y0) ** 2 / den, g1)
            ynew = np.clip(ynew, y0 - 0.45, y0 + 0.45)
            xnew = read("x", ynew, todo, **kw)
            change = np.maximum(np.abs(ynew - y0), np.abs(xnew - x[todo]))
            x[todo], y[todo] = xnew, ynew
            going = change >= 2.0 * tol
            # past its first steps, a Steffensen step that does not halve the
            # move cycles too: left for the wider readings
            stuck = going & (change > 0.5 * step[todo]) & (it > 0)
            step[todo] = change
            cycling = np.concatenate([cycling, todo[stuck]])
            todo = todo[going & ~stuck]
        return np.sort(np.concatenate([cycling, todo]))

    everything = np.arange(x.size)
    x = read("x", y, everything, first=True, **kwargs)
    y = read("y", x, everything, first=True, **kwargs)
    # the first round's move bounds the next (the contraction is < 1): later
    # brackets are a few times the last move wide, and widen when they miss
    step = np.maximum(np.abs(x - np.ravel(xc)), np.abs(y - np.ravel(yc)))
    todo = solve(everything)
    for _ in range(WIDER_READINGS):
        if todo.size == 0:
            break
        # Where a boundary jumps at the corner (next to a strong aggressor the
        # row boundary left and right of the column boundary can lie a few
        # 1e-4 px apart), readings 2 tol either side straddle the jump in turn
        # and the alternation cycles: read those corners 4 times farther out.
        delta[0] *= 4.0
        x[todo] = read("x", y[todo], todo, first=True, **kwargs)
        y[todo] = read("y", x[todo], todo, first=True, **kwargs)
        step[todo] = 0.45
        todo = solve(todo)
    if todo.size:
        raise ComputationError(f"{todo.size} corner(s) did not converge in {max_passes} passes, "
                               f"e.g. near ({x[todo[0]]:.4f}, {y[todo[0]]:.4f})")
    return x, y


class BoundaryGrid:
    """Pixel boundaries of a rectangular block of pixels.

    Attributes
    ----------
    i0, j0 : int
        Indices of the lower-left pixel of the block.
    corners : ndarray, shape (ny + 1, nx + 1, 2)
        Corner positions (x, y), pixel units; ``corners[J, I]`` is the corner
        nominally at (i0 + I - 0.5, j0 + J - 0.5).
    vedge : ndarray, shape (ny, nx + 1, ns)
        x of the column boundaries at the samples; ``vedge[J, I]`` is the left
        edge of pixel (i0 + I, j0 + J).
    hedge : ndarray, shape (ny + 1, nx, ns)
        y of the row boundaries at the samples; ``hedge[J, I]`` is the bottom
        edge of pixel (i0 + I, j0 + J).
    fractions : ndarray, shape (ns,)
        Sample fractions along each edge (from its lower/left corner).
    """

    def __init__(self, i0, j0, corners, vedge, hedge, fractions):
        self.i0, self.j0 = int(i0), int(j0)
        self.corners, self.vedge, self.hedge = corners, vedge, hedge
        self.fractions = np.asarray(fractions, float)

    @property
    def shape(self):
        """(ny, nx) of the block."""
        return self.vedge.shape[0], self.hedge.shape[1]

    def nominal(self):
        """The undistorted grid of the same block."""
        ny, nx = self.shape
        ii, jj = np.meshgrid(np.arange(nx + 1) + self.i0 - 0.5, np.arange(ny + 1) + self.j0 - 0.5)
        corners = np.stack([ii, jj], axis=-1)
        vedge = np.broadcast_to(corners[:-1, :, 0, None], self.vedge.shape).copy()
        hedge = np.broadcast_to(corners[:, :-1, 1, None], self.hedge.shape).copy()
        return BoundaryGrid(self.i0, self.j0, corners, vedge, hedge, self.fractions)

    def displacements(self, reference=None):
        """Displacements from ``reference`` (default the nominal grid).

        Returns
        -------
        corner_d : ndarray (ny + 1, nx + 1, 2)
        vedge_d : ndarray (ny, nx + 1, ns)
        hedge_d : ndarray (ny + 1, nx, ns)
        """
        ref = self.nominal() if reference is None else reference
        return (self.corners - ref.corners, self.vedge - ref.vedge, self.hedge - ref.hedge)


def _bisect_task(model, kind, arrays, kw):
    """Worker body (module level so that it can be sent to a process)."""
    if kind == "corner":
        return locate_corners(model, *arrays, **kw)
    return bisect_boundary(model, arrays[0], arrays[1], kind, arrays[2], half_width=arrays[3],
                           **kw)


def _split_run(model, kind, arrays, kw, workers):
    """Run a bisection task on ``workers`` chunks of the samples.

    With the compiled drift engine (the default for the package's own field
    terms) the kernel already shares the lines between all cores, and forking
    after its thread pool has started is unsafe: everything runs in-process.
    Otherwise chunks go to forked worker processes (numpy on small arrays
    holds the GIL, so threads do not help); where ``fork`` is unavailable the
    chunks run in turn. Results are concatenated in order and do not depend
    on ``workers``.
    """
    import multiprocessing as mp  # starts worker processes: only when chunks run in them
    from concurrent.futures import ProcessPoolExecutor  # likewise

    arrays = [np.asarray(a).ravel() for a in np.broadcast_arrays(*arrays)]
    n = arrays[0].size
    workers = max(1, min(int(workers), n))
    engine = (kw.get("drift_kwargs") or {}).get("engine", "auto")
    if workers > 1 and ("fork" not in mp.get_all_start_methods()
                        or (engine != "numpy" and compile_model(model) is not None)):
        workers = 1
    if workers == 1:
        return _bisect_task(model, kind, arrays, kw)
    bounds = np.linspace(0, n, workers + 1).astype(int)
    chunks = [[a[b0:b1] for a in arrays] for b0, b1 in zip(bounds[:-1], bounds[1:])]
    progress = kw.pop("progress", None)
    with ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork")) as pool:
        futures = [pool.submit(_bisect_task, model, kind, ch, kw) for ch in chunks]
        results = [f.result() for f in futures]
    if progress is not None:
        progress(workers)
    if isinstance(results[0], tuple):
        return tuple(np.concatenate(parts) for parts in zip(*results))
    return np.concatenate(results)


def pixel_boundaries(model, i_range, j_range, *, edge_samples=8, tol=1e-4, z0=None,
                     drift_kwargs=None, progress=None, workers=1, spacing="uniform"):
    """Boundaries of all pixels ``i0 <= i < i1``, ``j0 <= j < j1``.

    Parameters
    ----------
    model : SensorModel
        The field model.
    i_range, j_range : tuple of int
        Half-open index ranges (i0, i1) and (j0, j1).
    edge_samples : int, optional
        Samples per edge, uniformly spaced.
    tol : float, optional
        Bisection tolerance (pixel units).
    z0 : float, optional
        Conversion height (um); default the entrance window.
    drift_kwargs : dict, optional
        Passed to :func:`~lsst_bfdrift.physics.drift.drift_lines`.
    progress : callable, optional
        Called with the number of traces done (for progress bars).
    workers : int, optional
        Processes sharing the drift lines (results do not depend on it).
    spacing : {'uniform', 'tan', 'ends'}, optional
        Placement of the edge samples (:func:`edge_fractions`).

    Returns
    -------
    BoundaryGrid
    """
    i0, i1 = (int(v) for v in i_range)
    j0, j1 = (int(v) for v in j_range)
    if i1 <= i0 or j1 <= j0:
        raise InputError(f"empty pixel range i={i_range}, j={j_range}")
    if not (0 < tol < 0.1):
        raise InputError(f"tol must be in (0, 0.1) pixel, got {tol}")
    fr = edge_fractions(edge_samples, spacing)
    nx, ny = i1 - i0, j1 - j0
    kw = dict(tol=tol, z0=z0, drift_kwargs=drift_kwargs, progress=progress)
    # Corners first: corner (I, J) nominally at (I - 0.5, J - 0.5).
    I, J = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1))
    cx, cy = _split_run(model, "corner", [I - 0.5, J - 0.5, I - 1, J - 1], dict(kw), workers)
    corners = np.stack([cx.reshape(I.shape), cy.reshape(I.shape)], axis=-1)
    # Each edge sample starts from the chord between its edge's corners, in a
    # bracket 4 times their largest move wide (at least 8 tol; it widens when
    # the edge bows out of it, as next to an aggressor)
    move = np.abs(corners - np.stack([I - 0.5, J - 0.5], axis=-1)).max(axis=-1)
    # Column boundaries: x = I - 0.5 for I in i0..i1, rows J in j0..j1-1.
    # meshgrid with indexing xy gives shape (nJ, nI, nF)
    I, J, F = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1), fr, indexing="xy")
    x0, x1 = corners[:-1, :, 0, None], corners[1:, :, 0, None]
    hw = np.broadcast_to(_bracket(np.maximum(move[:-1, :, None], move[1:, :, None]), tol),
                         F.shape)
    vx = _split_run(model, "x", [J - 0.5 + F, x0 + F * (x1 - x0), I - 1, hw], dict(kw), workers)
    vedge = vx.reshape(ny, nx + 1, edge_samples)
    # Row boundaries: y = J - 0.5 for J in j0..j1, columns I in i0..i1-1.
    I, J, F = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1 + 1), fr, indexing="xy")
    y0, y1 = corners[:, :-1, 1, None], corners[:, 1:, 1, None]
    hw = np.broadcast_to(_bracket(np.maximum(move[:, :-1, None], move[:, 1:, None]), tol),
                         F.shape)
    hy = _split_run(model, "y", [I - 0.5 + F, y0 + F * (y1 - y0), J - 1, hw], dict(kw), workers)
    hedge = hy.reshape(ny + 1, nx, edge_samples)
    return BoundaryGrid(i0, j0, corners, vedge, hedge, fr)


def _mirror_index(k):
    """Index in the traced quadrant (0..) and sign of full-grid offset ``k`` of a
    boundary at ``k - 1/2`` (boundaries at negative positions mirror to 1 - k)."""
    k = np.asarray(k)
    return np.where(k < 1, 1 - k, k), np.where(k < 1, -1.0, 1.0)


def centred_boundaries(model, c, **kwargs):
    """Boundaries of the pixels within ``c`` of pixel (0, 0), using the model's
    mirror symmetry when it has it.

    A model symmetric under x -> -x and y -> -y about the centre of pixel
    (0, 0) (``model.mirror_symmetric``) is traced on the quadrant of pixels
    0..c only, (c + 1)^2 pixels instead of (2 c + 1)^2, and the other three
    are its mirror images: a boundary's displacement across itself changes
    sign under the mirror that moves it, and the samples along an edge run the
    other way under the mirror along it. Other models are traced whole.

    Parameters
    ----------
    model : SensorModel
        The field model.
    c : int
        Half side: pixels -c..c on both axes.
    **kwargs
        Passed to :func:`pixel_boundaries`; the edge samples must be placed
        symmetrically along the edge (both spacings are).

    Returns
    -------
    BoundaryGrid
        The block of pixels -c..c (as ``pixel_boundaries(model, (-c, c + 1),
        (-c, c + 1), ...)`` gives it, to the bisection's tolerance).
    """
    c = int(c)
    if not getattr(model, "mirror_symmetric", False):
        return pixel_boundaries(model, (-c, c + 1), (-c, c + 1), **kwargs)
    q = pixel_boundaries(model, (0, c + 1), (0, c + 1), **kwargs)
    fr = q.fractions
    if not np.allclose(fr, 1.0 - fr[::-1], rtol=0, atol=1e-12):
        return pixel_boundaries(model, (-c, c + 1), (-c, c + 1), **kwargs)
    nom = q.nominal()
    dc, dv, dh = q.displacements(nom)
    offs = np.arange(-c, c + 1)           # pixel offsets
    bnds = np.arange(-c, c + 2)           # boundary k at k - 1/2
    # column boundaries: rows mirror (samples reversed), boundaries mirror (sign)
    jr, ib = np.abs(offs), _mirror_index(bnds)
    vd = dv[jr][:, ib[0]] * ib[1][None, :, None]
    vd[offs < 0] = vd[offs < 0][..., ::-1]
    # row boundaries: boundaries mirror (sign), columns mirror (samples reversed)
    jb, ic = _mirror_index(bnds), np.abs(offs)
    hd = dh[jb[0]][:, ic] * jb[1][:, None, None]
    hd[:, offs < 0] = hd[:, offs < 0][..., ::-1]
    # corners: each coordinate's displacement flips under its own mirror
    cd = dc[jb[0]][:, ib[0]].copy()
    cd[..., 0] *= ib[1][None, :]
    cd[..., 1] *= jb[1][:, None]
    full = BoundaryGrid(-c, -c, np.zeros((2 * c + 2, 2 * c + 2, 2)),
                        np.zeros((2 * c + 1, 2 * c + 2, fr.size)),
                        np.zeros((2 * c + 2, 2 * c + 1, fr.size)), fr).nominal()
    return BoundaryGrid(-c, -c, full.corners + cd, full.vedge + vd, full.hedge + hd, fr)
