"""Fit of the electrostatic model to measured area coefficients a_ij.

Measured area coefficients a_ij (per electron; Astier et al. 2019) are the
relative area change of the pixel at lag (i, j) = (serial, parallel) per
electron collected in the aggressor pixel, a_ij = d ln A_ij / dQ. This module

* reads tables of a_ij with errors (:func:`read_acoeff_table`),
* establishes which file axis is parallel from the data
  (:func:`assign_axes`: the larger nearest neighbour is the parallel one,
  because the clock barriers are weaker than the channel stops) and whether
  a00 was set by the area sum rule (:func:`sum_rule_check`),
* computes the model's a_ij for lags 0..L from drift lines
  (:func:`electrostatic_acoeffs`, symmetric quadrant, fine edge sampling for
  the nearest lags and coarse sampling where the field is smooth),
* fits chosen :class:`~lsst_bfdrift.physics.sensor.SensorParameters` to the table
  (:func:`fit_acoeffs`) with uncertainties, correlations, chi2 per lag and a
  residual map. The fit's Jacobian at the optimum is kept
  (:class:`AcoeffFit`), so that :mod:`lsst_bfdrift.calibration.diagnosis` can refit the
  electrostatic parameters in the linear approximation while it tries extra
  effects.

Arrays of coefficients are indexed ``a[i, j]`` with i the serial lag and j
the parallel lag, 0 <= i, j <= L (the model is symmetric in the sign of each).
"""

import math

import numpy as np

from lsst_bfdrift.calibration.fitting import ParameterFit, fit_parameters
from lsst_bfdrift.utils.io import data_path
from lsst_bfdrift.physics.boundaries import pixel_boundaries
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.physics.sensor import SensorModel
from lsst_bfdrift.utils.errors import InputError

__all__ = ["AcoeffTable", "read_acoeff_table", "assign_axes", "sum_rule_check",
           "electrostatic_acoeffs", "AcoeffFit", "fit_acoeffs", "DEFAULT_FREE",
           "lag_radius", "acoeff_square", "LinearBasis", "default_basis_path",
           "load_default_basis", "linear_basis", "MAX_TABLE_LAG"]

#: Largest lag an a_ij table may hold (measured tables reach ~20; a larger
#: lag is a typo, and the square arrays grow as its square).
MAX_TABLE_LAG = 64

#: Default free parameters of the fit and their bounds: the barrier dipole
#: scale xi0 (e), the channel-stop strength relative to it (xi0), the channel
#: depth (um) and the backside bias (V, sets the backdrop field).
DEFAULT_FREE = {"xi0": (500.0, 1e5), "xi_cs": (-60.0, -2.0),
                "channel_depth": (0.1, 5.0), "v_bss": (-120.0, -15.0)}


def lag_radius(max_lag):
    """Array r[i, j] = sqrt(i^2 + j^2) for 0 <= i, j <= max_lag."""
    i, j = np.meshgrid(np.arange(max_lag + 1), np.arange(max_lag + 1), indexing="ij")
    return np.hypot(i, j)


class AcoeffTable:
    """Measured a_ij (per e) with 1-sigma errors, indexed [serial, parallel].

    Attributes
    ----------
    a, sigma : ndarray, shape (L + 1, L + 1)
        Coefficients and errors (per e).
    max_lag : int
    source : str
        Where the table came from.
    axis_note : str
        How the axis assignment was established.
    exclude_a00 : bool
        True when a00 must be left out of chi2 (set by the sum rule).
    """

    def __init__(self, a, sigma, *, source="", axis_note="", exclude_a00=False):
        a = np.array(a, dtype=np.float64)
        sigma = np.array(sigma, dtype=np.float64)
        if a.ndim != 2 or a.shape[0] != a.shape[1]:
            raise InputError(f"a_ij must be a square 2-d array, got shape {a.shape}")
        if sigma.shape != a.shape:
            raise InputError(f"errors have shape {sigma.shape}, coefficients {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InputError("a_ij table holds non-finite coefficients")
        if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
            raise InputError("a_ij errors must be finite and positive (found NaN, inf, zero "
                             "or negative errors)")
        self.a, self.sigma = a, sigma
        self.max_lag = a.shape[0] - 1
        self.source, self.axis_note, self.exclude_a00 = source, axis_note, bool(exclude_a00)

    def mask(self):
        """Boolean array of the lags that enter chi2."""
        m = np.ones(self.a.shape, dtype=bool)
        if self.exclude_a00:
            m[0, 0] = False
        return m

    def transposed(self):
        """The table with the two axes exchanged."""
        return AcoeffTable(self.a.T, self.sigma.T, source=self.source,
                           axis_note=self.axis_note, exclude_a00=self.exclude_a00)

    def truncated(self, max_lag):
        """The table restricted to lags <= ``max_lag``."""
        k = int(max_lag) + 1
        return AcoeffTable(self.a[:k, :k], self.sigma[:k, :k], source=self.source,
                           axis_note=self.axis_note, exclude_a00=self.exclude_a00)


def acoeff_square(path, i, j, a, s):
    """Checked square arrays a[i, j], sigma[i, j] from row values."""
    i = np.asarray(i, dtype=float)
    j = np.asarray(j, dtype=float)
    a = np.asarray(a, dtype=float)
    s = np.asarray(s, dtype=float)
    if i.size == 0:
        raise InputError(f"{path}: no a_ij rows found; accepted: rows of i j value sigma")
    lags = np.column_stack([i, j])
    badlag = ~np.isfinite(lags).all(axis=1) | np.any(lags != np.round(lags), axis=1) | np.any(
        lags < 0, axis=1)
    if badlag.any():
        bad = [(float(x), float(y)) for x, y in lags[badlag][:3]]
        raise InputError(f"{path}: lags must be non-negative integers (i serial, j parallel); "
                         f"found {bad}")
    if not np.all(np.isfinite(a)):
        k = int(np.flatnonzero(~np.isfinite(a))[0])
        raise InputError(f"{path}: coefficient at lag ({int(i[k])}, {int(j[k])}) is {a[k]}; "
                         "accepted: finite a_ij (per electron)")
    badsig = ~(np.isfinite(s) & (s > 0))
    if badsig.any():
        ks = np.flatnonzero(badsig)[:3]
        found = ", ".join(f"({int(i[k])}, {int(j[k])}): {s[k]:g}" for k in ks)
        raise InputError(f"{path}: {int(badsig.sum())} a_ij error(s) not positive and finite "
                         f"(lag: error {found}); accepted: positive 1-sigma errors per electron")
    if max(i.max(), j.max()) > MAX_TABLE_LAG:
        k = int(np.argmax(np.maximum(i, j)))
        raise InputError(f"{path}: lag ({int(i[k])}, {int(j[k])}) is beyond {MAX_TABLE_LAG}; "
                         f"accepted: lags 0..{MAX_TABLE_LAG} (measured tables reach ~20)")
    ii, jj = i.astype(int), j.astype(int)
    if not np.any((ii == 0) & (jj == 0)):
        raise InputError(f"{path}: no a00 (lag 0, 0) row; the table must include a00, measured "
                         "or set by the area sum rule")
    L = int(max(ii.max(), jj.max()))
    A = np.full((L + 1, L + 1), np.nan)
    S = np.full((L + 1, L + 1), np.nan)
    for x, y, v, e in zip(ii, jj, a, s):
        if not np.isnan(A[x, y]):
            raise InputError(f"{path}: lag ({x}, {y}) appears twice; each lag once")
        A[x, y], S[x, y] = v, e
    if np.isnan(A).any():
        miss = [tuple(m) for m in np.argwhere(np.isnan(A))[:3].tolist()]
        raise InputError(f"{path}: incomplete table, missing lags e.g. {miss}; accepted: every "
                         f"lag 0 <= i, j <= {L} once")
    return A, S


def _text_rows(path):
    rows = []
    with open(path, encoding="utf-8") as fh:
        for n, line in enumerate(fh, 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                if rows:
                    raise InputError(f"{path}:{n}: non-numeric row {s!r}; accepted: i j value "
                                     "sigma") from None
                continue
            if len(vals) != 4:
                raise InputError(f"{path}:{n}: {len(vals)} columns; accepted: 4 (i j value "
                                 "sigma)")
            rows.append(vals)
    d = np.array(rows).reshape(-1, 4)
    return d[:, 0], d[:, 1], d[:, 2], d[:, 3]


def read_acoeff_table(path, *, orient=True):
    """Read a text table ``i j value sigma`` (one lag per row, header allowed).

    Parameters
    ----------
    path : str
        File name. Rows hold integer lags i, j >= 0, the coefficient (per e)
        and its 1-sigma error; a first non-numeric line is a header.
    orient : bool, optional
        Establish the axis assignment from the data (:func:`assign_axes`)
        and detect a sum-rule a00 (:func:`sum_rule_check`).

    Returns
    -------
    AcoeffTable
        Indexed [serial, parallel] when ``orient`` is true, else in the file's
        (i, j) order.
    """
    a, s = acoeff_square(path, *_text_rows(path))
    table = AcoeffTable(a, s, source=str(path))
    if orient:
        table = assign_axes(table)
        ok, note = sum_rule_check(table)
        table.exclude_a00 = ok
        table.axis_note += "; " + note
    return table


def assign_axes(table):
    """Orient a table as [serial, parallel] from the data itself.

    The clock barriers between rows are weaker than the channel stops, so a
    collected charge pushes the row boundaries further: the parallel nearest
    neighbour has the larger coefficient (the paper's A01 > A10; every
    measured LSST sensor). The axis of the larger of the file's a[0, 1] and
    a[1, 0] is taken as parallel; the significance of the difference is
    reported in ``axis_note``.

    Parameters
    ----------
    table : AcoeffTable
        In the file's (i, j) order.

    Returns
    -------
    AcoeffTable
        [serial, parallel] order.
    """
    a01, a10 = table.a[0, 1], table.a[1, 0]
    s = math.hypot(table.sigma[0, 1], table.sigma[1, 0])
    z = abs(a01 - a10) / s
    if a01 >= a10:
        out = AcoeffTable(table.a, table.sigma, source=table.source,
                          exclude_a00=table.exclude_a00)
        which = "file (i, j) = (serial, parallel): a[0,1] > a[1,0]"
    else:
        out = table.transposed()
        which = "file (i, j) = (parallel, serial): a[1,0] > a[0,1], axes swapped"
    out.axis_note = (f"{which} by {z:.1f} sigma ({max(a01, a10):.3g} vs {min(a01, a10):.3g}; "
                     "the larger nearest neighbour is the parallel one)")
    return out


def sum_rule_check(table, *, nsigma=1.0):
    """Whether a00 equals minus the sum of all other lags (area sum rule).

    Sums a_ij over all signed lags except (0, 0) (weights 2 on the axes, 4
    off them) and compares with -a00. When they agree to better than
    ``nsigma`` times the error of a00 *divided by 10*, a00 was evidently set
    by the rule, not measured, and must stay out of chi2.

    Returns
    -------
    (bool, str)
        The verdict and a sentence with the numbers.
    """
    a = table.a
    w = np.full(a.shape, 4.0)
    w[0, :] = 2.0
    w[:, 0] = 2.0
    w[0, 0] = 0.0
    s = float(np.sum(w * a))
    gap = a[0, 0] + s
    ok = abs(gap) < nsigma * table.sigma[0, 0] / 10.0
    note = (f"a00 = {a[0, 0]:.4g}, minus the sum of the other lags = {-s:.4g} (gap {gap:.2g}, "
            f"a00 error {table.sigma[0, 0]:.2g}): "
            + ("a00 set by the sum rule, left out of chi2" if ok else "a00 measured, kept"))
    return ok, note


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
                          near_lag=1, tol=2e-5, definition="log"):
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
    ``near_samples`` uniformly spaced samples per edge (their boundaries bend
    most); the others from ``far_samples`` samples placed densest at the
    corners ('tan' spacing), where the far field is smooth.

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
    far = _quadrant_areas(model, L + 1, far_samples, tol, "tan", scales)
    k = min(int(near_lag), L) + 1
    near = _quadrant_areas(model, k, near_samples, tol, "uniform", scales)
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
        electrostatics can (``benchmarks/diagnose_base_model.py``: the
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
    """The shipped :class:`LinearBasis` (written by ``benchmarks/diagnose_itl.py``)."""
    import json
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
