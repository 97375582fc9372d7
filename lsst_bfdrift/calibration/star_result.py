"""The result of the joint star-field calibration and its text report.

:class:`StarCalibrationResult` is what
:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars` returns: the
jointly calibrated template, the fit's chi2, tension and coefficients, the
move within the a-matrix's errors with the precision it leaves, and the
held-out (cross-validated) slopes, with the one-line and table summaries the
CLI and the benchmarks print; :func:`joint_template` gives the jointly
calibrated template its metadata.
"""

import numpy as np

from lsst_bfdrift.templates.refine import combine_templates, without_parameter_modes

__all__ = ["STAR_SLOPES", "StarCalibrationResult", "fields_for_precision", "joint_template"]

#: The star slopes measured on every field, in the order of the fit's star vector.
STAR_SLOPES = ("size", "e1", "e2")


def fields_for_precision(flats_percent, joint_percent, n_fields, goal_percent):
    """Number of star fields like the fitted ones that would state the size slope to a goal.

    The joint fit is a Gaussian update of the flats' estimate: each field's
    stars add the same information, ``(1 / joint^2 - 1 / flats^2) / n_fields``,
    to the flats' ``1 / flats^2``. This inverts that for the goal.

    Parameters
    ----------
    flats_percent, joint_percent : float
        Standard deviation of the corrected size slope that the flats' errors
        leave, and that the flats and the ``n_fields`` fitted fields leave
        (% of the uncorrected slope; ``uncertainty['size_slope_sigma']``).
    n_fields : int
        Fields in the fit.
    goal_percent : float
        The standard deviation wanted (% of the uncorrected slope).

    Returns
    -------
    int or None
        Fields needed (``n_fields`` or fewer when the goal is met already; 0
        when the flats alone meet it); None when the stars add no measurable
        information (``joint_percent`` not below ``flats_percent``) or an
        input is not finite.

    Raises
    ------
    ValueError
        When a precision or the goal is not positive, or ``n_fields`` < 1.
    """
    f, j, g = (float(v) for v in (flats_percent, joint_percent, goal_percent))
    if not all(np.isfinite(v) for v in (f, j, g)):
        return None
    if min(f, j, g) <= 0 or int(n_fields) < 1:
        raise ValueError(f"precisions and goal must be > 0 and n_fields >= 1, got flats {f}, "
                         f"joint {j}, goal {g}, n_fields {n_fields}")
    if f <= g:
        return 0
    per_field = (1.0 / j ** 2 - 1.0 / f ** 2) / int(n_fields)
    if per_field <= 1e-12 / f ** 2:
        return None
    return int(np.ceil((1.0 / g ** 2 - 1.0 / f ** 2) / per_field - 1e-9))


class StarCalibrationResult:
    """Result of :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars` and
    :func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`.

    Attributes
    ----------
    template : DistortionTemplate
        The jointly calibrated template T(c).
    flats_template : DistortionTemplate
        The a-matrix-only template T_a it started from.
    directions : list of str
        The model directions used (chosen by the data; the lags of the flats'
        uncertainty are always in and are reported in ``uncertainty``).
    uncertainty : dict or None
        The move within the a-matrix's errors (None with
        ``flats_uncertainty=False``): ``n_directions`` and ``steps`` along
        each direction of those errors; the joint template's change from the
        flats template as the a-matrix sees it (all directions, exact
        polygon areas): ``a_change`` per lag (1/e), ``chi2`` (with the
        a-matrix's errors), ``largest`` (the three largest a_ij changes, also
        in units of their errors, ``sigma``); ``slope_change`` (per fitted
        field, the size, e1 and e2 slope change of the whole move, per 1e5 e);
        ``size_slope_sigma`` (per fitted field, the standard deviation of its
        corrected size slope that the a-matrix's errors leave, ``flats``, and
        that they and the stars leave, ``joint``: per 1e5 e, and
        ``*_percent`` of the field's uncorrected slope; propagated linearly
        from the steps' covariances, so the model's own error beyond the
        a-matrix's is not in it); ``e1_slope_sigma``, the same for the e1
        slope, in % of the e1 slope the flats template removes from the
        field (``removed``, per 1e5 e: the correction's own e1 change, as a
        field's uncorrected e1 slope is mostly its noise), and, when e1 is
        not fitted, ``all_fitted`` (and ``_percent``): the same with every
        measured slope fitted, what ``fitted_slopes=('size', 'e1', 'e2')``
        would give (the fit itself is not changed); ``fields_for_size_goal``
        (``goal_percent`` and ``fields``: how many fields like the fitted
        ones would state the size slope to the goal,
        :func:`fields_for_precision` on the fields' mean precisions).
    coefficients : dict
        Per direction: ``steps`` (c_k), ``parameter_change`` (c_k h_k, in the
        parameter's unit) and its error.
    covariance : ndarray
        Covariance of the coefficients c.
    chi2 : dict
        ``amatrix`` and ``stars`` chi2 with T_a (``flats_only``) and with
        T(c) (``joint``), and the number of points of each.
    tension : dict
        Rise of the a-matrix chi2 needed to null the fitted star slopes, its
        degrees of freedom and p-value; ``drivers``: the lags the fit moved
        most and the slopes it left furthest from zero
        (:func:`~lsst_bfdrift.calibration.star_report.tension_drivers`);
        ``unfitted``: the chi2 of the slopes measured and not fitted, after
        the fit, against zero.
    star_information : dict
        Per direction, the share of the Fisher information from the stars.
    fit_slopes, held_out : dict
        Slopes (value, error; per 1e5 e) of the fitted and of the held-out
        stars (or spot rows), per field or spot series: ``before``,
        ``flats_only``, ``joint``; ``held_out`` also names each data set's
        ``kind`` (``stars`` or ``spots``).
    fields : list of dict
        Per data set: name, kind and counts
        (:func:`~lsst_bfdrift.calibration.star_fit.fields_summary`).
    selection : list of dict
    star_error_scale : float
        Factor applied to the fitted slopes' bootstrap errors (1: none;
        ``scale_star_errors``).
    seconds : dict
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def summary(self):
        """JSON-friendly summary."""
        keys = ("directions", "coefficients", "uncertainty", "chi2", "tension",
                "star_information", "star_error_scale",
                "fit_slopes", "held_out", "selection", "seconds", "fields", "warnings")
        out = {k: getattr(self, k) for k in keys}
        out["covariance"] = np.asarray(self.covariance).tolist()
        return out

    def uncertainty_line(self):
        """One line on the move within the a-matrix's errors ('' without it)."""
        u = self.uncertainty
        if not u:
            return ""
        sc = u["slope_change"]
        return (f"within the a-matrix's errors ({u['n_directions']} directions): chi2 cost "
                f"{u['chi2']:.2f}; largest a_ij changes " + ", ".join(
                    f"{d['lag']} {d['sigma']:+.2f} sigma" for d in u["largest"])
                + "; fitted size slopes moved by " + ", ".join(
                    f"{v['size']:+.2e}" for v in sc.values()) + " per 1e5 e"
                + self._sigma_text(u.get("size_slope_sigma"), u.get("e1_slope_sigma")))

    @staticmethod
    def _sigma_text(ss, se):
        if not ss:
            return ""
        f, j = (np.mean([v[k] for v in ss.values()]) for k in ("flats_percent", "joint_percent"))
        text = (f"; the corrected size slope is known to +- {f:.1f} % of the uncorrected "
                f"from the flats' errors, +- {j:.1f} % with the stars")
        if se:
            f, j = (np.nanmean([v[k] for v in se.values()])
                    for k in ("flats_percent", "joint_percent"))
            text += (f"; the e1 slope to +- {f:.1f} % and +- {j:.1f} % of the e1 slope the "
                     "flats template removes")
            a = [v["all_fitted_percent"] for v in se.values() if "all_fitted_percent" in v]
            if a:
                text += f" (+- {np.nanmean(a):.1f} % with the e1 and e2 slopes fitted too)"
        return text

    def tension_line(self):
        """The tension's p-value and drivers, and the chi2 of the slopes measured and not
        fitted."""
        t = self.tension
        line = f"tension p = {t['p_value']:.2g} ({t['dof']} fitted slopes)"
        d = t.get("drivers")
        if d:
            line += ("; driven by the a_ij moved (" + ", ".join(
                f"{x['what']} {x['pull']:+.1f} sigma" for x in d["lags"]) + ") and the slopes "
                "left (" + ", ".join(f"{x['what']} {x['pull']:+.1f} sigma" for x in d["slopes"])
                + ")")
        u = t.get("unfitted")
        if u:
            line += (f"; {', '.join(u['slopes'])} not fitted, after the fit chi2 "
                     f"{u['chi2']:.1f} / {u['dof']} (p = {u['p_value']:.2g})")
        return line

    def held_out_table(self):
        """Text table of the held-out slopes (the validation)."""
        lines = []
        for name, d in self.held_out.items():
            b = d["before"]
            spots = d.get("kind") == "spots"
            how = " (two-fold cross-validation)" if "folds" in d else ""
            count = f"{d['n_stars']} spot rows" if spots else f"{d['n_stars']} stars"
            lines.append(f"held-out {'spots' if spots else 'stars'} of {name}{how} ({count}), "
                         "slopes per 1e5 e (% of before):")
            for what in ("before", "flats_only", "joint"):
                row = d[what]
                cells = []
                for k in ("size", "e1"):
                    v, e = row[k]
                    pct = 100 * v / b[k][0] if b[k][0] else float("nan")
                    cells.append(f"{k} {v:+.3e} +- {e:.1e} ({pct:+6.1f} %)")
                lines.append(f"  {what:<11s} " + "  ".join(cells))
        return "\n".join(lines)


def joint_template(template, flats_template, stars_meta, *, key="stars"):
    """The joint template with the star (or spot) calibration in its metadata.

    Parameters
    ----------
    template : DistortionTemplate
        T(c); when it is ``flats_template`` itself (no direction in the
        fit), a copy is made, so the input is not modified.
    flats_template : DistortionTemplate
        T_a: its metadata are the base of the result's.
    stars_meta : dict
        Stored as ``meta['calibration'][key]``. The flats' ``parameter_modes``
        (:func:`~lsst_bfdrift.calibration.tuning.parameter_modes`) leave the
        stored uncertainty: the stars or spots measure what they describe.
    key : str, optional
        ``'stars'``, or ``'spots'`` when spot series are in the fit.

    Returns
    -------
    DistortionTemplate
    """
    if template is flats_template:
        template = combine_templates(flats_template, [], [])
    meta = dict(flats_template.meta)
    # the stars or spots measure how area changes divide between column and row
    # edges: the flats' parameter modes of that part are not carried
    calib = without_parameter_modes(meta.get("calibration"))
    calib[key] = stars_meta
    meta["calibration"] = calib
    template.meta = meta
    return template
