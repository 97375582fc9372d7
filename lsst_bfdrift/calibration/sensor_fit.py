"""Calibration of the model's free scales against template numbers.

:func:`fit_sensor_parameters` adjusts chosen :class:`~lsst_bfdrift.physics.sensor.SensorParameters`
so that the template computed from them matches target numbers (e.g. the
paper's A00, A01, A10, A11 for a 1e4 e aggressor), by non-linear least
squares (:func:`~lsst_bfdrift.calibration.fitting.fit_parameters`) with numerical derivatives, and
reports the fitted values with uncertainties and correlations from the
Jacobian. Template numbers are quantised by the bisection tolerance, so the
derivative steps are a few percent of each parameter and the tolerance is set
well below the targets' errors.
"""

import math

import numpy as np

from lsst_bfdrift.calibration.fitting import fit_parameters
from lsst_bfdrift.templates.template import TemplateSettings, build_template
from lsst_bfdrift.utils.errors import InputError

__all__ = ["CalibrationResult", "template_numbers", "fit_sensor_parameters"]

#: Settings used for calibration: a 3 x 3 neighbourhood is enough for A00..A11;
#: 32 samples per edge converge the areas to ~4e-5 (8 leave errors of ~6e-4).
CALIBRATION_SETTINGS = TemplateSettings(size=3, edge_samples=32, tol=1e-4, workers=1)


def template_numbers(params, settings=CALIBRATION_SETTINGS):
    """Summary numbers (A00, A01, A10, A11, ratio_01_10, ...) of a template.

    Besides :meth:`~lsst_bfdrift.templates.template.DistortionTemplate.summary`, every
    lag (i, j) >= 0 inside the template is given as ``"A{i}{j}"`` (i serial,
    j parallel: the area in px^2 of pixel (c + i, c + j) for the aggressor at
    c), e.g. ``A02`` and ``A20`` for a template of size 5 or more.
    """
    tpl = build_template(params, settings)
    out = tpl.summary()
    area = tpl.moments().area
    c = tpl.center
    for j in range(min(c, 9) + 1):
        for i in range(min(c, 9) + 1):
            out[f"A{i}{j}"] = float(area[c + j, c + i])
    return out


class CalibrationResult:
    """Result of :func:`fit_sensor_parameters`.

    Attributes
    ----------
    params : SensorParameters
        Best-fit parameters.
    values, errors : dict
        Fitted values of the free parameters and their 1-sigma errors.
    correlation : ndarray
        Correlation matrix of the free parameters (order of ``names``).
    names : list of str
        The free parameters.
    model, targets : dict
        Template numbers at the best fit, and the targets (value, sigma).
    chi2 : float
    n_evaluations : int
    seconds : float
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def table(self):
        """Rows (name, target, sigma, model, pull) as a list of tuples."""
        return [(k, v, s, self.model[k], (self.model[k] - v) / s)
                for k, (v, s) in self.targets.items()]

    def as_dict(self):
        """JSON-friendly summary."""
        return {"values": self.values, "errors": self.errors, "names": self.names,
                "correlation": np.asarray(self.correlation).tolist(), "chi2": self.chi2,
                "model": {k: self.model[k] for k in self.targets}, "targets": self.targets,
                "n_evaluations": self.n_evaluations, "seconds": self.seconds}


def fit_sensor_parameters(targets, params0, free, *, settings=CALIBRATION_SETTINGS,
                          log_params=None, diff_step=0.03, max_nfev=40, callback=None):
    """Fit sensor parameters so that template numbers match targets.

    Parameters
    ----------
    targets : dict
        ``{name: (value, sigma)}`` with names from
        :meth:`~lsst_bfdrift.templates.template.DistortionTemplate.summary` (e.g. 'A00').
    params0 : SensorParameters
        Starting point; parameters not in ``free`` stay fixed.
    free : dict
        ``{parameter: (lower, upper)}`` bounds of the free parameters.
    settings : TemplateSettings, optional
        Template settings used in the fit.
    log_params : sequence of str, optional
        Parameters fitted in log space (default: those with positive bounds).
    diff_step : float, optional
        Relative step of the numerical derivatives (>> bisection quantisation).
    max_nfev : int, optional
        Largest number of template evaluations of the search (the final
        central-difference Jacobian adds 2 per free parameter).
    callback : callable, optional
        Called with (parameter dict, numbers) after each evaluation.

    Returns
    -------
    CalibrationResult
    """
    if not targets:
        raise InputError("no targets given")
    for k, (v, s) in targets.items():
        if not (math.isfinite(v) and s > 0):
            raise InputError(f"target {k!r} needs a finite value and a positive sigma")
    names = list(free)
    if not names:
        raise InputError("no free parameters given")
    for n in names:
        lo, hi = free[n]
        if not lo < getattr(params0, n) < hi:
            raise InputError(f"start value of {n!r} ({getattr(params0, n)}) is outside "
                             f"its bounds {free[n]}")
    logp = [n for n in names if free[n][0] > 0] if log_params is None else list(log_params)

    def fwd(n, v):
        return math.log(v) if n in logp else v

    def inv(n, v):
        return math.exp(v) if n in logp else v

    keys = list(targets)
    data = np.array([targets[k][0] for k in keys])
    sigma = np.array([targets[k][1] for k in keys])
    numbers = {}

    def model(u):
        p = params0.replace(**{n: inv(n, u[n]) for n in names})
        nums = template_numbers(p, settings)
        numbers[tuple(sorted(u.items()))] = nums
        if callback is not None:
            callback({n: getattr(p, n) for n in names}, nums)
        return np.array([nums[k] for k in keys])

    fit = fit_parameters(model, data, sigma, {n: fwd(n, getattr(params0, n)) for n in names},
                         {n: (fwd(n, free[n][0]), fwd(n, free[n][1])) for n in names},
                         diff_step=diff_step, max_evaluations=max_nfev, central=True)
    best = {n: inv(n, fit.values[n]) for n in names}
    # errors of the parameters themselves (log-space errors times the value)
    scale = np.array([best[n] if n in logp else 1.0 for n in names])
    cov = fit.covariance * np.outer(scale, scale)
    err = np.sqrt(np.clip(np.diag(cov), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(err, err)
    params = params0.replace(**best)
    return CalibrationResult(
        params=params, values=best, errors=dict(zip(names, map(float, err))),
        covariance=cov, correlation=corr, names=names,
        model=numbers[tuple(sorted(fit.values.items()))],
        targets={k: tuple(v) for k, v in targets.items()}, chi2=fit.chi2,
        n_evaluations=fit.n_evaluations, seconds=fit.seconds)
