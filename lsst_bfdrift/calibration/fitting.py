"""One fit engine: model parameters against measured numbers with errors.

Every fit of the package's model to data goes through :func:`fit_parameters`:
the a-matrix fit of the electrostatic model
(:func:`~lsst_bfdrift.calibration.acoeff_model.fit_acoeffs`), the fit of
template numbers (:func:`~lsst_bfdrift.calibration.sensor_fit.fit_sensor_parameters`),
:func:`~lsst_bfdrift.calibration.tuning.calibrate` and the fits of base model
plus effects in :func:`~lsst_bfdrift.diagnosis.effects_fit.diagnose`.

The model is a callable of a parameter dict returning an array shaped like
the data. The engine minimises chi2 = sum(((model - data) / sigma)^2) over
the points in ``mask`` with a bounded Levenberg-Marquardt iteration in
scaled parameters. Bounds are handled by an active set: a parameter held on
a bound by the gradient is taken out of the step and the others are solved
for without it, so that strongly correlated parameters still reach the
constrained optimum when one of them ends on a bound. Model evaluations are
the expensive part (each is a set of drift-line bisections), so the engine

* accepts a starting Jacobian (``jacobian0``: e.g. from a linear basis, an
  emulator of the model) and then updates it by Broyden's rank-one rule from
  the evaluations the iteration makes anyway, so that a step costs one
  evaluation;
* computes the Jacobian by finite differences only where no start is given
  and, at the end, once at the optimum (``final_jacobian``), for the
  parameter covariance;
* caches every evaluation.

The covariance is (J^T W J)^-1 at the optimum, not scaled by chi2/dof (the
errors of the data are taken as given; a poor chi2 is reported, not hidden).
"""

import math
import time

import numpy as np
from scipy import stats

from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.utils.errors import FitError

__all__ = ["ParameterFit", "fit_parameters", "FitError"]


class ParameterFit:
    """Result of :func:`fit_parameters`.

    Attributes
    ----------
    names : list of str
        Free parameters, in the order of the matrices.
    values, errors : dict
        Best-fit values and 1-sigma errors (from the covariance).
    start : dict
        Starting values.
    covariance, correlation : ndarray, shape (n, n)
        Parameter covariance (units of the parameters squared) and
        correlation.
    data, sigma, model : ndarray
        Measured numbers, their errors and the model at the best fit (shape
        of the data).
    mask : ndarray of bool
        Points in chi2.
    jacobian : ndarray, shape data.shape + (n,)
        d model / d parameter at the best fit (finite differences when
        ``final_jacobian``; else the engine's updated estimate).
    chi2 : float
    dof : int
    n_evaluations : int
        Model evaluations made.
    seconds : float
        Wall time.
    converged : bool
        The change of chi2 fell below the tolerance.
    at_bound : list of str
        Parameters that ended within 1e-4 of the span of a bound: their
        errors describe the curvature there, not a confidence interval.
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    @property
    def chi2_dof(self):
        """chi2 per degree of freedom (inf without degrees of freedom)."""
        return self.chi2 / self.dof if self.dof > 0 else math.inf

    @property
    def p_value(self):
        """Probability of a chi2 this large or larger for ``dof`` degrees of freedom."""
        return float(stats.chi2.sf(self.chi2, self.dof)) if self.dof > 0 else math.nan

    @property
    def residual(self):
        """Data minus model, NaN where not in chi2."""
        return np.where(self.mask, self.data - self.model, np.nan)

    @property
    def pulls(self):
        """(data - model) / sigma, NaN where not in chi2."""
        return self.residual / self.sigma

    def worst(self, n=3):
        """The ``n`` points with the largest absolute pull: list of (index, pull)."""
        p = np.where(self.mask, np.abs(np.nan_to_num(self.pulls)), -1.0)
        order = np.argsort(p, axis=None)[::-1][:n]
        return [(tuple(int(v) for v in np.unravel_index(k, p.shape)),
                 float(self.pulls[np.unravel_index(k, p.shape)])) for k in order
                if p.flat[k] >= 0]

    def as_dict(self):
        """JSON-friendly summary."""
        return {"names": self.names, "values": self.values, "errors": self.errors,
                "start": self.start, "covariance": np.asarray(self.covariance).tolist(),
                "correlation": np.asarray(self.correlation).tolist(), "chi2": self.chi2,
                "dof": self.dof, "chi2_dof": self.chi2_dof, "p_value": self.p_value,
                "n_evaluations": self.n_evaluations, "seconds": self.seconds,
                "converged": self.converged, "at_bound": self.at_bound}


def _check_inputs(data, sigma, mask, start, bounds):
    data = np.asarray(data, dtype=float)
    sigma = np.broadcast_to(np.asarray(sigma, dtype=float), data.shape)
    mask = np.ones(data.shape, bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != data.shape:
        raise FitError(f"mask shape {mask.shape} does not match the data {data.shape}")
    if not np.all(np.isfinite(data[mask])):
        raise FitError("data in the fit hold NaN or inf")
    if not (np.all(np.isfinite(sigma[mask])) and np.all(sigma[mask] > 0)):
        raise FitError("errors of the data in the fit must be finite and positive")
    names = list(start)
    if not names:
        raise FitError("no free parameters given")
    missing = [n for n in names if n not in bounds]
    if missing:
        raise FitError(f"no bounds for {missing}")
    for n in names:
        lo, hi = bounds[n]
        if not lo < start[n] < hi:
            raise FitError(f"start value of {n!r} ({start[n]:.6g}) is outside its bounds "
                           f"({lo:.6g}, {hi:.6g})")
    if mask.sum() < len(names):
        raise FitError(f"{int(mask.sum())} data points cannot constrain {len(names)} "
                       f"parameters")
    return data, sigma, mask, names


def _bounded_step(A, r, x, scale, lo, hi, lam):
    """Levenberg-Marquardt step from ``x`` that respects the box [lo, hi].

    ``A`` is the weighted Jacobian in scaled parameters u = x / scale and
    ``r`` the weighted residual. A parameter on a bound whose gradient points
    out of the box is held there, and the step is solved for the others
    alone; a parameter that the step would carry across a bound is put on
    it and the step solved again for the rest (which then take up what it
    cannot do). Clipping the full step instead loses the compensation of
    correlated parameters and stalls the descent. Returns the new point.
    """
    g = A.T @ r
    H = A.T @ A
    M = H + lam * np.diag(np.maximum(np.diag(H), 1e-12))
    ulo, uhi, u = lo / scale, hi / scale, x / scale
    tiny = 1e-9 * np.maximum(np.abs(u), 1.0)
    fixed = ((u - ulo <= tiny) & (g > 0)) | ((uhi - u <= tiny) & (g < 0))
    du = np.zeros_like(u)
    du[fixed] = np.clip(u, ulo, uhi)[fixed] - u[fixed]
    for _ in range(u.size + 1):
        free = ~fixed
        if not np.any(free):
            break
        rhs = -(g[free] + M[np.ix_(free, fixed)] @ du[fixed])
        Mf = M[np.ix_(free, free)]
        try:
            du[free] = np.linalg.solve(Mf, rhs)
        except np.linalg.LinAlgError:
            du[free] = np.linalg.lstsq(Mf, rhs, rcond=None)[0]
        un = u + du
        out = free & ((un < ulo) | (un > uhi))
        if not np.any(out):
            break
        du[out] = np.clip(un, ulo, uhi)[out] - u[out]
        fixed = fixed | out
    return np.clip((u + du) * scale, lo, hi)


def fit_parameters(model, data, sigma, start, bounds, *, mask=None, jacobian0=None,
                   diff_step=0.02, max_evaluations=40, tol=1e-3, final_jacobian=True,
                   central=False, update="broyden", progress=False, callback=None):
    """Least-squares fit of model parameters to measured numbers.

    Parameters
    ----------
    model : callable
        ``model(values) -> ndarray`` shaped like ``data``; ``values`` is a
        dict {name: float}.
    data, sigma : array_like
        Measured numbers and their 1-sigma errors (same units as the model).
    start : dict
        {name: starting value} of the free parameters.
    bounds : dict
        {name: (lower, upper)}; the fit stays strictly inside.
    mask : array_like of bool, optional
        Points in chi2 (default all).
    jacobian0 : array_like, shape data.shape + (n,), optional
        d model / d parameter near the start (parameter order of ``start``),
        e.g. from a linear basis. Default: finite differences at the start.
    diff_step : float, optional
        Finite-difference step, relative to max(abs(value), 1e-3 x bound span).
    max_evaluations : int, optional
        Model evaluations allowed for the search (the final Jacobian adds n
        or 2n more).
    tol : float, optional
        Stop when an accepted step lowers chi2 by less than ``tol``, or when
        the next step would change chi2 by less than ``tol`` in the local
        linear model (absolute: 1e-3 leaves the parameters within about 0.03
        sigma of the optimum; without the second rule a fit at its optimum
        spends ~18 evaluations raising the damping until it gives up).
    final_jacobian : bool, optional
        Recompute the Jacobian by finite differences at the optimum for the
        covariance (recommended; otherwise the updated estimate is used).
    central : bool, optional
        Central instead of forward differences (2n instead of n evaluations).
    update : {'broyden', 'exact'}, optional
        After a step, update the Jacobian by Broyden's rule (one evaluation a
        step; for expensive models) or recompute it by finite differences
        after every accepted step (for cheap models with many parameters,
        where Broyden's estimate converges slowly).
    progress : bool, optional
        Progress bar on stderr, one tick per model evaluation.
    callback : callable, optional
        ``callback(values, chi2)`` after each accepted step.

    Returns
    -------
    ParameterFit

    Raises
    ------
    FitError
        Inconsistent input, or a model that returns the wrong shape or
        non-finite values at the start.
    """
    t0 = time.perf_counter()
    if update not in ("broyden", "exact"):
        raise FitError(f"update must be 'broyden' or 'exact', got {update!r}")
    data, sigma, mask, names = _check_inputs(data, sigma, mask, start, bounds)
    n = len(names)
    x0 = np.array([float(start[k]) for k in names])
    lo = np.array([float(bounds[k][0]) for k in names])
    hi = np.array([float(bounds[k][1]) for k in names])
    span = hi - lo
    scale = np.where(np.isfinite(span), np.maximum(np.abs(x0), 1e-3 * span), np.abs(x0))
    scale = np.where(scale > 0, scale, 1.0)
    cache = {}
    extra = (2 if central else 1) * n if final_jacobian else 0
    bar = ProgressBar(max_evaluations + extra + n, "fit", enabled=progress)

    def evaluate(x):
        key = tuple(np.round(x / scale, 12))
        if key not in cache:
            m = np.asarray(model(dict(zip(names, map(float, x)))), dtype=float)
            if m.shape != data.shape:
                raise FitError(f"model returned shape {m.shape}, data have {data.shape}")
            cache[key] = m
            bar(1)
        return cache[key]

    def weighted(m):
        return ((m - data) / sigma)[mask]

    def fd_jacobian(x):
        cols = []
        for k in range(n):
            col = None
            for sgn in (1.0, -1.0, 0.25, -0.25):  # the other side, then a smaller step,
                h = diff_step * scale[k]            # where the model fails
                xp = x.copy()
                xp[k] = x[k] + sgn * h
                if not lo[k] < xp[k] < hi[k]:
                    continue
                if central:
                    xm = x.copy()
                    xm[k] = x[k] - sgn * h
                    if not lo[k] < xm[k] < hi[k]:
                        xm = x
                    c = (evaluate(xp) - evaluate(xm)) / (xp[k] - xm[k])
                else:
                    c = (evaluate(xp) - evaluate(x)) / (xp[k] - x[k])
                if np.all(np.isfinite(c[mask])):
                    col = c
                    break
            cols.append(np.zeros(data.shape) if col is None else np.nan_to_num(col))
        return np.stack(cols, axis=-1)

    m0 = evaluate(x0)
    if not np.all(np.isfinite(m0[mask])):
        raise FitError("model is not finite at the start values")
    if jacobian0 is None:
        J = fd_jacobian(x0)
    else:
        J = np.array(jacobian0, dtype=float)
        if J.shape != data.shape + (n,):
            raise FitError(f"jacobian0 has shape {J.shape}, expected {data.shape + (n,)}")
    # work in scaled parameters u = x / scale; A = weighted Jacobian in u
    w = (1.0 / sigma)[mask]
    A = J[mask] * w[:, None] * scale[None, :]
    x, r = x0.copy(), weighted(m0)
    chi2 = float(r @ r)
    margin = 1e-6 * np.where(np.isfinite(span), span, 0)
    lo_in, hi_in = lo + margin, hi - margin  # the iteration stays strictly inside
    lam = 1e-3
    converged = False
    n_start = len(cache)
    while len(cache) - n_start < max_evaluations:
        xn = _bounded_step(A, r, x, scale, lo_in, hi_in, lam)
        step = (xn - x) / scale
        if not np.any(step) or float(np.sum((A @ step) ** 2)) < tol:
            # the step would change chi2 by less than tol in the local linear
            # model (a move of under ~sqrt(tol) sigma): the model's own
            # noise would decide it, so it is not taken
            converged = True
            break
        mn = evaluate(xn)
        rn = weighted(mn)
        if not np.all(np.isfinite(rn)):
            lam *= 10.0
            continue
        chi2n = float(rn @ rn)
        if update == "broyden":
            # Broyden's rank-one update from this evaluation (accepted or not)
            dr = rn - r - A @ step
            A = A + np.outer(dr, step) / (step @ step)
        if chi2n < chi2:
            gain = chi2 - chi2n
            x, r, chi2 = xn, rn, chi2n
            if update == "exact":
                A = fd_jacobian(x)[mask] * w[:, None] * scale[None, :]
            lam = max(lam / 3.0, 1e-7)
            if callback is not None:
                callback(dict(zip(names, map(float, x))), chi2)
            if gain < tol:
                converged = True
                break
        else:
            lam *= 4.0
            if lam > 1e8:
                converged = True  # no descent left in the local model
                break
    if final_jacobian:
        J = fd_jacobian(x)
        A = J[mask] * w[:, None] * scale[None, :]
    else:
        J = np.zeros(data.shape + (n,))
        J[mask] = A / w[:, None] / scale[None, :]
    cov_u = np.linalg.pinv(A.T @ A)
    cov = cov_u * np.outer(scale, scale)
    err = np.sqrt(np.clip(np.diag(cov), 0, None))
    dead = ~np.any(A, axis=0)  # no derivative could be taken: unconstrained
    err[dead] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(err, err)
    bar.done = bar.total
    if progress:
        bar._draw(final=True)
    near = np.isfinite(span) & ((x - lo < 1e-4 * span) | (hi - x < 1e-4 * span))
    return ParameterFit(at_bound=[k for k, b in zip(names, near) if b], names=names,
                        values=dict(zip(names, map(float, x))),
                        errors=dict(zip(names, map(float, err))),
                        start=dict(zip(names, map(float, x0))), covariance=cov,
                        correlation=corr, data=data, sigma=np.array(sigma), model=evaluate(x),
                        mask=mask, jacobian=J, chi2=chi2, dof=int(mask.sum() - n),
                        n_evaluations=len(cache), seconds=time.perf_counter() - t0,
                        converged=converged)
