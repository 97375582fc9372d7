"""What the joint star-field fit says: chi2, tension, information and the precision it leaves.

The report steps of
:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`, from the
fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`'s dict) to the
entries of :class:`~lsst_bfdrift.calibration.star_result.StarCalibrationResult`:

* :func:`fit_chi2`: each data set's chi2 with T_a and with T(c);
* :func:`tension_test`: the rise of the total chi2 from the flats' optimum
  when the stars are added, against chi2 with as many degrees of freedom as
  fitted slopes;
* :func:`star_information` and :func:`direction_coefficients`: per model
  direction, the stars' share of its Fisher information, and its steps;
* :func:`uncertainty_report`: the move within the a-matrix's errors and the
  precision of the corrected slopes it leaves (:func:`lag_changes`,
  :func:`slope_precision`).
"""

import numpy as np
from scipy import stats

from lsst_bfdrift.calibration.star_result import STAR_SLOPES, fields_for_precision
from lsst_bfdrift.calibration.star_solve import fitted_rows

__all__ = ["TENSION_P", "N_DRIVERS", "fit_chi2", "tension_test", "tension_drivers",
           "star_information", "direction_coefficients", "lag_changes", "slope_precision",
           "uncertainty_report"]

#: The tension's p-value below which the report names the worst rows.
TENSION_P = 1e-3
#: Lags and slopes named as the tension's drivers.
N_DRIVERS = 3


def fit_chi2(final, rows, star_scale=1.0):
    """chi2 of the a-matrix and of the stars, with T_a and with T(c).

    The star chi2 uses the bootstrap errors as measured: a scale absorbs a
    field of another sensor as readily as noise the bootstrap misses, so the
    chi2 (and the tension) stay blind to it (the fit's weights and
    covariance use the scaled errors).

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`).
    rows : AmatrixRows
    star_scale : float, optional
        The factor the fit's star errors were scaled by.

    Returns
    -------
    chi2 : dict
        ``flats_only`` and ``joint``: ``amatrix`` and ``stars`` chi2;
        ``n_amatrix``, ``n_stars`` (fitted slopes).
    star_sigma : ndarray
        The star rows' errors as measured (inf where not fitted).
    """
    n_a = rows.size
    r_fin, a_sig = final["r_fin"], rows.sigma
    sig_s = final["sig_s"] / star_scale
    return {"flats_only": {"amatrix": float(np.sum(((rows.start - rows.measured) / a_sig) ** 2)),
                           "stars": float(np.sum((final["r_s0"] / sig_s) ** 2))},
            "joint": {"amatrix": float(np.sum((r_fin[:n_a] / a_sig) ** 2)),
                      "stars": float(np.sum((r_fin[n_a:] / sig_s) ** 2))},
            "n_amatrix": int(n_a), "n_stars": int(np.isfinite(sig_s).sum())}, sig_s


def tension_test(final, rows, star_sigma, fields, *, fitted_slopes=("size",)):
    """Can one template satisfy the a-matrix and the stars?

    The rise of the total chi2 from the flats' optimum T_a when the star
    slopes are added: the a-matrix chi2 of the template's change plus the
    stars' chi2 left, against chi2 with as many degrees of freedom as
    fitted slopes.

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`).
    rows : AmatrixRows
    star_sigma : ndarray
        The star rows' errors as measured (:func:`fit_chi2`).
    fields : sequence of StarField or SpotField
        The fitted data sets (they name the star rows).
    fitted_slopes : sequence of str, optional
        The slopes fitted on data sets that state none of their own
        (:func:`~lsst_bfdrift.calibration.star_solve.fitted_rows`).

    Returns
    -------
    tension : dict
        ``chi2_rise``, ``dof``, ``p_value`` and ``note``; ``drivers``
        (:func:`tension_drivers`: the lags the fit moved most and the
        slopes it left furthest from zero); ``unfitted`` (the slopes
        measured and not fitted: their chi2 after the fit against zero, a
        check); ``worst`` (the three rows of largest pull) when p <
        :data:`TENSION_P`.
    warnings : list of str
        The tension, when p < :data:`TENSION_P`.
    """
    n_a, r_fin, a_sig, sig_s = rows.size, final["r_fin"], rows.sigma, star_sigma
    chi2_s1 = float(np.sum((r_fin[n_a:] / sig_s) ** 2))
    n_s = int(np.isfinite(sig_s).sum())
    rise = float(np.sum((final["a_change"] / a_sig) ** 2)) + chi2_s1
    tension = {"chi2_rise": rise, "dof": n_s, "p_value": float(stats.chi2.sf(rise, n_s)),
               "note": "rise of the total chi2 from the a-matrix-only optimum when the star "
                       "slopes are added; large with a small p-value means the model's "
                       "directions cannot satisfy both data sets",
               "drivers": tension_drivers(final, rows, star_sigma, fields)}
    fitted = fitted_rows(fields, fitted_slopes)
    if not fitted.all():
        # the slopes measured and not fitted, after the fit, against zero (a check: the
        # loop's curl term shows in e1 here first)
        rows_u = ~fitted
        unfitted = [k for i, k in enumerate(STAR_SLOPES) if rows_u[i::3].any()]
        chi2_u = float(np.sum((r_fin[n_a:][rows_u] / final["sig_u"][rows_u]) ** 2))
        tension["unfitted"] = {"slopes": unfitted, "chi2": chi2_u, "dof": int(rows_u.sum()),
                               "p_value": float(stats.chi2.sf(chi2_u, int(rows_u.sum())))}
    if not tension["p_value"] < TENSION_P:
        return tension, []
    sig_d = np.concatenate([a_sig, sig_s])
    worst = np.argsort(-np.abs(r_fin / sig_d))[:3]
    labels = rows.labels() + [f"{f.name}:{k}" for f in fields for k in STAR_SLOPES]
    tension["worst"] = [{"what": labels[w], "pull": float(r_fin[w] / sig_d[w])} for w in worst]
    warning = ("tension between the a-matrix and the stars (p = "
               f"{tension['p_value']:.1e}); worst: " + ", ".join(
                   f"{t['what']} pull {t['pull']:+.1f}" for t in tension["worst"]))
    return tension, [warning]


def tension_drivers(final, rows, star_sigma, fields, *, n=N_DRIVERS):
    """The lags and slopes that drive the tension: what the fit moved, what it left.

    The rise of the chi2 (:func:`tension_test`) has two parts: the
    a-matrix's cost of the template's change from T_a (per measured lag,
    its a_ij change over its error) and the fitted slopes left after the
    fit (per slope, its value over its error). The largest of each are its
    drivers: a spot series' e1 slope that only a 3-sigma change of a10 and
    a01 can null shows as those lags and that slope.

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`):
        ``a_change``, ``r_fin`` and, when given, ``r_s0`` (the slopes with
        T_a).
    rows : AmatrixRows
    star_sigma : ndarray
        The star rows' errors as measured (inf where not fitted; :func:`fit_chi2`).
    fields : sequence of StarField or SpotField
        The fitted data sets (they name the star rows).
    n : int, optional
        How many of each.

    Returns
    -------
    dict
        ``lags``: the ``n`` lags of largest change, each ``what`` (``a{i}{j}``),
        ``change`` (1/e) and ``pull`` (change over error); ``slopes``: the
        ``n`` fitted slopes of largest pull after the fit, each ``what``
        (``<data set>:<slope>``), ``value`` (per 1e5 e), ``pull`` and
        ``pull_flats`` (with T_a; None without ``r_s0``).
    """
    n_a = rows.size
    pa = final["a_change"] / rows.sigma
    labels = rows.labels()
    lags = [{"what": labels[k], "change": float(final["a_change"][k]), "pull": float(pa[k])}
            for k in np.argsort(-np.abs(pa))[:n]]
    r_s = final["r_fin"][n_a:]
    fitted = np.flatnonzero(np.isfinite(star_sigma))
    pulls = r_s[fitted] / star_sigma[fitted]
    names = [f"{f.name}:{k}" for f in fields for k in STAR_SLOPES]
    r0 = final.get("r_s0")
    slopes = [{"what": names[fitted[k]], "value": float(r_s[fitted[k]]),
               "pull": float(pulls[k]),
               "pull_flats": None if r0 is None else float(r0[fitted[k]]
                                                           / star_sigma[fitted[k]])}
              for k in np.argsort(-np.abs(pulls))[:n]]
    return {"lags": lags, "slopes": slopes}


def star_information(final, basis, rows, star_sigma, star_scale=1.0):
    """Per model direction in the fit, the share of its Fisher information from the stars.

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`).
    basis : DirectionBasis
    rows : AmatrixRows
    star_sigma : ndarray
        The star rows' errors as measured (:func:`fit_chi2`).
    star_scale : float, optional
        The factor the fit's star errors were scaled by.

    Returns
    -------
    dict
        Direction name -> F_stars / (F_amatrix + F_stars) of its diagonal
        (None when both are 0).
    """
    cols, Ja, Js = final["cols"], basis.jacobian, final["Js"]
    Fa = Ja[:, cols].T @ (Ja[:, cols] / rows.sigma[:, None] ** 2)
    Fs = Js[:, cols].T @ (Js[:, cols] / (star_scale * star_sigma[:, None]) ** 2)
    return {n: float(Fs[k, k] / (Fa[k, k] + Fs[k, k])) if (Fa[k, k] + Fs[k, k]) > 0 else None
            for k, n in enumerate(final["chosen"], start=basis.n_lag)}


def direction_coefficients(final, basis):
    """Steps of the model directions in the fit, and their parameter changes.

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`).
    basis : DirectionBasis
        ``steps`` (h_k) and ``n_lag`` (the lag directions come first in the
        fit).

    Returns
    -------
    dict
        Direction name -> ``steps`` (c_k) and ``steps_err``,
        ``parameter_change`` (c_k h_k) and ``parameter_change_err``, and
        ``step`` (h_k).
    """
    coef, steps = final["coef"], basis.steps
    err = np.sqrt(np.clip(np.diag(final["cov"]), 0, None))
    return {n: {"steps": float(coef[k]), "steps_err": float(err[k]),
                "parameter_change": float(coef[k] * steps[n]),
                "parameter_change_err": float(abs(err[k] * steps[n])),
                "step": float(steps[n])} for k, n in enumerate(final["chosen"],
                                                               start=basis.n_lag)}


def lag_changes(a_change, rows):
    """The template's a_ij change per measured lag, and in units of its error.

    Parameters
    ----------
    a_change : ndarray
        Change of the a-matrix rows (1/e), in row order.
    rows : AmatrixRows

    Returns
    -------
    dict
        Lag name (``a{i}{j}``, ``a{i},{j}`` beyond lag 9) -> (change, change
        / error).
    """
    d_a = np.full(rows.lag_mask.shape, np.nan)
    d_a[rows.lag_mask] = a_change
    return {(f"a{i}{j}" if max(i, j) < 10 else f"a{i},{j}"): (float(d_a[i, j]),
                                                             float(d_a[i, j]
                                                                   / rows.sigma_lags[i, j]))
            for i, j in zip(*np.nonzero(rows.lag_mask))}


def slope_precision(final, fields, flats_template, *, n_boot=200, seed=20151):
    """How well each fitted field's corrected size and e1 slopes are known.

    Linear propagation of the steps' covariances, from the flats' errors
    alone (``cov_flats``) and with the stars (``cov``); the directions span
    the a-matrix's errors, not the model's own. The size slope's in % of the
    field's uncorrected slope; the e1 slope's in % of the e1 slope the
    flats template removes (the correction's own e1 change on the same
    stars: a field's uncorrected e1 slope is mostly its noise).

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`).
    fields : sequence of StarField
        The fitted fields.
    flats_template : DistortionTemplate
        T_a.
    n_boot, seed : int, optional
        Bootstrap of the fitted stars' slopes.

    Returns
    -------
    size_sigma, e1_sigma : dict
        Field name -> ``flats``, ``joint`` (per 1e5 e), ``flats_percent``,
        ``joint_percent``; for e1 also ``removed`` and, when ``cov_all`` is
        known, ``all_fitted`` (and ``_percent``).
    """
    cols, cov, Js = final["cols"], final["cov"], final["Js"]
    size_sigma, e1_sigma = {}, {}
    for m, f in enumerate(fields):
        before = f.slopes(None, f.fit_stars, n_boot=n_boot, seed=seed)
        flats = f.slopes(flats_template, f.fit_stars, n_boot=n_boot, seed=seed)
        removed = float(before["e1"][0] - flats["e1"][0])
        for i, out, ref in ((0, size_sigma, abs(before["size"][0])),
                            (1, e1_sigma, abs(removed))):
            g = Js[3 * m + i, cols]
            sf, sj = (float(np.sqrt(max(g @ cv @ g, 0.0))) for cv in (final["cov_flats"], cov))
            pf, pj = ((100.0 * v / ref if ref > 0 else float("nan")) for v in (sf, sj))
            out[f.name] = {"flats": sf, "joint": sj, "flats_percent": pf, "joint_percent": pj}
            if i == 1:
                out[f.name]["removed"] = removed
                if final["cov_all"] is not None:
                    sa = float(np.sqrt(max(g @ final["cov_all"] @ g, 0.0)))
                    out[f.name]["all_fitted"] = sa
                    out[f.name]["all_fitted_percent"] = 100.0 * sa / ref if ref > 0 \
                        else float("nan")
    return size_sigma, e1_sigma


def _precision_warnings(uncertainty, size_goal, n_fields):
    """Warnings on the precision of the corrected e1 and size slopes.

    Parameters
    ----------
    uncertainty : dict
        :func:`uncertainty_report`'s, with ``size_slope_sigma`` and
        ``e1_slope_sigma``; ``fields_for_size_goal`` is added to it.
    size_goal : float
        Precision wanted (% of the uncorrected size slope).
    n_fields : int
        Fitted fields.

    Returns
    -------
    list of str
    """
    warnings = []
    e1_sigma, size_sigma = uncertainty["e1_slope_sigma"], uncertainty["size_slope_sigma"]
    e1_pct = np.array([v["joint_percent"] for v in e1_sigma.values()], float)
    if np.all(np.isfinite(e1_pct)) and np.mean(e1_pct) > 100.0:
        per = np.mean([v["joint"] for v in e1_sigma.values()])
        warnings.append(f"the corrected e1 slope is uncertain by +- {np.mean(e1_pct):.0f} % of "
                        f"the e1 slope the flats template removes (+- {per:.1e} per 1e5 e): "
                        "the flats do not pin the sensor's serial/parallel anisotropy, so the "
                        "correction's e1 is not known; more flat pairs (the e1 error falls as "
                        "their square root) or e1 fitted on many fields would pin it")
    if size_sigma:
        fp, jp = (float(np.mean([v[k] for v in size_sigma.values()]))
                  for k in ("flats_percent", "joint_percent"))
        need = fields_for_precision(fp, jp, n_fields, size_goal)
        uncertainty["fields_for_size_goal"] = {"goal_percent": float(size_goal),
                                               "fields": need}
        if np.isfinite(jp) and jp > size_goal:
            how = (f"about {need} fields like these would state it to +- {size_goal:g} % "
                   "(each field's stars add alike), or more flat pairs"
                   if need is not None else
                   "the stars add no measurable precision; more flat pairs would")
            warnings.append(f"the corrected size slope is known to +- {jp:.1f} % of the "
                            f"uncorrected (+- {fp:.1f} % from the flats alone): {how}")
    return warnings


def uncertainty_report(final, basis, rows, fields, flats_template, *, n_boot=200, seed=20151,
                      size_goal=3.0):
    """The move within the a-matrix's errors, and the precision of the corrected slopes.

    The joint template's change from T_a as the a-matrix sees it (exact
    polygon areas, computed by the fit; with model directions in, their
    a_ij change is part of it), what the whole move does to each fitted
    slope (linear), and how well the corrected slopes are known
    (:func:`slope_precision`).

    Parameters
    ----------
    final : dict
        The fit (:func:`~lsst_bfdrift.calibration.star_solve.fit_joint`).
    basis : DirectionBasis
    rows : AmatrixRows
    fields : sequence of StarField
        The fitted fields.
    flats_template : DistortionTemplate
        T_a.
    n_boot, seed : int, optional
        Bootstrap of the fitted stars' slopes.
    size_goal : float, optional
        Precision (% of the uncorrected size slope) the report measures the
        fit against (:func:`~lsst_bfdrift.calibration.star_result.fields_for_precision`).

    Returns
    -------
    uncertainty : dict or None
        ``StarCalibrationResult.uncertainty`` (None without lag directions).
    warnings : list of str
        The e1 slope not known, the size slope short of the goal.
    """
    n_lag = basis.n_lag
    if not n_lag:
        return None, []
    cols, coef, Js = final["cols"], final["coef"], final["Js"]
    pulls = lag_changes(final["a_change"], rows)
    order = sorted(pulls, key=lambda n: -abs(pulls[n][1]))
    moved = Js[:, cols] @ coef
    size_sigma, e1_sigma = slope_precision(final, fields, flats_template, n_boot=n_boot,
                                           seed=seed)
    uncertainty = {
        "n_directions": n_lag,
        "steps": {basis.names[cols[k]]: float(coef[k]) for k in range(n_lag)},
        "chi2": float(sum(v[1] ** 2 for v in pulls.values())),
        "a_change": {n: v[0] for n, v in pulls.items()},
        "largest": [{"lag": n, "a_change": pulls[n][0], "sigma": pulls[n][1]}
                    for n in order[:3]],
        "slope_change": {f.name: {k: float(moved[3 * m + i]) for i, k in enumerate(STAR_SLOPES)}
                         for m, f in enumerate(fields)},
        "size_slope_sigma": size_sigma,
        "e1_slope_sigma": e1_sigma,
        "note": "the joint template's change from the flats template: a_ij change per "
                "lag (1/e) and its chi2 with the a-matrix's errors; steps along the "
                "directions of those errors (the measured lags' area sum kept when the "
                "record's keep_lag_sum is true); size_slope_sigma: per "
                "fitted field, the standard deviation of its corrected size slope (per "
                "1e5 e, and % of its uncorrected slope) that the flats' errors leave, "
                "and that the flats and the stars together leave; e1_slope_sigma: the "
                "same for the e1 slope, in % of the e1 slope the flats template "
                "removes from the field (``removed``, per 1e5 e), and, when e1 is not "
                "fitted, with every measured slope fitted (``all_fitted``)"}
    return uncertainty, _precision_warnings(uncertainty, size_goal, len(fields))
