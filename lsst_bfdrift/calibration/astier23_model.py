"""The electrostatic model of Astier & Regnault 2023, fitted to an a-matrix.

This is the model behind LSST's ASTIER23 correction (the DP2 route), written
here from the description in P. Astier & N. Regnault 2023, A&A 670, A118,
section on the electrostatic model (no code taken from any implementation).
It serves as a baseline: :func:`fit_astier23` gives the per-edge boundary
shifts ``aN``, ``aS``, ``aE``, ``aW`` that LSST's
``electroBfDistortionMatrix`` carries, from the same a-matrix this package's
own model is fitted to.

The model
---------
* The sensor is a slab of thickness ``thickness`` (pixels) between two
  equipotential planes: the gates (z = 0) and the entrance window
  (z = ``thickness``); charges are mirrored in both (an infinite series of
  images, summed to ``images`` pairs).
* The charge collected in the aggressor pixel is a uniform rectangle of
  ``a`` x ``b`` pixels (serial x parallel) at height ``z_q`` above the gates.
* A pixel boundary is displaced by the integral of the transverse field
  along the drift, from the entrance window (conversions at the top, blue
  light) down to ``z_sv`` for the column boundaries (vertical, set by the
  channel stops below it) and to ``z_sh`` for the row boundaries
  (horizontal, set by the clock barriers), divided by a uniform drift field:
  a normalisation ``alpha`` (per electron) absorbs the drift field and the
  permittivity. The displacement is averaged along each edge.
* The relative area change of pixel (i, j) per electron is the sum of the
  outward shifts of its four edges, a_ij = aN + aS + aE + aW, plus ``beta``
  on a00 alone (a part of the central variance the electrostatics does not
  make, as the paper allows).

Arrays are indexed ``[i, j]`` with i the serial and j the parallel lag,
0 <= i, j <= L, as the package's a-matrix tables (:mod:`lsst_bfdrift.ptc.acoeffs`)
and LSST's distortion matrix are.
"""

import dataclasses
import math

import numpy as np
from scipy.optimize import least_squares

from lsst_bfdrift.utils.errors import FitError, InputError

__all__ = ["Astier23Parameters", "Astier23Fit", "ASTIER23_FREE", "astier23_shifts",
           "astier23_acoeffs", "fit_astier23"]

#: Free parameters of the fit and their bounds (pixels; alpha per electron).
ASTIER23_FREE = {"alpha": (-1e-3, 1e-3), "z_q": (0.02, 2.0), "z_sh": (0.0, 3.0),
                 "z_sv": (0.0, 3.0), "a": (0.05, 0.95), "b": (0.05, 0.95),
                 "beta": (-1e-5, 1e-5)}

# Gauss-Legendre nodes on [-1/2, 1/2] (edge and source rectangle)
_EDGE_NODES = 6
_SOURCE_NODES = 4


@dataclasses.dataclass(frozen=True)
class Astier23Parameters:
    """Parameters of the Astier & Regnault 2023 model (lengths in pixels).

    Attributes
    ----------
    alpha : float
        Normalisation (per electron): displacement per unit of the field
        integral; negative for electrons collected in a p-type sensor (the
        aggressor pushes boundaries away).
    z_q : float
        Height of the collected charge above the gates.
    z_sh, z_sv : float
        Heights below which the row (horizontal) and column (vertical)
        boundaries no longer move.
    a, b : float
        Serial and parallel sides of the charge rectangle.
    beta : float
        Added to a00 alone (per electron).
    thickness : float
        Sensor thickness (10 px: 100 um at 10 um pixels).
    images : int
        Image pairs on each side of the slab.
    """

    alpha: float = -2.0e-7
    z_q: float = 0.25
    z_sh: float = 0.3
    z_sv: float = 0.3
    a: float = 0.5
    b: float = 0.3
    beta: float = 0.0
    thickness: float = 10.0
    images: int = 20

    def replace(self, **changes):
        """A copy with ``changes`` applied."""
        return dataclasses.replace(self, **changes)


def _nodes(n):
    x, w = np.polynomial.legendre.leggauss(n)
    return 0.5 * x, 0.5 * w


def _z_integral(dx, rho2, z0, z1, zc):
    """int_{z0}^{z1} dx / (rho^2 + (z - zc)^2)^(3/2) dz, rho^2 > 0 (closed form)."""
    def prim(z):
        u = z - zc
        return dx * u / (rho2 * np.sqrt(rho2 + u * u))
    return prim(z1) - prim(z0)


def _field_integral(px, py, stop, p):
    """Integral over z from ``stop`` to the top of the transverse field, along x,
    at points (px, py) (arrays of one shape), of a unit charge spread over the
    source rectangle at height z_q and its images (Coulomb's constant left
    out)."""
    t = p.thickness
    xs, ws = _nodes(_SOURCE_NODES)
    # source nodes (S,) and image heights (H,), broadcast against the points
    u = np.repeat(xs * p.a, _SOURCE_NODES)[:, None, None]
    v = np.tile(xs * p.b, _SOURCE_NODES)[:, None, None]
    w = np.outer(ws, ws).ravel()
    k = np.arange(-p.images, p.images + 1, dtype=float)
    zc = np.concatenate([2 * k * t + p.z_q, 2 * k * t - p.z_q])[None, :, None]
    q = np.concatenate([np.ones(k.size), -np.ones(k.size)])[None, :, None]
    dx = np.ravel(px)[None, None, :] - u
    rho2 = dx * dx + (np.ravel(py)[None, None, :] - v) ** 2
    vals = (q * _z_integral(dx, rho2, stop, t, zc)).sum(axis=1)  # (S, points)
    return (w @ vals).reshape(np.shape(px))


def astier23_shifts(params, max_lag=8):
    """Per-edge boundary shifts of pixel (i, j) per electron in pixel (0, 0).

    Parameters
    ----------
    params : Astier23Parameters
    max_lag : int, optional
        Largest lag L.

    Returns
    -------
    aN, aS, aE, aW : ndarray, shape (L + 1, L + 1)
        Outward shifts (pixels per electron), averaged along the edge, of the
        top (+y), bottom (-y), right (+x) and left (-x) edges of pixel [i, j].
    """
    p = params
    if int(max_lag) != max_lag or max_lag < 1:
        raise InputError(f"max_lag must be a positive integer, got {max_lag!r}")
    n = int(max_lag) + 1
    i, j = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    e, we = _nodes(_EDGE_NODES)

    # the field along x at the column boundaries x = i + 1/2, and along y at the row
    # boundaries y = j + 1/2 (roles of x and y swapped), averaged along the edge
    swapped = dataclasses.replace(p, a=p.b, b=p.a)
    east, north = np.zeros((n, n)), np.zeros((n, n))
    for f, w in zip(e, we):
        east += w * _field_integral(i + 0.5, j + f, p.z_sv, p)
        north += w * _field_integral(j + 0.5, i + f, p.z_sh, swapped)
    # the source rectangle is symmetric about its centre, so the field along x is odd
    # in x: the west edge of pixel i is the east edge of pixel i - 1, and at x = -1/2
    # minus the east edge of pixel 0 (likewise south from north)
    west = np.concatenate([-east[:1], east[:-1]], axis=0)
    south = np.concatenate([-north[:, :1], north[:, :-1]], axis=1)
    # outward: +x at the east edge, -x at the west edge (likewise in y)
    return p.alpha * north, -p.alpha * south, p.alpha * east, -p.alpha * west


def astier23_acoeffs(params, max_lag=8):
    """The model's a_ij (per electron), [i serial, j parallel], 0..max_lag.

    The sum of the four outward edge shifts, plus ``beta`` on a00.
    """
    a_n, a_s, a_e, a_w = astier23_shifts(params, max_lag)
    a = a_n + a_s + a_e + a_w
    a[0, 0] += params.beta
    return a


@dataclasses.dataclass
class Astier23Fit:
    """Result of :func:`fit_astier23`.

    Attributes
    ----------
    params : Astier23Parameters
        The best fit.
    names : list of str
        The free parameters.
    errors : dict
        1-sigma errors of the free parameters (from the Jacobian at the
        optimum, scaled by sqrt(chi2/dof) when that exceeds 1).
    covariance : ndarray
        Of the free parameters, same scaling.
    chi2 : float
    dof : int
    model : ndarray
        The model's a_ij over the fitted lags.
    used : ndarray of bool
        The lags in the fit.
    shifts : tuple of ndarray
        aN, aS, aE, aW of the best fit (over the fitted lags).
    """

    params: Astier23Parameters
    names: list
    errors: dict
    covariance: np.ndarray
    chi2: float
    dof: int
    model: np.ndarray
    used: np.ndarray
    shifts: tuple

    @property
    def reduced_chi2(self):
        """chi2 / dof (nan without degrees of freedom)."""
        return self.chi2 / self.dof if self.dof > 0 else math.nan


def fit_astier23(a, sigma, *, fit_range=None, free=("alpha", "z_q", "z_sh", "z_sv", "a", "b"),
                 start=None, use_a00=True, thickness=10.0):
    """Fit the Astier & Regnault 2023 model to a measured a-matrix.

    Parameters
    ----------
    a, sigma : ndarray, shape (L + 1, L + 1)
        Measured a_ij and their 1-sigma errors (per electron), [i serial, j
        parallel]; lags with a non-finite value or error are left out.
    fit_range : int, optional
        Fit lags 0..fit_range - 1 in each direction (LSST's ``fitRange``);
        default all of them.
    free : sequence of str, optional
        Free parameters (names of :data:`ASTIER23_FREE`); the others stay at
        ``start``.
    start : Astier23Parameters, optional
        Starting point; default the class defaults with ``alpha`` scaled to
        the measured a01.
    use_a00 : bool, optional
        Keep a00 in the fit (with ``beta`` free, a00 is fitted exactly and
        says nothing of the other parameters).
    thickness : float, optional
        Sensor thickness in pixels.

    Returns
    -------
    Astier23Fit

    Raises
    ------
    InputError
        Unknown parameter names, arrays of other shapes, negative errors.
    FitError
        Fewer lags than free parameters, or a fit that fails.
    """
    a = np.asarray(a, dtype=float)
    sigma = np.asarray(sigma, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or sigma.shape != a.shape:
        raise InputError(f"a and sigma must be square arrays of one shape, got {a.shape} and "
                         f"{sigma.shape}")
    if np.any(sigma[np.isfinite(sigma)] <= 0):
        raise InputError("a-matrix errors must be positive")
    unknown = [n for n in free if n not in ASTIER23_FREE]
    if unknown:
        raise InputError(f"unknown Astier & Regnault parameters {unknown}; accepted: "
                         f"{sorted(ASTIER23_FREE)}")
    n = a.shape[0] if fit_range is None else int(fit_range)
    if not 2 <= n <= a.shape[0]:
        raise InputError(f"fit_range must be 2..{a.shape[0]}, got {fit_range}")
    a, sigma = a[:n, :n], sigma[:n, :n]
    used = np.isfinite(a) & np.isfinite(sigma)
    if not use_a00:
        used[0, 0] = False
    names = list(free)
    if int(used.sum()) <= len(names):
        raise FitError(f"{int(used.sum())} lags cannot constrain {len(names)} parameters "
                       f"({names})")
    if start is None:
        ref = Astier23Parameters(alpha=-1.0, thickness=thickness)
        a01 = astier23_acoeffs(ref, 1)[0, 1]
        # the model is linear in alpha: a01(alpha) = -alpha * a01(alpha = -1)
        start = ref.replace(alpha=-float(a[0, 1]) / a01 if a01 else ref.alpha)
    x0 = np.array([getattr(start, k) for k in names], dtype=float)
    lo = np.array([ASTIER23_FREE[k][0] for k in names])
    hi = np.array([ASTIER23_FREE[k][1] for k in names])
    x0 = np.clip(x0, lo + 1e-12 * (hi - lo), hi - 1e-12 * (hi - lo))
    scale = np.where(np.abs(x0) > 0, np.abs(x0), 1.0)

    def params_of(x):
        return start.replace(**{k: float(v) for k, v in zip(names, x)})

    def resid(x):
        return ((astier23_acoeffs(params_of(x), n - 1) - a) / sigma)[used]

    try:
        with np.errstate(all="ignore"):
            sol = least_squares(resid, x0, bounds=(lo, hi), x_scale=scale, method="trf")
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise FitError(f"the Astier & Regnault fit failed ({exc})") from exc
    best = params_of(sol.x)
    chi2 = float(np.sum(sol.fun ** 2))
    dof = int(used.sum()) - len(names)
    jac = sol.jac
    cov = np.linalg.pinv(jac.T @ jac)
    if dof > 0 and chi2 / dof > 1.0:
        cov = cov * (chi2 / dof)
    errs = {k: float(math.sqrt(max(cov[m, m], 0.0))) for m, k in enumerate(names)}
    return Astier23Fit(params=best, names=names, errors=errs, covariance=cov, chi2=chi2,
                       dof=dof, model=astier23_acoeffs(best, n - 1), used=used,
                       shifts=astier23_shifts(best, n - 1))
