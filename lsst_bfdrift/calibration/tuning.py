"""Calibrate the electrostatic model from a sensor's own data (Rasmussen 2015's title).

:func:`calibrate` takes a measured a-matrix (from flat pairs, a PTC, an
a-matrix table or cp_pipe's PTC dataset; see
:mod:`~lsst_bfdrift.ptc.inputs`) and gives the fitted sensor
parameters with their covariance, the per-lag measured and model a_ij with
pulls, and the template that corrects that sensor.

The steps:

1. **Which physics the data need.** The model's a_ij (the linear area
   response of the template, ``definition='alpha'`` of
   :func:`~lsst_bfdrift.calibration.acoeff_model.electrostatic_acoeffs`) are
   differentiated once with respect to every candidate parameter of
   :data:`~lsst_bfdrift.calibration.fit_model.CANDIDATES` at the start. In
   that linear approximation, parameters are added one at a time, the one
   that lowers chi2 most first, while the drop exceeds the Bayesian
   information criterion's ln(N) (N measured lags) and the data have more
   lags than parameters. This chooses with the
   data: a PTC that measures only a00 frees one parameter; a full a-matrix
   frees what its lags constrain.
2. **The fit.** :func:`~lsst_bfdrift.calibration.fitting.fit_parameters`
   with the chosen columns as its starting Jacobian (Broyden updates: one
   drift-line evaluation per step), every measured lag in chi2, a00
   included; the sum rule is reported, not imposed. The parameter
   covariance comes from a finite-difference Jacobian at the optimum.
3. **A poor fit is stated, and refused only where nothing would match the
   data**: chi2/dof above ``max_chi2_dof`` with a p-value below 1e-3. With
   refinement (the default) the template is matched to the measured a_ij,
   so the data decide its area response: the misfit is stated (a
   :class:`CalibrationWarning` naming the worst lags, ``misfit`` in the
   result and the template's metadata) and carried into the template's
   uncertainty, the a_ij errors scaled by the Birge ratio
   (:func:`poor_fit_policy`). Without refinement the template would be the
   model's alone: a :class:`CalibrationError` unless ``allow_poor_fit``. A
   table inconsistent in itself (a00 > 0; the area sum rule broken when the
   lags are complete) is refused first, naming the check
   (:func:`~lsst_bfdrift.ptc.acoeffs.check_consistency`).
4. **The template.** Built exactly at the best fit, then, with ``refine``,
   its pixel areas are matched to the measured a_ij where they differ from
   the model significantly (:func:`refinement_target`: the residual weighted
   by max(0, 1 - 1/pull^2)) by the smallest curl-free boundary change
   (:func:`~lsst_bfdrift.templates.refine.match_area_coefficients`): the
   model gives the shape of the boundary shifts, the data their divergence.
   The template's ``meta['calibration']`` stores the parameters, their
   covariance, chi2, the inputs and the date, and its uncertainty: the
   a_ij errors (Birge-scaled for a poor fit) and what the parameters'
   covariance does beyond the areas (:func:`parameter_modes`: how area
   changes divide between column and row edges, which sets the e1 stars
   keep).
"""

import datetime
import math
import time
import warnings

import numpy as np

from lsst_bfdrift.ptc.acoeffs import AcoeffTable, check_consistency, near_field_response
from lsst_bfdrift.calibration.fit_model import (CANDIDATES, CHARGE, MODEL_SETTINGS,
                                                default_start, model_acoeffs, start_jacobian)
from lsst_bfdrift.calibration.fitting import FitError, fit_parameters
from lsst_bfdrift.ptc.covariances import fit_ptc_exponential
from lsst_bfdrift.ptc.full_model import fit_covariance_model
from lsst_bfdrift.templates.refine import lag_multiplicity, match_area_coefficients, template_alpha
from lsst_bfdrift.templates.template import (TemplateSettings, build_template,
                                             load_default_template)
from lsst_bfdrift.utils.progress import StageProgress
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["CalibrationError", "CalibrationWarning", "CalibrationResult", "calibrate",
           "poor_fit_policy", "check_refined_match", "measured_acoeffs", "refinement_target",
           "refine_template", "parameter_modes", "select_parameters", "STAGE_SECONDS",
           "MODE_MAX_SIZE", "MODE_EDGE_SAMPLES"]

#: Typical seconds of :func:`calibrate`'s stages on 2 cores, the weights of its
#: progress bar: one evaluation of the model's a_ij, the template build at the
#: bundled default's settings (21 x 21, 32 samples, 1e-5 px) and the refinement.
STAGE_SECONDS = {"model evaluation": 1.5, "template build": 12.0, "refinement": 1.0,
                 "parameter modes": 6.0}


class CalibrationError(FitError):
    """The data do not calibrate the model (poor fit, too few lags, bad input)."""


def measured_acoeffs(data, *, progress=None):
    """The measured a-matrix (an :class:`AcoeffTable`) of any calibration input.

    * An a-matrix with errors (a table, or cp_pipe's EXPAPPROXIMATION a00):
      as read.
    * Covariances of flat pairs (flats, or cp_pipe's covariances when it
      stores no a-matrix errors): the full covariance model of Astier et al.
      (2019) fitted to them
      (:func:`~lsst_bfdrift.ptc.full_model.fit_covariance_model`; errors
      from the covariances' own errors or pixel counts), a00 measured by the
      curvature of the PTC.
    * A PTC of means and variances only: a00 alone, from the exponential
      PTC model (:func:`~lsst_bfdrift.ptc.covariances.fit_ptc_exponential`).

    Parameters
    ----------
    data : CalibrationData
        From :func:`~lsst_bfdrift.ptc.inputs.read_calibration_input`.
    progress : callable, optional
        Passed to :func:`~lsst_bfdrift.ptc.full_model.fit_covariance_model`
        (called after each evaluation of the covariance model; the other
        inputs need no fit and never call it).

    Returns
    -------
    AcoeffTable
        a_ij (1/e), [i serial, j parallel].
    """
    src = ", ".join(data.files)
    if data.a is not None and data.a_sigma is not None:
        return data.acoeff_table()
    if data.cov is not None and data.mu is not None and data.cov.shape[1] > 1:
        sig = data.cov_sigma
        npix = None if sig is not None else data.npix
        fit = fit_covariance_model(np.asarray(data.mu, float), np.asarray(data.cov, float),
                                   sigma=sig, npix=npix,
                                   gain=1.0 if data.units == "electron" else None,
                                   progress=progress)
        bt = fit["b_test"]
        b_note = "" if bt is None else (
            f"; b_ij {'fitted' if fit['b_fitted'] else 'fixed to 0'} (their chi2 gain "
            f"{bt['delta_chi2']:.1f} for {bt['dof']} dof, p = {bt['p_value']:.2g})")
        return AcoeffTable(fit["a"], fit["a_err"], source=f"{src} (covariance model fit)",
                           axis_note="flats: i along x (serial), j along y (parallel)" + b_note)
    if data.mu is not None and data.var is not None:
        e = fit_ptc_exponential(np.asarray(data.mu, float), np.asarray(data.var, float),
                                mu_max=None)
        if not (np.isfinite(e["a00_err"]) and e["a00_err"] > 0):
            raise CalibrationError(f"{src}: the PTC does not measure a00 (error "
                                   f"{e['a00_err']!r})")
        return AcoeffTable([[e["a00"]]], [[e["a00_err"]]], source=f"{src} (PTC curvature)",
                           axis_note="a00 only")
    raise CalibrationError(f"{src}: no a-matrix, covariances or PTC to calibrate from")


def refinement_target(template, table):
    """The a_ij the refined template is given: the template's own where the
    data agree with it, the data where they differ significantly.

    Each lag's residual r = measured - template (its linear response) is
    kept with the weight max(0, 1 - 1 / pull^2), pull = r / sigma: a lag
    within its error is left to the model (refining it would copy the
    noise of the measurement into the template), a lag many sigma away is
    matched (the model lacks something there). NaN where not measured.
    """
    c = template.center
    L = min(table.max_lag, c - 1)
    model = template_alpha(template)[c:c + L + 1, c:c + L + 1].T
    a = table.a[:L + 1, :L + 1]
    r = a - model
    pull2 = (r / table.sigma[:L + 1, :L + 1]) ** 2
    with np.errstate(divide="ignore"):
        w = np.clip(1.0 - 1.0 / pull2, 0.0, 1.0)
    return np.where(table.mask()[:L + 1, :L + 1], model + w * r, np.nan)


def refine_template(template, table):
    """The template refined as :func:`calibrate` refines it: its linear area
    response matched to :func:`refinement_target` (the measured a_ij where
    they differ significantly from the template's, its own elsewhere) over
    the lags of ``table`` that fit in the template.

    Parameters
    ----------
    template : DistortionTemplate
        Template built from the fitted parameters.
    table : AcoeffTable
        Measured a_ij (1/e) with their errors.

    Returns
    -------
    DistortionTemplate
        The refined copy (``template`` is not modified).
    """
    return match_area_coefficients(template, refinement_target(template, table),
                                   max_lag=min(table.max_lag, template.center - 1))


#: Largest side of the templates :func:`parameter_modes` builds (lags up to 4
#: around the aggressor, where the stars' e1 is set) and their samples per
#: edge (a mode keeps each edge's mean shift): two such builds per free
#: parameter cost about 0.25-0.6 s each (benchmarks/performance/bench_calibrate.py).
MODE_MAX_SIZE = 9
MODE_EDGE_SAMPLES = 8


def _edge_means(template, size):
    """Corner shifts and per-edge mean shifts of the central ``size`` block."""
    c, h = template.center, size // 2
    o = c - h
    return (template.corner_d[o:o + size + 1, o:o + size + 1],
            template.vedge_d[o:o + size, o:o + size + 1].mean(axis=-1),
            template.hedge_d[o:o + size + 1, o:o + size].mean(axis=-1))


def parameter_modes(params, fit, candidates, table, settings, *, scale=1.0, progress=None):
    """What the fitted parameters' uncertainty does to a refined template beyond its areas.

    The refined template has the measured areas whatever the parameters
    (within their errors), but how each pixel's area change divides between
    its column and row edges, the divergence-free part of the boundary
    shifts that no a-matrix measures and that sets the e1 stars keep,
    follows the parameters. For each eigenvector v_m of the fit's parameter
    covariance (eigenvalue lambda_m), templates are built at the best fit
    +- sqrt(lambda_m) v_m (clipped to the bounds), each refined to the same
    a_ij (:func:`refine_template`); half their difference is mode m, one
    standard deviation. The templates are built on the central block of
    side ``2 (L + 1) + 1`` (L the table's largest lag), at most
    :data:`MODE_MAX_SIZE` and the settings' size, with
    :data:`MODE_EDGE_SAMPLES` samples per edge (at most the settings'), where
    the boundaries are those of the full build (lags beyond the block's are
    refined no further: their areas change with the parameters); a mode is kept
    as its corner shifts and the mean shift of each edge (the samples along
    an edge move together), so that it stays small in the template's
    metadata. :func:`~lsst_bfdrift.templates.refine.draw_templates` adds the
    modes times independent standard normal numbers.

    Parameters
    ----------
    params : SensorParameters
        Best-fit parameters.
    fit : ParameterFit
        The fit (``names``, ``values``, ``covariance``).
    candidates : dict
        {name: (lo, hi)} bounds of the fitted parameters.
    table : AcoeffTable
        The a_ij the templates are refined to.
    settings : TemplateSettings
        Settings of the calibrated template (its charge, samples, tolerance).
    scale : float, optional
        Factor on the standard deviations (a poor fit's Birge ratio, as its
        a_ij errors are scaled).
    progress : callable, optional
        Called with the fraction done.

    Returns
    -------
    dict or None
        ``size`` (side of the block, centred on the aggressor), ``names``,
        ``eigenvalues``, ``vectors`` (columns v_m), ``scale``, ``kept`` (the
        indices m of the modes stored), ``corner_d`` (per mode,
        shape (size + 1, size + 1, 2)), ``vedge_d`` (per mode, mean shift of
        each column edge, shape (size, size + 1)), ``hedge_d`` (per mode, each
        row edge, shape (size + 1, size)), pixel units at the template's
        charge, rounded to 5 significant digits; ``skipped``: modes whose
        builds failed (parameters the model refuses), with the reason. None
        without a usable covariance.
    """
    cov = np.asarray(fit.covariance, float)
    if cov.size == 0 or not np.all(np.isfinite(cov)):
        return None
    lam, vec = np.linalg.eigh(cov)
    size = int(min(settings.size, MODE_MAX_SIZE, 2 * (int(table.max_lag) + 1) + 1))
    small = TemplateSettings.from_dict({**settings.to_dict(), "size": size,
                                        "edge_samples": min(settings.edge_samples,
                                                            MODE_EDGE_SAMPLES)})
    out = {"size": size, "names": list(fit.names), "eigenvalues": lam.tolist(),
           "vectors": vec.tolist(), "scale": float(scale), "kept": [], "corner_d": [],
           "vedge_d": [], "hedge_d": [], "skipped": []}
    for m in range(lam.size):
        step = float(scale) * math.sqrt(max(float(lam[m]), 0.0)) * vec[:, m]
        pair = []
        for sign in (1.0, -1.0):
            vals = {n: float(np.clip(fit.values[n] + sign * step[k], *candidates[n]))
                    for k, n in enumerate(fit.names)}
            try:
                built = build_template(params.replace(**vals), small)
            except (InputError, RuntimeError, ValueError) as exc:
                out["skipped"].append({"mode": m, "values": vals, "reason": str(exc)})
                break
            pair.append(_edge_means(refine_template(built, table), size))
            if progress is not None:
                progress((2 * m + len(pair)) / (2 * lam.size))
        if len(pair) < 2:
            continue
        out["kept"].append(m)
        for key, plus, minus in zip(("corner_d", "vedge_d", "hedge_d"), *pair):
            half = 0.5 * (np.asarray(plus) - np.asarray(minus))
            out[key].append(np.vectorize(lambda v: float(f"{v:.5g}"))(half).tolist())
    return out


class CalibrationResult:
    """Result of :func:`calibrate`.

    Attributes
    ----------
    params : SensorParameters
        Best-fit parameters (the others as in the start).
    fit : ParameterFit
        The fit (values, errors, covariance, correlation, chi2, dof, pulls).
    table : AcoeffTable
        The measured a_ij used (1/e, [i serial, j parallel]).
    model : ndarray
        Model a_ij at the best fit (1/e).
    template_acoeffs : ndarray or None
        The final template's a_ij (its linear area response) at the measured
        lags.
    template : DistortionTemplate or None
        The calibrated template (None with ``build=False``).
    built_template : DistortionTemplate or None
        The template built at the best fit, before refinement.
    settings : TemplateSettings or None
        Settings of the build.
    candidates : dict
        The candidate parameters and their bounds.
    selection : list of dict
        The parameter choice: per step, the parameter added and the linear
        chi2 after it.
    sum_rule : dict
        Sum of the measured a_ij over all lags (both signs) and its error.
    seconds : dict
        Wall time of the steps.
    jacobian_source : str
        Where the start Jacobian came from: ``'package data'`` (the default
        start and candidates,
        :func:`~lsst_bfdrift.calibration.fit_model.start_jacobian`) or
        ``'computed'``.
    model_settings : dict
        Numerical settings of the fit's model a_ij
        (:data:`~lsst_bfdrift.calibration.fit_model.MODEL_SETTINGS` or those
        passed).
    """

    #: Defaults of the attributes a result built by hand may lack.
    jacobian_source = None
    model_settings = None

    def __init__(self, **kw):
        self.__dict__.update(kw)

    @property
    def pulls(self):
        """(measured - model) / sigma per lag."""
        return (self.table.a - self.model) / self.table.sigma

    def lag_rows(self):
        """Per-lag rows: (i, j, measured, sigma, model, pull, template)."""
        rows = []
        L = self.table.max_lag
        for i in range(L + 1):
            for j in range(L + 1):
                if not self.table.mask()[i, j]:
                    continue
                t = None if self.template_acoeffs is None else float(self.template_acoeffs[i, j])
                rows.append((i, j, float(self.table.a[i, j]), float(self.table.sigma[i, j]),
                             float(self.model[i, j]), float(self.pulls[i, j]), t))
        return rows

    @property
    def near_field(self):
        """S1 = a00 + 2 (a01 + a10) + 4 a11 (per e;
        :func:`~lsst_bfdrift.ptc.acoeffs.near_field_response`) of the data
        (with its error), the fitted model and the template; None without
        lags 0-1 on both axes."""
        t = self.table
        if t.max_lag < 1:
            return None
        s1, err = near_field_response(t.a, t.sigma, from_sum_rule=t.exclude_a00)
        tpl = self.template_acoeffs
        return {"data": s1, "error": err, "relative_error": err / abs(s1) if s1 else None,
                "model": near_field_response(self.model)[0],
                "template": None if tpl is None else near_field_response(tpl)[0]}

    def summary(self):
        """JSON-friendly summary (no arrays of the template)."""
        f = self.fit
        return {"parameters": {n: {"value": f.values[n], "error": f.errors[n]}
                               for n in f.names},
                "covariance": np.asarray(f.covariance).tolist(),
                "correlation": np.asarray(f.correlation).tolist(), "names": f.names,
                "chi2": f.chi2, "dof": f.dof, "chi2_dof": f.chi2_dof, "p_value": f.p_value,
                "worst_lags": [{"lag": list(k), "pull": p} for k, p in f.worst(3)],
                "at_bound": f.at_bound,
                "lags": [dict(zip(("i", "j", "a", "sigma", "model", "pull", "template"), r))
                         for r in self.lag_rows()],
                "selection": self.selection, "sum_rule": self.sum_rule,
                "near_field": self.near_field, "n_evaluations": f.n_evaluations,
                "seconds": self.seconds,
                "jacobian_source": self.jacobian_source, "model_settings": self.model_settings,
                "source": self.table.source,
                "template": None if self.template is None else self.template.summary()}


def _sum_rule(table):
    a, s = table.a, table.sigma
    L = a.shape[0] - 1
    mult = lag_multiplicity(L)
    m = table.mask()
    return {"sum": float((a * mult)[m].sum()), "error": float(np.sqrt(((s * mult)[m] ** 2).sum())),
            "max_lag": int(L),
            "note": "sum of a_ij over all measured lags (both signs); BF conserves area, so it "
                    "is zero within its error when the lags beyond the table are small"}


def select_parameters(J, r, sigma, mask, names, *, max_params, always_first=True,
                      n_points=None, base=()):
    """Greedy choice of the parameters a linearised model needs: chi2 drop > ln N.

    Columns of ``J`` are added one at a time, each time the one that lowers
    the weighted least-squares chi2 most, while the drop exceeds
    ``max(ln N, 1)``. A candidate must beat the best so far by more than
    rounding (1e-9 of the chi2), so columns that fit equally keep their
    order in ``names``. Used by :func:`calibrate` (the model's parameters)
    and by :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`
    (the template's directions).

    Parameters
    ----------
    J : ndarray, shape (n_rows, n_names)
        The model's change per unit of each parameter.
    r : ndarray, shape (n_rows,)
        Model minus data at the start.
    sigma : ndarray, shape (n_rows,)
        Errors of the rows (inf: no weight).
    mask : ndarray of bool, shape (n_rows,)
        The rows used.
    names : sequence of str
        Name of each column.
    max_params : int
        Most parameters chosen (besides ``base``); at most N - 1.
    always_first : bool, optional
        Take the first parameter without the ln N test.
    n_points : int, optional
        N of the ln N test when some rows are priors, not data (default: the
        rows in ``mask``).
    base : sequence of int, optional
        Indices of columns always in the model (not chosen, not returned,
        not counted in ``max_params``).

    Returns
    -------
    chosen : list of str
        The names chosen, in the order they were added.
    steps : list of dict
        ``parameter`` (None for the start) and ``chi2_linear`` after each
        addition.
    """
    w = 1.0 / sigma[mask]
    A = J[mask] * w[:, None]
    b = -r[mask] * w
    n_points = int(mask.sum()) if n_points is None else int(n_points)
    base = [int(k) for k in base]
    chosen, steps = list(base), []
    chi2_now = float(b @ b)
    if base:
        x = np.linalg.lstsq(A[:, base], b, rcond=None)[0]
        chi2_now = float(np.sum((b - A[:, base] @ x) ** 2))
    steps.append({"parameter": None, "chi2_linear": chi2_now})
    limit = (min(max_params, n_points - 1) if n_points > 1 else 1) + len(base)
    while len(chosen) < limit:
        best = None
        # a candidate must beat the best so far by more than rounding: columns
        # that fit the data equally (one datum, any one parameter: chi2 ~ 1e-30)
        # keep their order in ``names``, whatever the LAPACK build rounds to
        tie = 1e-9 * max(chi2_now, 1.0)
        for k in range(len(names)):
            if k in chosen:
                continue
            cols = A[:, chosen + [k]]
            x = np.linalg.lstsq(cols, b, rcond=None)[0]
            c2 = float(np.sum((b - cols @ x) ** 2))
            if best is None or c2 < best[1] - tie:
                best = (k, c2)
        if best is None:
            break
        drop = chi2_now - best[1]
        if (len(chosen) > len(base) or not always_first) \
                and drop < max(math.log(n_points), 1.0):
            break
        chosen.append(best[0])
        chi2_now = best[1]
        steps.append({"parameter": names[best[0]], "chi2_linear": chi2_now})
    return [names[k] for k in chosen[len(base):]], steps


class CalibrationWarning(UserWarning):
    """The model fits the a-matrix poorly; the template was refined to the data and its
    uncertainty scaled (:func:`poor_fit_policy`)."""


def poor_fit_policy(fit, table, chosen, *, refined, allow_poor_fit):
    """What a poor physics fit gives: an error, or a template with the misfit carried.

    When the template is refined to the measured a_ij, the data decide its
    area response and a physics misfit is no reason to refuse them: the
    misfit is stated (a :class:`CalibrationWarning` naming the worst lags)
    and carried into the template's uncertainty, whose a_ij errors are
    scaled by the Birge ratio sqrt(chi2/dof) (what the data do not pin, the
    far lags and the serial/parallel sharing, comes from a model that
    misfits). Without refinement the template would be the model's alone,
    which does not match the data: an error unless ``allow_poor_fit``.

    Parameters
    ----------
    fit : ParameterFit
    table : AcoeffTable
    chosen : list of str
        The fitted parameters.
    refined : bool
        A template is built and refined to the data.
    allow_poor_fit : bool

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``chi2_dof``, ``p_value``, ``birge`` and ``worst_lags``.

    Raises
    ------
    CalibrationError
        Without refinement, unless ``allow_poor_fit``.
    """
    worst = ", ".join(f"a{i}{j} pull {p:+.1f}" for (i, j), p in fit.worst(3))
    src = table.source or "the a-matrix"
    text = (f"poor fit of {chosen} to {src}: chi2/dof = {fit.chi2_dof:.2f} ({fit.chi2:.1f} "
            f"for {fit.dof} dof, p = {fit.p_value:.1e}); worst lags: {worst}")
    if not refined and not allow_poor_fit:
        raise CalibrationError(
            f"{text}. The model cannot match these data within their errors, and without "
            "refinement (--no-refine, refine=False) the template would be the model's; "
            "refine it to the data, check the errors, or pass allow_poor_fit=True "
            "(--allow-poor-fit) to build it anyway")
    birge = math.sqrt(fit.chi2_dof)
    if refined and not allow_poor_fit:  # allow_poor_fit: the caller expects it, no warning
        warnings.warn(f"{text}. The template is refined to the measured a_ij and its "
                      f"uncertainty (the a_ij errors) scaled by the Birge ratio {birge:.2f}: "
                      "what the data do not pin (the far lags, how the area change divides "
                      "between serial and parallel edges) comes from a model that misfits",
                      CalibrationWarning, stacklevel=3)
    return {"chi2": float(fit.chi2), "dof": int(fit.dof), "chi2_dof": float(fit.chi2_dof),
            "p_value": float(fit.p_value), "birge": birge,
            "worst_lags": [{"lag": list(k), "pull": float(p)} for k, p in fit.worst(3)]}


def check_refined_match(template_a, table, max_chi2_dof):
    """The refined template's a_ij against the data (after a poor physics fit).

    Returns
    -------
    dict
        ``template_chi2`` and ``template_lags`` (measured lags the template
        holds).

    Raises
    ------
    CalibrationError
        The refinement did not bring the template within ``max_chi2_dof`` per
        lag of the data: nothing the package could write would match them.
    """
    m = table.mask() & np.isfinite(template_a)
    chi2 = float(np.sum(((template_a - table.a) / table.sigma)[m] ** 2))
    n = int(m.sum())
    if n and chi2 / n > max_chi2_dof:
        raise CalibrationError(f"{table.source or 'the a-matrix'}: the template refined to the "
                               f"data still misses them (chi2 {chi2:.1f} over {n} lags): the "
                               "refinement failed; check the errors and the lags given")
    return {"template_chi2": chi2, "template_lags": n}


def calibrate(table, *, start=None, free=None, max_params=6, refine=True, settings=None,
              max_chi2_dof=3.0, allow_poor_fit=False, build=True, max_evaluations=25,
              progress=False, model_settings=None, modes=True):
    """Fit the electrostatic model to a measured a-matrix and build its template.

    Parameters
    ----------
    table : AcoeffTable
        Measured a_ij (1/e) with errors, [i serial, j parallel]; a00 is used
        when the table measures it (``exclude_a00`` False). Read one with
        :func:`~lsst_bfdrift.ptc.inputs.read_calibration_input`.
    start : SensorParameters, optional
        Starting point; default
        :func:`~lsst_bfdrift.calibration.fit_model.default_start` (the
        bundled template's sensor).
    free : dict or sequence of str, optional
        Free parameters with bounds ({name: (lo, hi)}) or names of
        :data:`~lsst_bfdrift.calibration.fit_model.CANDIDATES`. Default: chosen
        from those by the data (module docstring).
    max_params : int, optional
        Most parameters the choice may free.
    refine : bool, optional
        Match the template's areas to the measured a_ij (module docstring).
    settings : TemplateSettings, optional
        Settings of the template build; default those of the bundled
        template (21 x 21 pixels, 32 samples per edge) at 1e4 e.
    max_chi2_dof : float, optional
        A fit with chi2/dof above this and a p-value below 1e-3 is poor.
    allow_poor_fit : bool, optional
        Without refinement: return a poor fit (and its template) instead of
        raising (with refinement a poor fit is never an error).
    build : bool, optional
        Build the template (about 1-4 s).
    max_evaluations : int, optional
        Model evaluations of the search (each about 0.6 s at 9 x 9 lags); a search that stops
        there reports its fit as it is (a poor one as poor).
    progress : bool, optional
        Progress bar on stderr, labelled with the stage: ``calibrate: model
        fit`` (the Jacobian and the search), ``calibrate: template build``,
        ``calibrate: refinement``, ``calibrate: parameter modes``; each
        weighted by its typical time
        (:data:`STAGE_SECONDS`).
    model_settings : dict, optional
        Numerical settings of the fit's model a_ij
        (:func:`~lsst_bfdrift.calibration.fit_model.model_acoeffs`; default
        :data:`~lsst_bfdrift.calibration.fit_model.MODEL_SETTINGS`, or
        :data:`~lsst_bfdrift.calibration.fit_model.CONVERGED_MODEL_SETTINGS`).
    modes : bool, optional
        With refinement: store the fitted parameters' uncertainty beyond the
        template's areas (:func:`parameter_modes`; two small template builds
        per free parameter, about 0.25-0.6 s each), so that templates drawn from the
        template's uncertainty vary how area changes divide between column
        and row edges too.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    CalibrationError
        Too few lags for one parameter, unknown parameter names, a poor fit
        without refinement (the message names the worst lags) and without
        ``allow_poor_fit``, or a refined template that still misses the data.
    InputError
        A table inconsistent in itself (the check is named).

    Warns
    -----
    CalibrationWarning
        A poor fit whose template is refined to the data (the Birge ratio
        that scales its uncertainty is given).
    """
    if not isinstance(table, AcoeffTable):
        raise InputTypeError("calibrate needs an AcoeffTable (see "
                        "lsst_bfdrift.ptc.inputs.read_calibration_input), got "
                        f"{type(table).__name__}")
    if isinstance(max_evaluations, bool) or int(max_evaluations) != max_evaluations \
            or max_evaluations < 1:
        raise InputError(f"max_evaluations must be a positive integer, got {max_evaluations!r}")
    t0 = time.perf_counter()
    seconds = {}
    consistency = check_consistency(table)  # data inconsistent in themselves are refused
    start = default_start() if start is None else start
    L = table.max_lag
    mask = table.mask()
    if mask.sum() < 1:
        raise CalibrationError("the a-matrix has no lag to fit")
    if free is not None and not isinstance(free, dict):
        unknown = [n for n in free if n not in CANDIDATES]
        if unknown:
            raise CalibrationError(f"unknown free parameters {unknown}; known: "
                                   f"{sorted(CANDIDATES)}")
        free = {n: CANDIDATES[n] for n in free}
    candidates = dict(CANDIDATES if free is None else free)
    for n, (lo, hi) in candidates.items():
        v = getattr(start, n)
        if v is None or not lo <= v <= hi:
            raise CalibrationError(f"start value of {n!r} ({v}) is outside its bounds "
                                   f"({lo}, {hi})")
    names = list(candidates)
    n_eval = (len(names) + 1) + max_evaluations + (max_params if free is None else len(names))
    stages = StageProgress({"model fit": n_eval * STAGE_SECONDS["model evaluation"],
                            "template build": STAGE_SECONDS["template build"] if build else 0,
                            "refinement": STAGE_SECONDS["refinement"] if build and refine
                            else 0,
                            "parameter modes": STAGE_SECONDS["parameter modes"]
                            if build and refine and modes else 0}, "calibrate",
                           enabled=progress)
    evaluations = 0
    mode_record = None

    def count(n):
        nonlocal evaluations
        evaluations += n
        stages("model fit", evaluations / n_eval)

    stages("model fit", 0.0)
    stages.bar.show()  # what runs, from the first second

    def model(values):
        count(1)
        try:
            return model_acoeffs(start.replace(**values), L, settings=model_settings)
        except (RuntimeError, ValueError):
            # drift lines that do not converge (a field that traps the charge,
            # far outside the data): a rejected step for the fit engine
            return np.full((L + 1, L + 1), np.nan)

    # 1. Jacobian of every candidate at the start (forward differences), from
    # the package data when the start and the candidates are the defaults
    x0 = {n: float(getattr(start, n)) for n in names}
    m0, J, jacobian_source = start_jacobian(start, candidates, L, model=model,
                                            settings=model_settings)
    seconds["jacobian"] = time.perf_counter() - t0
    if jacobian_source == "package data":
        count(len(names) + 1)
    # 2. which parameters the data need
    if free is None:
        chosen, selection = select_parameters(J, m0 - table.a, table.sigma, mask, names,
                                                max_params=max_params)
    else:
        chosen, selection = names, [{"parameter": n, "chi2_linear": None} for n in names]
    if int(mask.sum()) < len(chosen):
        raise CalibrationError(f"{int(mask.sum())} measured lags cannot constrain "
                               f"{len(chosen)} parameters {chosen}")
    cols = [names.index(n) for n in chosen]
    t1 = time.perf_counter()
    # a chosen parameter starting on a bound (e.g. a point charge, cloud 0)
    # starts 1 % of its span inside
    fit_start = {}
    for n in chosen:
        lo, hi = candidates[n]
        fit_start[n] = (x0[n] if lo < x0[n] < hi
                        else x0[n] + (0.01 if x0[n] == lo else -0.01) * (hi - lo))
    fit = fit_parameters(model, table.a, table.sigma, fit_start,
                         {n: candidates[n] for n in chosen}, mask=mask, jacobian0=J[..., cols],
                         max_evaluations=max_evaluations)
    seconds["fit"] = time.perf_counter() - t1
    params = start.replace(**fit.values)
    poor = fit.dof > 0 and fit.chi2_dof > max_chi2_dof and fit.p_value < 1e-3
    misfit = poor_fit_policy(fit, table, chosen, refined=bool(refine and build),
                             allow_poor_fit=allow_poor_fit) if poor else None
    template = tpl_a = built = None
    if build:
        t2 = time.perf_counter()
        if settings is None:
            d = dict(load_default_template().meta.get("settings", {}))
            d["aggressor_charge"] = CHARGE
            settings = TemplateSettings.from_dict(d)
        stages("template build", 0.0)
        template = built = build_template(params, settings,
                                          progress=lambda f: stages("template build", f))
        seconds["build"] = time.perf_counter() - t2
        if refine:
            t3 = time.perf_counter()
            stages("refinement", 0.0)
            template = refine_template(template, table)
            seconds["refine"] = time.perf_counter() - t3
            if modes and fit.names:
                t4 = time.perf_counter()
                stages("parameter modes", 0.0)
                mode_record = parameter_modes(
                    params, fit, {n: candidates[n] for n in fit.names}, table, settings,
                    scale=1.0 if misfit is None else misfit["birge"],
                    progress=lambda f: stages("parameter modes", f))
                seconds["modes"] = time.perf_counter() - t4
        c = template.center
        k = min(L, c - 1) + 1
        tpl_a = np.full_like(table.a, np.nan)
        tpl_a[:k, :k] = template_alpha(template)[c:c + k, c:c + k].T
        if misfit is not None:  # the refined template must match what the model could not
            misfit.update(check_refined_match(tpl_a, table, max_chi2_dof))
    seconds["total"] = time.perf_counter() - t0
    stages.__exit__(None, None, None)
    result = CalibrationResult(params=params, fit=fit, table=table, model=fit.model,
                               template_acoeffs=tpl_a, template=template, selection=selection,
                               sum_rule=_sum_rule(table), seconds=seconds, poor_fit=poor,
                               refined=bool(refine and build), built_template=built,
                               settings=settings, candidates=candidates, start=start,
                               jacobian_source=jacobian_source, misfit=misfit,
                               model_settings=dict(MODEL_SETTINGS if model_settings is None
                                                   else model_settings),
                               consistency=consistency)
    if template is not None:
        template.meta["params"] = params.to_dict()
        template.meta["calibration"] = {
            "source": table.source, "date": datetime.datetime.now(datetime.timezone.utc)
            .isoformat(timespec="seconds"), "names": fit.names, "values": fit.values,
            "errors": fit.errors, "covariance": np.asarray(fit.covariance).tolist(),
            "chi2": fit.chi2, "dof": fit.dof, "p_value": fit.p_value, "poor_fit": poor,
            "refined": bool(refine), "max_lag": int(L), "a00_in_fit": bool(mask[0, 0]),
            "model_settings": result.model_settings,
            "misfit": misfit,
            "uncertainty": (
                {"kind": "data", "sigma": np.where(
                    mask, table.sigma * (1.0 if misfit is None else misfit["birge"]),
                    np.nan).tolist(), **({"parameter_modes": mode_record}
                                         if mode_record else {})}
                if refine else
                {"kind": "parameters", "jacobian": np.asarray(fit.jacobian).tolist(),
                 "covariance": np.asarray(fit.covariance).tolist(), "names": fit.names})}
    return result
