"""The directions of the joint star-field fit and the a-matrix rows they are fitted to.

:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars` moves the
flats template T_a along a set of directions (displacement changes Delta T_k,
:func:`direction_basis`): the model's parameter steps and ``scale``, or the
directions of the a-matrix's errors, and ``curl`` in either case. The
a-matrix side of the fit (:class:`AmatrixRows`) is linear in them
(:func:`amatrix_jacobian`); the star side is measured on corrected fields,
and :func:`evaluate_directions` corrects every fitted field once with each
direction, keeping those the stars can be corrected with
(:class:`DirectionBasis`).
"""

import numpy as np

from lsst_bfdrift.calibration.tuning import CalibrationError
from lsst_bfdrift.templates.refine import (combine_templates, curl_free_template,
                                          template_alpha, template_difference)
from lsst_bfdrift.templates.template import build_template
from lsst_bfdrift.utils.errors import InputError

__all__ = ["STAR_JACOBIAN_STEP", "AmatrixRows", "DirectionBasis", "model_direction_step",
           "direction_basis", "amatrix_jacobian", "evaluate_directions", "evaluated_basis"]

#: Finite-difference step of the star Jacobian (in units of each direction).
STAR_JACOBIAN_STEP = 0.25

#: The displacement arrays of a template, as a direction's change holds them.
_ARRAYS = ("corner_d", "vedge_d", "hedge_d", "vedge_t", "hedge_t")


def _tick(bar, n=1):
    """Advance the progress bar ``bar`` (None: no bar) by ``n``."""
    if bar is not None:
        bar(n)


class AmatrixRows:
    """The a-matrix side of the joint fit: the measured lags and a template's a_ij there.

    Parameters
    ----------
    table : AcoeffTable
        The measured a_ij and their errors.
    template : DistortionTemplate
        The flats template T_a; its a_ij at the measured lags are ``start``.

    Attributes
    ----------
    center, max_lag : int
        The template's central pixel, and the largest lag fitted (the
        table's, within the template).
    lag_mask : ndarray of bool, shape (max_lag + 1, max_lag + 1)
        The measured lags.
    measured, sigma : ndarray
        The measured a_ij and their errors at those lags (1/e).
    sigma_lags : ndarray, shape (max_lag + 1, max_lag + 1)
        The errors per lag, NaN where not measured.
    start : ndarray
        ``alpha(template)``: T_a's a_ij at the measured lags.
    """

    def __init__(self, table, template):
        mask = table.mask()
        c = template.center
        L = min(table.max_lag, c - 1)
        self.center, self.max_lag = c, L
        self.lag_mask = mask[:L + 1, :L + 1]
        self.measured = table.a[:L + 1, :L + 1][self.lag_mask]
        self.sigma = table.sigma[:L + 1, :L + 1][self.lag_mask]
        self.sigma_lags = np.where(mask, table.sigma, np.nan)[:L + 1, :L + 1]
        self.start = self.alpha(template)

    @property
    def size(self):
        """Number of a-matrix rows (measured lags)."""
        return self.start.size

    def alpha(self, template):
        """The template's linear area response at the measured lags (1/e), in row order.

        Parameters
        ----------
        template : DistortionTemplate

        Returns
        -------
        ndarray
            :func:`~lsst_bfdrift.templates.refine.template_alpha` at lag
            (i, j) for every measured lag, i the row of ``lag_mask``.
        """
        c, L = self.center, self.max_lag
        return template_alpha(template)[c:c + L + 1, c:c + L + 1].T[self.lag_mask]

    def labels(self):
        """Row names ``a{i}{j}``, in row order."""
        L = self.max_lag
        return [f"a{i}{j}" for i in range(L + 1) for j in range(L + 1) if self.lag_mask[i, j]]


class DirectionBasis:
    """The directions of the joint fit that the star fields can be corrected with.

    Attributes
    ----------
    names : list of str
        Direction names: model parameters, ``scale``, ``curl``, and the
        directions of the a-matrix's errors (``mode0``, ... or ``a{i}{j}``).
    steps : dict
        Per direction, the change of its parameter for one unit (h_k; 1 for
        the others), including directions dropped by
        :func:`evaluate_directions`.
    deltas : list of dict
        Displacement change of each direction
        (:func:`~lsst_bfdrift.templates.refine.combine_templates`).
    is_lag : ndarray of bool
        The directions of the a-matrix's errors (always in the fit).
    templates : list of DistortionTemplate
        T_a plus ``eps`` times each direction: the templates the star
        Jacobian is measured with.
    eps : list of float
        The step of each direction's template.
    jacobian : ndarray, shape (n_lags, n_directions)
        The a-matrix rows' change per unit of each direction
        (:func:`amatrix_jacobian`).
    """

    def __init__(self, names, steps, deltas, is_lag, templates, eps, jacobian):
        self.names, self.steps, self.deltas = names, steps, deltas
        self.is_lag, self.templates, self.eps, self.jacobian = is_lag, templates, eps, jacobian

    @property
    def n_lag(self):
        """Number of directions of the a-matrix's errors (they come first in a fit)."""
        return int(self.is_lag.sum())


def model_direction_step(x0, lo, hi):
    """Step of a model parameter's direction: a tenth of its value, inside its range.

    Parameters
    ----------
    x0 : float
        The parameter's value.
    lo, hi : float
        Its range.

    Returns
    -------
    float or None
        ``h = 0.1 * max(|x0|, 0.01 * (hi - lo))``, negative when ``x0 + h``
        would pass ``hi``; None when the step back would pass ``lo`` too (no
        room for the direction).
    """
    h = 0.1 * max(abs(x0), 0.01 * (hi - lo))
    if x0 + h > hi:
        h = -h
    if x0 + h < lo:
        return None
    return h


def direction_basis(result, lag_dirs, *, bar=None):
    """The directions the stars may move the flats template along (before evaluation).

    Without ``lag_dirs``: ``scale`` (T_a itself: c is the fractional change
    of its strength) and each candidate parameter's change of the built
    template for one step (:func:`model_direction_step`); with them, the
    model's directions are left out (the directions of the a-matrix's errors
    would undo a model direction's change at the measured lags for free,
    leaving a change of the unmeasured far lags alone that nothing
    measures). Always ``curl``: T_a minus the curl-free template with its
    areas (:func:`~lsst_bfdrift.templates.refine.curl_free_template`), then
    the ``lag_dirs``.

    Parameters
    ----------
    result : CalibrationResult
        The flats calibration: ``template`` (T_a), ``built_template``,
        ``params``, ``settings`` and ``candidates``.
    lag_dirs : dict
        :func:`~lsst_bfdrift.templates.refine.area_response_directions` of
        T_a (empty: the model's directions).
    bar : callable, optional
        Progress bar, advanced once per candidate and once for ``curl``.

    Returns
    -------
    names : list of str
    steps : dict
        Name -> h_k (1 for ``scale``, ``curl`` and the lag directions).
    deltas : list of dict
        Displacement change of each direction.
    lag_names : set of str
        The names of the lag directions.
    warnings : list of str
        Candidates skipped because the model fails at their step.
    """
    ta, params, settings = result.template, result.params, result.settings
    names, steps, deltas, warnings = [], {}, [], []
    if not lag_dirs:
        names, steps = ["scale"], {"scale": 1.0}
        deltas = [{k: getattr(ta, k) for k in _ARRAYS}]
    for n, (lo, hi) in ({} if lag_dirs else result.candidates).items():
        _tick(bar)
        x0 = float(getattr(params, n))
        h = model_direction_step(x0, lo, hi)
        if h is None:
            continue
        try:
            tk = build_template(params.replace(**{n: x0 + h}), settings)
        except (RuntimeError, ValueError) as exc:
            warnings.append(f"direction {n} skipped: the model fails at {n} = {x0 + h:g} "
                            f"({exc})")
            continue
        names.append(n)
        deltas.append(template_difference(tk, result.built_template))
        steps[n] = h
    _tick(bar)
    names.append("curl")
    deltas.append(template_difference(ta, curl_free_template(ta)))
    steps["curl"] = 1.0
    lag_names = set()
    for name, d in lag_dirs.items():
        names.append(name)
        deltas.append(d["delta"])
        steps[name] = 1.0
        lag_names.add(name)
    return names, steps, deltas, lag_names, warnings


def amatrix_jacobian(rows, template, deltas):
    """The a-matrix rows' change per unit of each direction.

    Exact, not a finite difference: a template's linear area response is
    linear in its displacements.

    Parameters
    ----------
    rows : AmatrixRows
    template : DistortionTemplate
        T_a (``rows.start`` is its a_ij).
    deltas : sequence of dict
        Displacement changes.

    Returns
    -------
    ndarray, shape (rows.size, len(deltas))
    """
    return np.column_stack([rows.alpha(combine_templates(template, [d], [1.0])) - rows.start
                            for d in deltas])


def evaluate_directions(template, names, deltas, lag_names, fields, *, bar=None):
    """Correct every fitted field once with each direction's template.

    A direction's template is T_a plus ``eps`` of it: a quarter step
    (:data:`STAR_JACOBIAN_STEP`), small enough that bright pixels stay in
    the modelled range; a lag direction (one error of the a-matrix, usually
    small) tries a whole step first, then a quarter, then 0.05. A direction
    no step of which corrects every field is dropped. The fields keep the
    corrected catalogs (:meth:`StarField.corrected_catalog
    <lsst_bfdrift.calibration.star_fit.StarField.corrected_catalog>`), so
    every subset of stars reuses them.

    Parameters
    ----------
    template : DistortionTemplate
        T_a.
    names, deltas : sequence
        The directions (:func:`direction_basis`).
    lag_names : set of str
        The lag directions.
    fields : sequence of StarField
        The fitted fields.
    bar : callable, optional
        Progress bar, advanced once per field and direction.

    Returns
    -------
    keep : list of int
        Indices of the directions kept.
    templates : list of DistortionTemplate
        Their templates.
    eps : list of float
        Their steps.
    warnings : list of str
        The directions dropped, with the reason.
    """
    templates, eps_kept, keep, warnings = [], [], [], []
    for k, d in enumerate(deltas):
        for eps in ((1.0, STAR_JACOBIAN_STEP, 0.05) if names[k] in lag_names
                    else (STAR_JACOBIAN_STEP,)):
            t_k = combine_templates(template, [d], [eps])
            try:
                for f in fields:
                    f.corrected_catalog(t_k)
            except InputError as exc:
                failed = exc
                continue
            break
        else:
            warnings.append(f"direction {names[k]} skipped: the stars cannot be corrected "
                            f"with it ({failed})")
            _tick(bar, len(fields))
            continue
        _tick(bar, len(fields))
        keep.append(k)
        templates.append(t_k)
        eps_kept.append(eps)
    return keep, templates, eps_kept, warnings


def evaluated_basis(template, rows, names, steps, deltas, lag_names, fields, *, bar=None):
    """The fit's directions: those every fitted field can be corrected with.

    Parameters
    ----------
    template : DistortionTemplate
        T_a.
    rows : AmatrixRows
    names, steps, deltas, lag_names
        The directions (:func:`direction_basis`).
    fields : sequence of StarField
        The fitted fields.
    bar : callable, optional
        Progress bar (:func:`evaluate_directions`).

    Returns
    -------
    basis : DirectionBasis
    warnings : list of str
        The directions dropped (:func:`evaluate_directions`).

    Raises
    ------
    CalibrationError
        When no direction can be evaluated on the fields.
    """
    keep, templates, eps, warnings = evaluate_directions(template, names, deltas, lag_names,
                                                         fields, bar=bar)
    if not keep:
        raise CalibrationError("no direction of the template family can be evaluated on "
                               "the star fields")
    names = [names[k] for k in keep]
    deltas = [deltas[k] for k in keep]
    is_lag = np.array([n in lag_names for n in names], bool)
    jacobian = amatrix_jacobian(rows, template, deltas)
    return DirectionBasis(names, steps, deltas, is_lag, templates, eps, jacobian), warnings
