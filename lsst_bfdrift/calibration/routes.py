"""Three routes from a measured a-matrix to a correction: this package's and LSST's two.

``electrostatic`` (this package)
    The drift model fitted to the a-matrix and refined to it
    (:func:`~lsst_bfdrift.calibration.tuning.calibrate`); corrected with the
    ``drift`` method.
``astier23`` (LSST's DP2 route)
    The electrostatic model of Astier & Regnault 2023 fitted to the a-matrix
    (:func:`~lsst_bfdrift.calibration.astier23_model.fit_astier23`), its per-edge
    shifts aN, aS, aE, aW (LSST's ``electroBfDistortionMatrix``); corrected
    with the ``astier23`` method.
``coulton18`` (LSST's DP1 route)
    The kernel whose discrete Laplacian is the measured a-matrix (Coulton et
    al. 2018; a00 set by the area sum rule over the measured lags, as a
    kernel needs a zero sum; LSST's ``bfk``); corrected with the
    ``coulton18`` method.

Each route gives a :class:`~lsst_bfdrift.templates.template.DistortionTemplate`
the Task takes (``meta['method']`` names the correction it is meant for) and
the route's own product, so that the three can be compared on the same data
(``benchmarks/`` compares them on GalSim stars).
"""

import dataclasses

import numpy as np

from lsst_bfdrift.calibration.astier23_model import ASTIER23_FREE, fit_astier23
from lsst_bfdrift.calibration.lsst_products import BfKernel, DistortionMatrix
from lsst_bfdrift.calibration.tuning import calibrate
from lsst_bfdrift.correction.solvers import coulton18_kernel
from lsst_bfdrift.templates.edge_shifts import template_from_edge_shifts, template_from_kernel
from lsst_bfdrift.utils.errors import FitError, InputError

__all__ = ["MODELS", "ROUTE_METHODS", "RouteResult", "calibrate_route", "astier23_route",
           "coulton18_route", "symmetric_amatrix"]

#: The routes, this package's first.
MODELS = ("electrostatic", "astier23", "coulton18")
#: The correction method each route's template is meant for.
ROUTE_METHODS = {"electrostatic": "drift", "astier23": "astier23", "coulton18": "coulton18"}

#: Free parameters of the Astier & Regnault fit in the astier23 route.
_AR_FREE = ("alpha", "z_q", "z_sh", "z_sv", "a", "b")


@dataclasses.dataclass
class RouteResult:
    """What one route makes of an a-matrix.

    Attributes
    ----------
    model : str
        One of :data:`MODELS`.
    method : str
        The Task's correction method the route uses.
    template : DistortionTemplate
        ``meta['method']`` = ``method``; ``meta['route']`` = ``model``.
    product : object
        :class:`~lsst_bfdrift.calibration.tuning.CalibrationResult`,
        :class:`~lsst_bfdrift.calibration.lsst_products.DistortionMatrix` or
        :class:`~lsst_bfdrift.calibration.lsst_products.BfKernel`.
    chi2, dof : float, int
        Of the route's fit to the a-matrix (the kernel route fits nothing:
        chi2 0, dof 0).
    """

    model: str
    method: str
    template: object
    product: object
    chi2: float
    dof: int

    def summary(self):
        """A JSON-ready summary."""
        return {"model": self.model, "method": self.method, "chi2": float(self.chi2),
                "dof": int(self.dof), "template_size": int(self.template.size)}


def symmetric_amatrix(a):
    """A quadrant a-matrix [i serial, j parallel] (0..L) as the full [dj, di] array
    of lags -L..L (the model is symmetric in the sign of each lag)."""
    a = np.asarray(a, dtype=float)
    n = a.shape[0]
    quad = a.T  # [j, i]
    top = np.concatenate([quad[:, :0:-1], quad], axis=1)
    return np.concatenate([top[:0:-1], top], axis=0)


def coulton18_route(table, *, size=None):
    """LSST's DP1 route: the kernel of the measured a-matrix (Coulton et al. 2018).

    Parameters
    ----------
    table : AcoeffTable
        Measured a_ij (1/e), [i serial, j parallel], lags 0..L; lags without a
        finite value are taken as zero.
    size : int, optional
        Side of the kernel and template (odd, >= 2 L + 1); default 2 L + 1.

    Returns
    -------
    RouteResult
        Product: a :class:`~lsst_bfdrift.calibration.lsst_products.BfKernel`.
    """
    a = np.where(np.isfinite(table.a), table.a, 0.0)
    full = symmetric_amatrix(a)
    n = full.shape[0]
    size = n if size is None else int(size)
    if size % 2 != 1 or size < n:
        raise InputError(f"kernel size must be odd and >= {n} (the a-matrix's lags), got {size}")
    pad = (size - n) // 2
    full = np.pad(full, pad)
    c = size // 2
    full[c, c] = 0.0
    full[c, c] = -full.sum()  # a kernel needs a zero sum: a00 from the sum rule
    kernel = coulton18_kernel(full)
    template = template_from_kernel(kernel, meta={"route": "coulton18", "method": "coulton18",
                                                  "source": "kernel of the measured a-matrix "
                                                            "(Coulton et al. 2018)"})
    return RouteResult("coulton18", "coulton18", template,
                       BfKernel(kernel=kernel, level="DETECTOR"), 0.0, 0)


def astier23_route(table, *, fit_range=None, free=_AR_FREE):
    """LSST's DP2 route: the Astier & Regnault 2023 model fitted to the a-matrix.

    Parameters
    ----------
    table : AcoeffTable
        Measured a_ij with errors; a00 is used when the table measures it.
    fit_range : int, optional
        Lags 0..fit_range - 1 are fitted and their shifts kept (LSST's
        ``fitRange``); default all of the table's.
    free : sequence of str, optional
        Free parameters of the model.

    Returns
    -------
    RouteResult
        Product: a :class:`~lsst_bfdrift.calibration.lsst_products.DistortionMatrix`.

    Raises
    ------
    FitError
        Fewer measured lags than free parameters (a PTC's a00 alone cannot
        constrain the model).
    """
    use_a00 = not getattr(table, "exclude_a00", False)
    measured = int(np.sum(np.isfinite(table.a) & np.isfinite(table.sigma))) - (not use_a00)
    if measured <= len(free):
        raise FitError(f"{getattr(table, 'source', '') or 'the a-matrix'}: the astier23 route "
                       f"fits {len(free)} parameters ({', '.join(free)}) and needs more "
                       f"measured lags than that; this input has {measured} (a PTC of means "
                       "and variances gives a00 alone: give flat pairs, an a-matrix or "
                       "cp_pipe's PTC)")
    fit = fit_astier23(table.a, table.sigma, fit_range=fit_range, free=free, use_a00=use_a00)
    names = list(ASTIER23_FREE)
    params = {k: float(getattr(fit.params, k)) for k in names}
    matrix = DistortionMatrix(
        a_matrix=np.asarray(table.a, float), a_sigma=np.asarray(table.sigma, float),
        a_model=fit.model, shifts=fit.shifts, fit_params=params,
        fit_errors={k: fit.errors.get(k, 0.0) for k in names}, free_params=list(fit.names),
        chi2=fit.chi2, reduced_chi2=fit.reduced_chi2, covariance=fit.covariance,
        used=np.pad(fit.used, (0, table.a.shape[0] - fit.used.shape[0])),
        normalization=[1.0, float(fit.params.beta)])
    template = matrix.template()
    template.meta.update({"route": "astier23", "method": "astier23",
                          "astier23_fit": {"params": params, "errors": matrix.fit_errors,
                                           "chi2": fit.chi2, "dof": fit.dof}})
    return RouteResult("astier23", "astier23", template, matrix, fit.chi2, fit.dof)


def calibrate_route(table, model="electrostatic", **kwargs):
    """The route ``model`` of :data:`MODELS` from a measured a-matrix.

    Parameters
    ----------
    table : AcoeffTable
    model : {'electrostatic', 'astier23', 'coulton18'}
    **kwargs
        Options of the route: :func:`~lsst_bfdrift.calibration.tuning.calibrate`
        (electrostatic), :func:`astier23_route`, :func:`coulton18_route`.

    Returns
    -------
    RouteResult
    """
    if model not in MODELS:
        raise InputError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    if model == "astier23":
        return astier23_route(table, **kwargs)
    if model == "coulton18":
        return coulton18_route(table, **kwargs)
    res = calibrate(table, **kwargs)
    res.template.meta.update({"route": "electrostatic", "method": "drift"})
    return RouteResult("electrostatic", "drift", res.template, res, float(res.fit.chi2),
                       int(res.fit.dof))
