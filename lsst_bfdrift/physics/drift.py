"""Drift lines: electrons follow -E from the conversion height to the channel.

Lines are integrated in arc length s with a classical Runge-Kutta (RK4)
scheme, ``dr/ds = -E / |E|``, so that the path (not the drift speed) is followed
and stagnation regions (where the collected charge cancels the backdrop) are
crossed at finite cost. In smooth regions the step depends only on height,
``h = clip(step_scale * (z - z_stop) + min_step, min_step, max_step)``, so
that neighbouring lines see the same discretisation and the landing map is
smooth in the starting point (which is what the boundary bisection relies
on). Where the field direction turns sharply within a step (lines passing a
saddle point above a barrier, on their way to one side or the other), the
step is cut by four until the turn is resolved, then grows back. Lines are
integrated all at once; finished lines leave the active set.
"""

import inspect

import numpy as np

from lsst_bfdrift.physics._drift_kernels import drift_batch
from lsst_bfdrift.physics.absorption import absorption_length
from lsst_bfdrift.physics.constants import COULOMB_UM
from lsst_bfdrift.physics.fields import (BackdropField, HalfPeriodicDipoleGrid, LineDipole,
                                         PeriodicDipoleGrid, PointDipoles, TabulatedBackdrop,
                                         TruncatedLineDipole)
from lsst_bfdrift.utils.errors import InputError

__all__ = ["DriftResult", "drift_lines", "compile_model", "compiled_line_arguments",
           "landing_pixels", "conversion_height"]


class DriftResult:
    """End points of a batch of drift lines.

    Attributes
    ----------
    x, y : ndarray
        Lateral positions (um) where the lines reach ``z_stop``.
    z : ndarray
        Final heights (um); equal to ``z_stop`` for finished lines.
    steps : ndarray of int
        RK4 steps taken by each line.
    finished : ndarray of bool
        False for lines stopped by ``max_steps`` (their last position is kept).
    stalled : ndarray of bool
        Lines that stopped descending at a null of the field (a saddle point
        exactly on a separatrix, i.e. on a pixel boundary); their last
        position is kept and they count as finished.
    """

    def __init__(self, x, y, z, steps, finished, stalled=None):
        self.x, self.y, self.z, self.steps, self.finished = x, y, z, steps, finished
        self.stalled = np.zeros(x.shape, bool) if stalled is None else stalled

    def __repr__(self):
        return (f"DriftResult(n={self.x.size}, unfinished={int((~self.finished).sum())}, "
                f"mean_steps={self.steps.mean() if self.steps.size else 0:.1f})")


def compile_model(model):
    """Flat arrays of a model's terms for the compiled integrator, or None.

    Returns None when the model has a term the compiled engine does not know
    (e.g. user-supplied field terms); :func:`drift_lines` then uses numpy.
    """
    lines, px, py, pz, ph = [], [], [], [], []
    bd_kind, bd, bd_z, bd_ez = 0, np.zeros(3), np.zeros(2), np.ones(2)
    n_backdrop = 0
    for t in model.terms:
        if isinstance(t, BackdropField):
            bd_kind, bd, n_backdrop = 0, np.array([t.mean_field, t.gradient, t.thickness]), \
                n_backdrop + 1
        elif isinstance(t, TabulatedBackdrop):
            bd_kind, bd_z, bd_ez, n_backdrop = 1, t.z, t.ez_table, n_backdrop + 1
        elif isinstance(t, (LineDipole, PeriodicDipoleGrid, HalfPeriodicDipoleGrid,
                            TruncatedLineDipole)):
            axis = 0.0 if t.axis == "x" else 1.0
            row = [0.0, axis, 0.0, t.position, t.height, t.m_perp, t.m_z, 0.0, 0.0, 0.0]
            if isinstance(t, PeriodicDipoleGrid):
                row[0], row[2], row[7] = 1.0, t.pitch, t.cutoff
            elif isinstance(t, HalfPeriodicDipoleGrid):
                row[0], row[2], row[7], row[8] = 2.0, t.pitch, float(t.side), float(t.n_direct)
            elif isinstance(t, TruncatedLineDipole):
                row[0], row[7], row[8] = 3.0, t.end, float(t.extends)
            lines.append(row)
        elif isinstance(t, PointDipoles):
            px.append(t.x), py.append(t.y), pz.append(t.p_z)
            ph.append(np.full(t.x.size, t.height))
        else:
            return None
    if n_backdrop > 1:
        return None
    cat = (lambda a: np.ascontiguousarray(np.concatenate(a)) if a else np.zeros(0))
    return (np.array(lines, dtype=float).reshape(-1, 10), bd_kind, np.asarray(bd, float),
            np.asarray(bd_z, float), np.asarray(bd_ez, float), cat(px), cat(py), cat(pz),
            cat(ph))


def drift_lines(model, x0, y0, z0=None, *, z_stop=None, step_scale=0.15, min_step=0.02,
                max_step=4.0, max_steps=5000, max_turn=0.2, engine="auto"):
    """Integrate drift lines down to the collection height.

    Parameters
    ----------
    model : SensorModel
        Field model (``model.field(x, y, z)`` in V/um, positions in um).
    x0, y0 : array_like
        Starting lateral positions (um); broadcast together.
    z0 : float or array_like, optional
        Conversion heights (um); default the entrance window
        (``model.params.thickness``).
    z_stop : float, optional
        Collection height (um); default ``model.params.z_collect``.
    step_scale, min_step, max_step : float, optional
        Step control (dimensionless, um, um), see the module docstring.
    max_steps : int, optional
        Safety limit of steps per line.
    max_turn : float, optional
        Largest change of field direction (rad) accepted within one step;
        steps that turn more are retried with a quarter of the length, which
        resolves the turn of lines passing next to a saddle of the field.
    engine : {'auto', 'compiled', 'numpy'}, optional
        'compiled' integrates each line with the numba kernel
        (:func:`lsst_bfdrift.physics._drift_kernels.drift_batch`, same algorithm, lines in
        parallel); 'numpy' steps all lines together with numpy; 'auto' uses
        the compiled engine when every term of the model is known to it.

    Returns
    -------
    DriftResult
        Arrays with the broadcast shape of the inputs.

    Examples
    --------
    Pixel (i, j) spans ``[i p, (i + 1) p)`` in x and ``[j p, (j + 1) p)`` in
    y (p = 10 um). A line that starts 0.2 um inside pixel (0, 0)'s right
    edge lands in that pixel in an empty sensor, and in its neighbour once
    the pixel holds 1e5 electrons:

    >>> from lsst_bfdrift import SensorModel, drift_lines
    >>> empty = SensorModel()
    >>> full = SensorModel(charge={(0, 0): 1e5})
    >>> for model in (empty, full):
    ...     line = drift_lines(model, [9.8], [5.0])
    ...     print(bool(line.finished[0]), [int(k[0]) for k in model.pixel_of(line.x, line.y)])
    True [0, 0]
    True [1, 0]
    """
    P = model.params
    if z0 is None:
        z0 = P.thickness
    if z_stop is None:
        z_stop = P.z_collect
    x0, y0, z0 = np.broadcast_arrays(np.asarray(x0, float), np.asarray(y0, float),
                                     np.asarray(z0, float))
    shape = x0.shape
    if not (np.all(np.isfinite(x0)) and np.all(np.isfinite(y0)) and np.all(np.isfinite(z0))):
        raise InputError("drift starting points must be finite")
    _check_heights(P, z0, z_stop)
    compiled = _kernel_arguments(model, z_stop, step_scale, min_step, max_step, max_steps,
                                 max_turn, engine)
    if compiled is not None:
        n = x0.size
        out = [np.empty(n), np.empty(n), np.empty(n), np.empty(n, np.int64),
               np.empty(n, np.bool_), np.empty(n, np.bool_)]
        # fresh contiguous copies: the inputs may be read-only broadcast views
        drift_batch(np.array(x0, dtype=np.float64).ravel(), np.array(y0, dtype=np.float64).ravel(),
                    np.array(z0, dtype=np.float64).ravel(), *compiled, *out)
        return DriftResult(*(a.reshape(shape) for a in out))
    x = x0.ravel().copy()
    y = y0.ravel().copy()
    z = z0.ravel().copy()
    steps = np.zeros(x.size, dtype=np.int64)
    finished = z <= z_stop
    active = np.flatnonzero(~finished)

    def direction(px, py, pz):
        ex, ey, ez = model.field(px, py, pz)
        norm = np.sqrt(ex * ex + ey * ey + ez * ez) + 1e-300
        return -ex / norm, -ey / norm, -ez / norm, norm

    cos_max = np.cos(max_turn)
    stalled = np.zeros(x.size, dtype=bool)
    idle = np.zeros(x.size, dtype=np.int64)
    h = np.clip(step_scale * (z - z_stop) + min_step, min_step, max_step)
    n_iter = 0
    while active.size and n_iter < max_steps:
        n_iter += 1
        px, py, pz = x[active], y[active], z[active]
        ha = h[active]
        k1 = direction(px, py, pz)
        k2 = direction(px + 0.5 * ha * k1[0], py + 0.5 * ha * k1[1], pz + 0.5 * ha * k1[2])
        k3 = direction(px + 0.5 * ha * k2[0], py + 0.5 * ha * k2[1], pz + 0.5 * ha * k2[2])
        k4 = direction(px + ha * k3[0], py + ha * k3[1], pz + ha * k3[2])
        # Step control: where the field turns by more than max_turn within a
        # step (near a saddle or null of E), retry with a quarter of the step.
        turn_ok = (k1[0] * k4[0] + k1[1] * k4[1] + k1[2] * k4[2] >= cos_max) | (ha <= 1e-7)
        # A line sitting on a null of E (exactly on a separatrix) cannot move:
        # stop it where it is after 40 steps without descent.
        null = k1[3] < 1e-12 * (1.0 + np.abs(k4[3]))
        nx = px + ha / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        ny = py + ha / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        nz = pz + ha / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
        descending = turn_ok & (nz < pz - 1e-6 * ha)
        idle[active] = np.where(descending, 0, idle[active] + 1)
        stuck = null | (idle[active] > 40)
        done = turn_ok & (nz <= z_stop)
        if np.any(done):
            # linear interpolation to the collection plane inside the last step
            f = (pz[done] - z_stop) / (pz[done] - nz[done])
            nx[done] = px[done] + f * (nx[done] - px[done])
            ny[done] = py[done] + f * (ny[done] - py[done])
            nz[done] = z_stop
        x[active] = np.where(turn_ok, nx, px)
        y[active] = np.where(turn_ok, ny, py)
        z[active] = np.where(turn_ok, nz, pz)
        h_base = np.clip(step_scale * (z[active] - z_stop) + min_step, min_step, max_step)
        h[active] = np.where(turn_ok, np.minimum(h_base, 2.0 * ha), 0.25 * ha)
        steps[active] += 1
        stalled[active[stuck & ~done]] = True
        done |= stuck
        finished[active[done]] = True
        active = active[~done]
    return DriftResult(x.reshape(shape), y.reshape(shape), z.reshape(shape),
                       steps.reshape(shape), finished.reshape(shape), stalled.reshape(shape))


def _check_heights(params, z0, z_stop):
    if np.any(z0 > params.thickness + 1e-9) or np.any(z0 < z_stop):
        raise InputError(f"conversion heights must lie in [z_stop={z_stop}, "
                         f"thickness={params.thickness}] um")


def _kernel_arguments(model, z_stop, step_scale, min_step, max_step, max_steps, max_turn,
                      engine):
    """Step settings and model arrays of the compiled integrator, or None (numpy engine)."""
    if engine not in ("auto", "compiled", "numpy"):
        raise InputError(f"engine must be 'auto', 'compiled' or 'numpy', got {engine!r}")
    arrays = None if engine == "numpy" else compile_model(model)
    if engine == "compiled" and arrays is None:
        raise InputError("this model has terms the compiled engine does not support")
    if arrays is None:
        return None
    return (float(z_stop), float(step_scale), float(min_step), float(max_step), int(max_steps),
            float(np.cos(max_turn)), *arrays, COULOMB_UM)


def compiled_line_arguments(model, z0=None, **drift_kwargs):
    """Arguments of the compiled line integrator for lines from one height, or None.

    What :func:`drift_lines` passes to its compiled kernel after the
    starting points, for callers that integrate lines inside their own
    compiled loop (:func:`lsst_bfdrift.physics.boundaries.bisect_boundary`).

    Parameters
    ----------
    model : SensorModel
        The field model.
    z0 : float, optional
        Conversion height (um); default the entrance window.
    **drift_kwargs
        The keyword options of :func:`drift_lines` (same defaults).

    Returns
    -------
    tuple or None
        ``(z0, z_stop, step_scale, min_step, max_step, max_steps, cos_max,
        *model arrays, coulomb)``; None where :func:`drift_lines` would use
        numpy (``engine='numpy'``, or model terms the kernel does not know) or
        ``z0`` is not one number.
    """
    kw = {**_LINE_OPTIONS, **drift_kwargs}
    unknown = set(kw) - set(_LINE_OPTIONS)
    if unknown:
        raise InputError(f"unknown drift line options {sorted(unknown)}")
    P = model.params
    z0 = P.thickness if z0 is None else z0
    if np.ndim(z0) != 0:
        return None
    z0 = float(z0)
    z_stop = P.z_collect if kw["z_stop"] is None else kw["z_stop"]
    if not np.isfinite(z0):
        raise InputError("drift starting points must be finite")
    _check_heights(P, z0, z_stop)
    compiled = _kernel_arguments(model, z_stop, kw["step_scale"], kw["min_step"],
                                 kw["max_step"], kw["max_steps"], kw["max_turn"], kw["engine"])
    return None if compiled is None else (z0, *compiled)


#: The keyword options of :func:`drift_lines` and their defaults.
_LINE_OPTIONS = {k: v.default for k, v in inspect.signature(drift_lines).parameters.items()
                 if v.kind is inspect.Parameter.KEYWORD_ONLY}

def landing_pixels(model, x0, y0, z0=None, **kwargs):
    """Pixel indices (i, j) where drift lines starting at (x0, y0, z0) land.

    Keyword arguments are passed to :func:`drift_lines`.
    """
    res = drift_lines(model, x0, y0, z0, **kwargs)
    return model.pixel_of(res.x, res.y)


def conversion_height(wavelength, thickness, *, z_stop=0.0, rng=None, size=None):
    """Conversion heights (um above the gates) for photons of ``wavelength``.

    Without ``rng`` returns the mean height ``thickness - L`` (L the absorption
    length); with a numpy Generator draws exponential depths. Heights are
    clipped to ``[z_stop, thickness]``.
    """
    L = absorption_length(wavelength)
    if rng is None:
        depth = L
    else:
        depth = rng.exponential(L, size=size)
    return np.clip(thickness - depth, z_stop, thickness)
