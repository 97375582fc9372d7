"""Fit of the electrostatic model to measured area coefficients a_ij.

This module

* computes the model's a_ij for lags 0..L from drift lines
  (:func:`electrostatic_acoeffs`, symmetric quadrant, fine edge sampling for
  the nearest lags and coarse sampling where the field is smooth),
* fits chosen :class:`~lsst_bfdrift.physics.sensor.SensorParameters` to a
  table (:class:`~lsst_bfdrift.ptc.acoeffs.AcoeffTable`; :func:`fit_acoeffs`)
  with uncertainties, correlations, chi2 per lag and a residual map. The
  fit's Jacobian at the optimum is kept (:class:`AcoeffFit`), so that
  :mod:`lsst_bfdrift.diagnosis.effects_fit` can refit the electrostatic
  parameters in the linear approximation while it tries extra effects,
* linearises the model around a sensor (:class:`LinearBasis`,
  :func:`linear_basis`; the bundled ITL basis: :func:`load_default_basis`).

Arrays of coefficients are indexed ``a[i, j]`` with i the serial lag and j
the parallel lag, 0 <= i, j <= L (the model is symmetric in the sign of each).
"""

import json

import numpy as np

from lsst_bfdrift.calibration.fitting import ParameterFit, fit_parameters
from lsst_bfdrift.physics.boundaries import pixel_boundaries
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.physics.sensor import SensorModel
from lsst_bfdrift.ptc.acoeffs import lag_radius
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.io import data_path

__all__ = ["electrostatic_acoeffs", "AcoeffFit", "fit_acoeffs", "DEFAULT_FREE",
           "LinearBasis", "default_basis_path", "load_default_basis", "linear_basis"]

#: Default free parameters of the fit and their bounds: the barrier dipole
#: scale xi0 (e), the channel-stop strength relative to it (xi0), the channel
#: depth (um) and the backside bias (V, sets the backdrop field).
DEFAULT_FREE = {"xi0": (500.0, 1e5), "xi_cs": (-60.0, -2.0),
                "channel_depth": (0.1, 5.0), "v_bss": (-120.0, -15.0)}



def _quadrant_areas(model, n, edge_samples, tol, spacing, scales=(1.0,)):
    """Pixel areas [i, j] of the quadrant block, with the boundary displacements
    scaled by each of ``scales`` (1 is the traced boundaries)."""
    g = pixel_boundaries(model, (0, n), (0, n), edge_samples=edge_samples, tol=tol,
                         spacing=spacing)
    nom = g.nominal()
    jj, ii = np.mgrid[0:n, 0:n]
    out = []
    for s in scales:
        x, y = pixel_polygons(nom.corners + s * (g.corners - nom.corners),
                              nom.vedge + s * (g.vedge - nom.vedge),
                              nom.hedge + s * (g.hedge - nom.hedge), g.fractions, i0=0, j0=0)
        out.append(polygon_moments(x, y, origin=(ii, jj)).area.T)  # -> [i, j]
    return out


def electrostatic_acoeffs(params, *, max_lag=8, charge=1e5, near_samples=32, far_samples=8,
                          near_lag=1, tol=2e-5, definition="log", near_spacing="uniform",
                          far_spacing="tan"):
    """Model a_ij (per e) for lags 0..max_lag.

    ``definition='log'`` gives ln(A_ij) / Q for the boundaries traced with
    charge Q. ``'alpha'`` gives the linear response d A_ij / d Q at Q = 0 of
    the template built from those boundaries (displacements scaled linearly
    in the charge, as the template is used): from the areas with the
    displacements scaled by 1 and 1/2, alpha = (4 (A(Q/2) - 1) - (A(Q) - 1))
    / Q, exact for areas quadratic in the displacements. This is the a_ij of
    the covariance model of Astier et al. (2019), which flats measure.

    The model is symmetric about both pixel axes, so only the quadrant
    i, j >= 0 is traced. Lags up to ``near_lag`` (both axes) come from
    ``near_samples`` samples per edge (their boundaries bend most); the
    others from ``far_samples`` samples, where the far field is smooth.

    The areas are those of the polygons through the samples, so they carry
    a discretisation error: next to the aggressor the boundaries bend
    sharply into its corners, which uniformly spaced samples resolve poorly.
    At the calibration fit's settings (16 uniform / 6 'tan' samples) the
    a_ij of lags 0-2 differ from their converged values by up to ~18 % (a10
    of the bundled template's sensor); 'ends' spacing (Chebyshev nodes)
    with 32 / 12 samples brings every lag 0-3 within ~1 %
    (``benchmarks/calibration/model_convergence.py``).

    Parameters
    ----------
    params : SensorParameters
        Model parameters; must have no fixed-pattern features.
    max_lag : int, optional
        Largest lag L.
    charge : float, optional
        Aggressor charge Q (e) used for the finite difference.
    near_samples, far_samples : int, optional
        Samples per edge.
    near_lag : int, optional
        Largest lag computed with ``near_samples``.
    tol : float, optional
        Bisection tolerance (pixel units).
    definition : {'log', 'alpha'}, optional
        Which a_ij (see above).
    near_spacing, far_spacing : {'uniform', 'tan', 'ends'}, optional
        Placement of the samples along the edges
        (:func:`~lsst_bfdrift.physics.boundaries.edge_fractions`).

    Returns
    -------
    ndarray, shape (max_lag + 1, max_lag + 1)
        a[i, j] per e.
    """
    if (params.bloom_stop is not None or params.edge is not None or params.column_overrides
            or params.row_overrides or params.row_shifts or params.truncations):
        raise InputError("electrostatic_acoeffs needs a model without fixed-pattern features "
                         "(the quadrant symmetry is used)")
    L = int(max_lag)
    if L < 1:
        raise InputError(f"max_lag must be >= 1, got {max_lag}")
    if definition not in ("log", "alpha"):
        raise InputError(f"definition must be 'log' or 'alpha', got {definition!r}")
    scales = (1.0,) if definition == "log" else (1.0, 0.5)
    model = SensorModel(params).with_charge({(0, 0): float(charge)})
    k = min(int(near_lag), L) + 1
    near = _quadrant_areas(model, k, near_samples, tol, near_spacing, scales)
    if k == L + 1:  # the near lags are all of them
        areas = near
    else:
        far = _quadrant_areas(model, L + 1, far_samples, tol, far_spacing, scales)
        areas = []
        for f, nr in zip(far, near):
            a = f.copy()
            a[:k, :k] = nr
            areas.append(a)
    if definition == "log":
        return np.log(areas[0]) / float(charge)
    return (4.0 * (areas[1] - 1.0) - (areas[0] - 1.0)) / float(charge)


class AcoeffFit(ParameterFit):
    """Result of :func:`fit_acoeffs`: a
    :class:`~lsst_bfdrift.calibration.fitting.ParameterFit` of a_ij.

    Attributes
    ----------
    params : SensorParameters
        Best fit.
    names : list of str
        Free parameters.
    values, errors : dict
        Best-fit values and 1-sigma errors (from the Jacobian, not scaled by
        chi2/dof).
    covariance : ndarray
        Parameter covariance (order of ``names``).
    correlation : ndarray
        Correlation matrix (order of ``names``).
    model, data, sigma : ndarray, shape (L + 1, L + 1)
        Model and measured a_ij and errors (per e).
    mask : ndarray of bool
        Lags in chi2.
    jacobian : ndarray, shape (L + 1, L + 1, n_free)
        d a_ij / d parameter at the best fit (per e per parameter unit).
    chi2, dof : float, int
    seconds : float
        Wall time of the fit.
    n_evaluations : int
        Model evaluations.
    """

    @property
    def chi2_per_lag(self):
        """Pull squared per lag (0 where not in chi2); sums to ``chi2``."""
        return np.where(self.mask, self.pulls, 0.0) ** 2

    def chi2_by_radius(self):
        """{rounded radius: (chi2, number of lags)} in rings of width 1."""
        r = np.rint(lag_radius(self.data.shape[0] - 1)).astype(int)
        c = self.chi2_per_lag
        return {int(k): (float(c[(r == k) & self.mask].sum()), int(((r == k) & self.mask).sum()))
                for k in np.unique(r[self.mask])}

    def as_dict(self):
        """JSON-friendly summary."""
        return {**super().as_dict(), "model": self.model.tolist(),
                "data": self.data.tolist(), "sigma": self.sigma.tolist(),
                "pulls": np.where(self.mask, self.pulls, 0.0).tolist(),
                "chi2_by_radius": {str(k): v for k, v in self.chi2_by_radius().items()}}


def fit_acoeffs(table, params0, free=None, *, model=None, diff_step=0.02, max_evaluations=30,
                jacobian0=None, progress=False, **model_kwargs):
    """Fit sensor parameters to a table of a_ij.

    Parameters
    ----------
    table : AcoeffTable
        Measured coefficients, [serial, parallel].
    params0 : SensorParameters
        Start; parameters not in ``free`` stay fixed.
    free : dict, optional
        ``{name: (lower, upper)}``; default :data:`DEFAULT_FREE`.
    model : callable, optional
        ``model(params) -> a[i, j]``; default :func:`electrostatic_acoeffs`
        with ``max_lag`` of the table and ``model_kwargs``.
    diff_step : float, optional
        Relative step of the central-difference derivatives.
    max_evaluations : int, optional
        Model evaluations of the search (:func:`~lsst_bfdrift.calibration.fitting.fit_parameters`;
        the final Jacobian adds 2 per free parameter).
    jacobian0 : ndarray, shape (L + 1, L + 1, n_free), optional
        d a_ij / d parameter near the start (e.g. :attr:`LinearBasis.jacobian`);
        default: central differences at the start.
    progress : bool, optional
        Progress bar on stderr (one tick per model evaluation).

    Returns
    -------
    AcoeffFit
    """
    free = dict(DEFAULT_FREE if free is None else free)
    if not free:
        raise InputError("no free parameters given")
    names = list(free)
    for n in names:
        lo, hi = free[n]
        if not lo < getattr(params0, n) < hi:
            raise InputError(f"start value of {n!r} ({getattr(params0, n)}) is outside its "
                             f"bounds {free[n]}")
    L = table.max_lag
    if model is None:
        def model(p):
            return electrostatic_acoeffs(p, max_lag=L, **model_kwargs)
    mask = table.mask()
    if mask.sum() <= len(names):
        raise InputError(f"{mask.sum()} lags cannot constrain {len(names)} parameters")
    fit = fit_parameters(lambda v: model(params0.replace(**v)), table.a, table.sigma,
                         {n: float(getattr(params0, n)) for n in names}, free, mask=mask,
                         jacobian0=jacobian0, diff_step=diff_step,
                         max_evaluations=max_evaluations, central=True, progress=progress)
    return AcoeffFit(**{**vars(fit), "params": params0.replace(**fit.values),
                        "data": table.a.copy(), "sigma": table.sigma.copy(),
                        "axis_note": table.axis_note, "source": table.source})


class LinearBasis:
    """Electrostatic a_ij linearised about a fit: a(x) = a0 + J (x - x0).

    Parameters
    ----------
    a0 : ndarray, shape (L + 1, L + 1)
        Model a_ij at ``x0`` (per e).
    jacobian : ndarray, shape (L + 1, L + 1, n)
        d a_ij / d x_k.
    names : list of str
        Parameter names (SensorParameters fields).
    x0, errors : dict
        Parameter values at the expansion point and their errors from the fit.
    """

    def __init__(self, a0, jacobian, names, x0, errors=None, *, note=""):
        self.a0 = np.asarray(a0, float)
        self.jacobian = np.asarray(jacobian, float)
        self.names = list(names)
        self.x0 = {n: float(x0[n]) for n in self.names}
        self.errors = {n: float((errors or {}).get(n, abs(self.x0[n]) * 0.1 or 1.0))
                       for n in self.names}
        self.note = note
        if self.jacobian.shape != self.a0.shape + (len(self.names),):
            raise InputError("jacobian shape does not match a0 and names")

    @property
    def max_lag(self):
        """Largest lag L."""
        return self.a0.shape[0] - 1

    @classmethod
    def from_fit(cls, fit, *, note=""):
        """From an :class:`AcoeffFit`."""
        return cls(fit.model, fit.jacobian, fit.names, fit.values, fit.errors, note=note)

    def a(self, x, max_lag=None):
        """a_ij (per e) at parameters ``x`` (sequence in ``names`` order)."""
        d = np.asarray(x, float) - np.array([self.x0[n] for n in self.names])
        out = self.a0 + self.jacobian @ d
        k = out.shape[0] if max_lag is None else int(max_lag) + 1
        return out[:k, :k]

    def with_scales(self, groups, *, error=0.05):
        """This basis plus one scale direction per group of lags.

        Scale ``scale{k}`` (1 at the expansion point) multiplies the a_ij of
        group k: a_ij += (s_k - 1) a0_ij for (i, j) in the group. It lets
        a base model follow a sensor's a-matrix beyond what the linearised
        electrostatics can (``benchmarks/diagnosis/diagnose_base_model.py``: the
        diagnosis' false alarms on large flat sets of other sensors vanish
        with scales for a00, a01 and a10).

        Parameters
        ----------
        groups : sequence of sequence of (int, int)
            Lags (i serial, j parallel) of each scale.
        error : float, optional
            The scales' prior error (the diagnosis' step scale).

        Returns
        -------
        LinearBasis
        """
        L = self.max_lag
        cols, names = [self.jacobian], list(self.names)
        x0, err = dict(self.x0), dict(self.errors)
        for k, group in enumerate(groups):
            col = np.zeros_like(self.a0)
            for i, j in group:
                if not (0 <= int(i) <= L and 0 <= int(j) <= L):
                    raise InputError(f"lag ({i}, {j}) is outside the basis' lags 0..{L}")
                col[int(i), int(j)] = self.a0[int(i), int(j)]
            name = f"scale{k}"
            if name in names:
                raise InputError(f"the basis already has a parameter {name!r}")
            cols.append(col[..., None])
            names.append(name)
            x0[name], err[name] = 1.0, float(error)
        return LinearBasis(self.a0, np.concatenate(cols, axis=-1), names, x0, err,
                           note=(self.note + "; " if self.note else "")
                           + f"scales of {[list(map(tuple, g)) for g in groups]}")

    def dlog_depth(self, max_lag=None):
        """D_ij = d a_ij / d ln(channel depth) at x0 (per e)."""
        if "channel_depth" not in self.names:
            raise InputError("the basis has no channel_depth derivative")
        k = self.names.index("channel_depth")
        d = self.jacobian[..., k] * self.x0["channel_depth"]
        m = d.shape[0] if max_lag is None else int(max_lag) + 1
        return d[:m, :m]

    def to_dict(self):
        """JSON-friendly form."""
        return {"a0": self.a0.tolist(), "jacobian": self.jacobian.tolist(), "names": self.names,
                "x0": self.x0, "errors": self.errors, "note": self.note}

    @classmethod
    def from_dict(cls, d):
        """Inverse of :meth:`to_dict`."""
        return cls(d["a0"], d["jacobian"], d["names"], d["x0"], d.get("errors"),
                   note=d.get("note", ""))


def default_basis_path():
    """Path of the shipped basis (the electrostatic fit to the ITL a_ij)."""
    return data_path("itl_acoeff_basis.json")


def load_default_basis():
    """The shipped :class:`LinearBasis` (written by ``benchmarks/diagnosis/diagnose_itl.py``)."""
    with open(default_basis_path()) as fh:
        return LinearBasis.from_dict(json.load(fh))


def linear_basis(params, names=None, *, max_lag=8, rel_step=0.02, model=None, note="",
                 **model_kwargs):
    """:class:`LinearBasis` about ``params`` by central differences.

    Parameters
    ----------
    params : SensorParameters
        Expansion point.
    names : sequence of str, optional
        Parameters (default: those of :data:`DEFAULT_FREE`).
    max_lag : int, optional
        Largest lag.
    rel_step : float, optional
        Relative step of the differences.
    model : callable, optional
        ``model(params) -> a[i, j]``; default :func:`electrostatic_acoeffs`.
    """
    names = list(DEFAULT_FREE if names is None else names)
    if model is None:
        def model(p):
            return electrostatic_acoeffs(p, max_lag=max_lag, **model_kwargs)
    a0 = np.asarray(model(params), float)
    jac = np.zeros(a0.shape + (len(names),))
    for k, n in enumerate(names):
        v = float(getattr(params, n))
        h = rel_step * (abs(v) if v != 0 else 1.0)
        jac[..., k] = (np.asarray(model(params.replace(**{n: v + h})))
                       - np.asarray(model(params.replace(**{n: v - h})))) / (2 * h)
    return LinearBasis(a0, jac, names, {n: float(getattr(params, n)) for n in names},
                       note=note)
