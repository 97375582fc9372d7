"""Findings of a flat set beside the covariance fit: every observable it carries.

The diagnosis (:mod:`lsst_bfdrift.diagnosis.effects_fit`) fits the
difference-image covariances C_ij(mu) and the pair-sum statistics S_ij(mu).
A flat set carries more, and the base BF model predicts each of these
exactly, so a significant departure is a finding the base model cannot
absorb (the quantities are measured by
:mod:`~lsst_bfdrift.ptc.observables`):

``linearity``
    Mean signal against exposure time (``EXPTIME``): mu = k t + c, with the
    shot noise of the pair mean as error. BF moves pixel boundaries, not
    charge, so the mean stays linear.
``sum_rule``
    The covariances summed over all lags with their multiplicity (4 off the
    axes, 2 on them, 1 at lag 0) against the base model's prediction: BF
    conserves area, so the full sum is mu / gain at every level (the a-matrix
    sums to zero); over lags <= L the base model gives the truncated sum. The
    gain is a free parameter of the fit, so a level-independent scale is
    absorbed: the check sees how the sum changes with the level.
``halves``
    Left/right and bottom/top halves of the image (standing in for
    amplifiers): ratio of their means (a constant offset: gain, illumination
    or response; a change with level: a non-linearity of one half) and
    their covariances C_ij / mu (after the BF slope times the difference of
    their means).
``pair_ratio``
    Mean of the second flat of each pair over the first's, minus 1 (a
    drifting lamp, a shutter). The covariances do not depend on it (the
    second flat is scaled to the first's mean), the linearity check does.
``turnoff``
    The level at which a pair's variance drops (saturation,
    :func:`~lsst_bfdrift.ptc.covariances.ptc_turnoff`); the pairs above are
    left out of the fit and of every check, and listed.

Every finding is a dictionary with ``observable``, ``available``,
``detected`` and, when available, ``value`` and ``error`` (with ``quantity``
and ``unit`` saying what they are), ``sign``, ``levels`` (ADU), ``chi2``,
``dof``, ``p_value`` and ``description``; when not, ``reason``. Errors are
statistical: shot noise of the pixels (through the sum rule, var of a pixel
total = mu / gain + read noise), and the per-lag covariance errors of the
fit. A lamp that fluctuates by 1e-4 between exposures is a real finding at
these errors (``linearity``, ``pair_ratio``), and is named as such.
"""


import numpy as np
from scipy import stats

from lsst_bfdrift.ptc.observables import (SPLITS, exposure_line, lag_error_factors,
                                          pair_mean_errors, pair_ratios, pixel_variance,
                                          weighted_mean)
from lsst_bfdrift.simulation.effects import BASE_OBSERVABLES
from lsst_bfdrift.templates.refine import lag_multiplicity
from lsst_bfdrift.utils.errors import InputError

__all__ = ["CHECKS", "not_available", "linearity_finding", "sum_rule_finding",
           "table_sum_rule_finding", "halves_finding", "pair_ratio_finding",
           "turnoff_finding", "assess_observables", "credit_findings"]

#: The checks made beside the covariance fit, in report order.
CHECKS = ("linearity", "sum_rule", "halves", "pair_ratio", "turnoff")


def not_available(name, reason):
    """Finding of an observable the input does not carry."""
    return {"observable": name, "available": False, "detected": False, "reason": reason,
            "description": f"{name}: not available with these data ({reason})"}


def _finding(name, **kw):
    d = {"observable": name, "available": True, "detected": False, "value": None,
         "error": None, "quantity": "", "unit": "", "sign": "", "levels": [], "chi2": None,
         "dof": None, "p_value": None, "description": ""}
    d.update(kw)
    return d


def linearity_finding(mu, exptime, sigma, *, exposure_scatter=0.0, scatter_dof=None,
                      p_threshold=1e-3):
    """Mean signal against exposure time: fit mu = k t + c and its residuals.

    Parameters
    ----------
    mu : array_like, shape (n,)
        Pair means (ADU).
    exptime : array_like, shape (n,)
        Exposure times (s).
    sigma : array_like, shape (n,)
        Shot-noise errors of ``mu`` (ADU).
    exposure_scatter : float, optional
        Relative scatter of one flat's exposure beyond shot noise (lamp,
        shutter; :func:`exposure_scatter` measures it from the pairs). Each
        pair mean gets ``exposure_scatter * mu / sqrt(2)`` added to its
        error in quadrature, so that random exposure noise is not taken for
        a non-linearity.
    scatter_dof : int, optional
        Degrees of freedom of an ``exposure_scatter`` that was estimated
        (pairs - 1). The residual is then tested with an F test, chi2 / dof
        against F(dof, scatter_dof), which accounts for the estimate's own
        noise; without it (a known scatter, or none) with chi2.
    p_threshold : float, optional
        p-value below which the residual is a finding.

    Returns
    -------
    dict
        The finding (module documentation) with ``slope`` (ADU/s) and
        ``offset`` (ADU) and their errors, ``offset_time`` (s, c / k: a shutter
        delay), per pair ``deviation`` ((mu - k t - c) / (k t + c)) and
        ``pull``; ``value`` and ``error`` are the relative deviation of the
        pair with the largest pull, at ``level``.
    """
    name = "linearity"
    mu, t, s = (np.asarray(v, float) for v in (mu, exptime, sigma))
    scatter = float(exposure_scatter)
    if not np.isfinite(scatter) or scatter < 0:
        raise InputError(f"exposure_scatter must be >= 0, got {exposure_scatter}")
    s = np.sqrt(s**2 + (scatter * mu) ** 2 / 2.0)
    if not np.all(np.isfinite(t) & (t > 0)):
        return not_available(name, "exposure times must be positive (s)")
    distinct = np.unique(np.round(np.log(t), 3)).size
    if distinct < 3:
        return not_available(name, f"{distinct} distinct exposure time(s); a line with an "
                                   "offset needs at least 3")
    coef, cov = exposure_line(mu, t, s)
    model = coef[0] * t + coef[1]
    res = mu - model
    pull = res / s
    chi2 = float(np.sum(pull**2))
    dof = mu.size - 2
    use_f = scatter > 0 and scatter_dof is not None and int(scatter_dof) > 0
    p = float(stats.f.sf(chi2 / dof, dof, int(scatter_dof)) if use_f
              else stats.chi2.sf(chi2, dof))
    dev, dev_err = res / model, s / model
    k = int(np.argmax(np.abs(pull)))
    detected = p < p_threshold
    bad = [float(mu[j]) for j in np.flatnonzero(np.abs(pull) > 3.0)] or [float(mu[k])]
    above = dev[k] > 0
    noise = ("shot noise" if scatter == 0
             else f"shot noise and {scatter * 100:.2g} % exposure scatter")
    desc = (f"linearity: the mean departs from a line in exposure time (chi2 {chi2:.1f} for "
            f"{dof} dof, p = {p:.1e}); largest at {mu[k]:.4g} ADU (t = {t[k]:.4g} s): "
            f"{abs(dev[k]) * 100:.3g} % {'above' if above else 'below'} the line "
            f"(+- {dev_err[k] * 100:.2g} %, pull {pull[k]:+.1f}); a non-linear signal chain "
            "or exposure (shutter, lamp) - BF moves no charge and cannot make it"
            ) if detected else (
        f"linearity: mean linear in exposure time within "
        f"{noise}"
        f" (chi2 {chi2:.1f} for "
        f"{dof} dof, p = {p:.2f}; largest deviation {dev[k] * 100:+.2g} +- "
        f"{dev_err[k] * 100:.2g} % at {mu[k]:.4g} ADU)")
    return _finding(name, detected=bool(detected), value=float(dev[k]),
                    error=float(dev_err[k]), quantity="relative deviation from mu = k t + c "
                    "of the pair with the largest pull", unit="", level=float(mu[k]),
                    sign="+" if above else "-", levels=bad, chi2=chi2, dof=int(dof), p_value=p,
                    slope=float(coef[0]), slope_err=float(np.sqrt(cov[0, 0])),
                    offset=float(coef[1]), offset_err=float(np.sqrt(cov[1, 1])),
                    offset_time=float(coef[1] / coef[0]), deviation=dev.tolist(),
                    pull=pull.tolist(), exptime=t.tolist(), exposure_scatter=scatter,
                    test="F" if use_f else "chi2", description=desc)


def sum_rule_finding(mu, cov, model, sigma, gain, *, p_threshold=1e-3):
    """The covariances summed over lags against the base BF model, per level.

    Parameters
    ----------
    mu : array_like, shape (n,)
        Pair means (ADU).
    cov, model, sigma : array_like, shape (n, L + 1, L + 1)
        Measured C_ij, the base model's (fitted) C_ij and the errors of the
        measured ones (ADU^2), lags [i, j] >= 0.
    gain : float
        The base fit's gain (e/ADU).
    p_threshold : float, optional

    Returns
    -------
    dict
        The finding with per level ``residual`` (sum over lags with
        multiplicity of measured minus model, over mu / g) and its ``sigma``,
        ``measured_sum`` and ``model_sum`` (same normalisation: the base model's
        truncated sum is below 1 by the a_ij beyond lag L); ``chi2`` over levels
        with n - 1 dof (the gain absorbs a common scale); ``value`` and
        ``error``: the weighted mean residual.
    """
    name = "sum_rule"
    mu = np.asarray(mu, float)
    cov, model, sigma = (np.asarray(v, float) for v in (cov, model, sigma))
    m = lag_multiplicity(cov.shape[1] - 1)
    norm = mu / gain
    res = np.sum(m * (cov - model), axis=(1, 2)) / norm
    err = np.sqrt(np.sum((m * sigma) ** 2, axis=(1, 2))) / norm
    pull = res / err
    chi2 = float(np.sum(pull**2))
    dof = max(mu.size - 1, 1)
    p = float(stats.chi2.sf(chi2, dof))
    mean, mean_err = weighted_mean(res, err)
    k = int(np.argmax(np.abs(pull)))
    detected = p < p_threshold
    bad = [float(mu[j]) for j in np.flatnonzero(np.abs(pull) > 3.0)] or [float(mu[k])]
    word = "more" if res[k] > 0 else "less"
    desc = (f"sum rule: the covariances summed over lags (4/2/1 per off-axis/axis/zero lag) "
            f"break the area conservation of BF (chi2 {chi2:.1f} for {dof} dof, p = {p:.1e}); "
            f"at {mu[k]:.4g} ADU they sum to {abs(res[k]) * 100:.2g} % {word} than the BF model "
            f"(+- {err[k] * 100:.2g} %, pull {pull[k]:+.1f}): a non-linear gain or anything that "
            "adds or removes variance, not a rearrangement of pixel boundaries"
            ) if detected else (
        f"sum rule: obeyed within errors (chi2 {chi2:.1f} for {dof} dof, p = {p:.2f}; mean "
        f"residual {mean * 100:+.2g} +- {mean_err * 100:.2g} % of mu/g)")
    return _finding(name, detected=bool(detected), value=mean, error=mean_err,
                    quantity="weighted mean over levels of (sum of C_ij - model) / (mu / g)",
                    unit="", sign="+" if mean > 0 else "-", levels=bad, chi2=chi2,
                    dof=int(dof), p_value=p, residual=res.tolist(), sigma=err.tolist(),
                    measured_sum=(np.sum(m * cov, axis=(1, 2)) / norm).tolist(),
                    model_sum=(np.sum(m * model, axis=(1, 2)) / norm).tolist(),
                    description=desc)


def table_sum_rule_finding(a, sigma, model, mask, *, p_threshold=1e-3):
    """The sum rule of an a-matrix table: sum over lags <= L (with multiplicity)
    of the measured a_ij minus the base model's (whose full sum is zero).

    Parameters
    ----------
    a, sigma, model : array_like, shape (L + 1, L + 1)
        Measured a_ij, their errors (taken as independent) and the fitted base
        model (per e).
    mask : array_like of bool
        Lags in the fit; a00 left out means the table's a00 was set by the sum
        rule, which then cannot be tested.
    p_threshold : float, optional

    Returns
    -------
    dict
        The finding; ``value`` and ``error`` in 1/e, ``table_sum`` and
        ``model_sum`` the two sums, ``relative`` the value over abs(a00).
    """
    name = "sum_rule"
    if not np.asarray(mask, bool)[0, 0]:
        return not_available(name, "the table's a00 was set by the sum rule")
    a, sigma, model = (np.asarray(v, float) for v in (a, sigma, model))
    m = lag_multiplicity(a.shape[0] - 1)
    r = float(np.sum(m * (a - model)))
    e = float(np.sqrt(np.sum((m * sigma) ** 2)))
    chi2 = (r / e) ** 2
    p = float(stats.chi2.sf(chi2, 1))
    detected = p < p_threshold
    desc = (f"sum rule: the table's a_ij sum to {r:+.3g} +- {e:.2g} /e more than the BF model "
            f"over lags <= {a.shape[0] - 1} (p = {p:.1e}; {abs(r / a[0, 0]) * 100:.2g} % of "
            "|a00|): the table breaks the area conservation of BF") if detected else (
        f"sum rule: obeyed within the table's errors ({r:+.3g} +- {e:.2g} /e, p = {p:.2f})")
    return _finding(name, detected=bool(detected), value=r, error=e,
                    quantity="sum over lags (4/2/1) of a_ij - model", unit="1/e",
                    sign="+" if r > 0 else "-", chi2=chi2, dof=1, p_value=p,
                    table_sum=float(np.sum(m * a)), model_sum=float(np.sum(m * model)),
                    relative=float(r / abs(a[0, 0])) if a[0, 0] else None,
                    description=desc)


def _slopes(mu, cov, npix):
    """d(C_ij / mu) / d mu of the whole image (weighted line per lag), shape (L+1, L+1)."""
    f = lag_error_factors(cov.shape[1] - 1)
    s = cov[:, 0, 0][:, None, None] * f / np.sqrt(npix) / mu[:, None, None]
    y = cov / mu[:, None, None]
    out = np.zeros(cov.shape[1:])
    if np.unique(mu).size < 2:
        return out
    for i in range(cov.shape[1]):
        for j in range(cov.shape[2]):
            A = np.stack([np.ones_like(mu), mu], axis=1) / s[:, i, j][:, None]
            out[i, j] = np.linalg.lstsq(A, y[:, i, j] / s[:, i, j], rcond=None)[0][1]
    return out


def halves_finding(mu, cov, npix, halves, gain, noise, *, p_threshold=1e-3):
    """Differences between the image halves (left/right, bottom/top).

    For each split and pair: the ratio of the halves' means minus 1,
    rho = mu_B / mu_A - 1 (error from the shot noise of each half's total),
    and the difference of their C_ij / mu after the BF slope (from the whole
    image) times mu_B - mu_A. Three tests per split: a constant offset of rho
    (gain, illumination or response), rho changing with the level (chi2 about
    its mean, n - 1 dof: a non-linearity of one half), and the covariances
    (chi2 over lags and pairs). The finding is detected when the smallest
    p-value times the number of tests (Bonferroni) is below ``p_threshold``.
    The variances tell a gain difference (C00 / mu follows the means: ratio
    ``gain_ratio`` ~ rho) from one of illumination or response (C00 / mu
    unchanged).

    Parameters
    ----------
    mu : array_like, shape (n,)
        Whole-image pair means (ADU).
    cov, npix : array_like, shape (n, L + 1, L + 1)
        Whole-image C_ij (ADU^2) and pixel pairs (for the BF slope).
    halves : sequence of dict
        Per pair, ``pair_observables(...)["halves"]``.
    gain, noise : float
        e/ADU and read noise (e^2) of the base fit (shot-noise errors).
    p_threshold : float, optional

    Returns
    -------
    dict
        The finding with ``splits``: split -> ``mean_ratio`` (rho, its weighted
        mean and error), ``gain_ratio`` (of C00 / mu, mean and error),
        ``p_offset``, ``p_trend``, ``p_covariances`` and the chi2 values.
    """
    name = "halves"
    mu = np.asarray(mu, float)
    cov = np.asarray(cov, float)
    npix = np.asarray(npix, float)
    slope = _slopes(mu, cov, npix)
    f = lag_error_factors(cov.shape[1] - 1)
    splits, reasons, ptests = {}, [], []
    for split, (na, nb) in SPLITS.items():
        rows = [h[split] for h in halves]
        why = next((r for r in rows if isinstance(r, str)), None)
        if why is not None:
            reasons.append(f"{split}: {why}")
            continue
        m = np.array([r["mu"] for r in rows])
        nv = np.array([r["nvalid"] for r in rows])
        c = np.array([r["cov"] for r in rows])
        npx = np.array([r["npix"] for r in rows])
        var = pixel_variance(m, gain, noise) / (2.0 * nv) / m**2  # relative, pair mean
        rho = m[:, 1] / m[:, 0] - 1.0
        srho = np.sqrt(var.sum(axis=1)) * (1.0 + rho)
        rbar, rerr = weighted_mean(rho, srho)
        z = rbar / rerr
        p_off = float(2.0 * stats.norm.sf(abs(z)))
        chi2_t = float(np.sum(((rho - rbar) / srho) ** 2))
        p_trend = float(stats.chi2.sf(chi2_t, max(rho.size - 1, 1)))
        # C_ij / mu per half; the BF slope times the difference of the means removed
        y = c / m[:, :, None, None]
        sy = c[:, :, 0, 0][:, :, None, None] * f / np.sqrt(npx) / m[:, :, None, None]
        d = y[:, 1] - y[:, 0] - slope * (m[:, 1] - m[:, 0])[:, None, None]
        sd = np.sqrt(sy[:, 0] ** 2 + sy[:, 1] ** 2)
        chi2_c = float(np.sum((d / sd) ** 2))
        dof_c = int(d.size)
        p_cov = float(stats.chi2.sf(chi2_c, dof_c))
        g = d[:, 0, 0] / y[:, 0, 0, 0]
        gbar, gerr = weighted_mean(g, sd[:, 0, 0] / y[:, 0, 0, 0])
        ptests += [(p_off, split, "offset"), (p_trend, split, "trend"),
                   (p_cov, split, "covariances")]
        splits[split] = {"halves": [na, nb], "mean_ratio": rho.tolist(),
                         "mean_ratio_sigma": srho.tolist(), "mean_ratio_mean": rbar,
                         "mean_ratio_err": rerr, "p_offset": p_off, "chi2_trend": chi2_t,
                         "dof_trend": int(max(rho.size - 1, 1)), "p_trend": p_trend,
                         "chi2_covariances": chi2_c, "dof_covariances": dof_c,
                         "p_covariances": p_cov, "gain_ratio_mean": gbar, "gain_ratio_err": gerr}
    if not splits:
        return not_available(name, "; ".join(reasons) or "no halves measured")
    p_min, split, test = min(ptests)
    p = float(min(1.0, p_min * len(ptests)))
    detected = p < p_threshold
    s = splits[split]
    na, nb = SPLITS[split]
    rho = np.array(s["mean_ratio"])
    if test == "covariances":
        value, err = s["gain_ratio_mean"], s["gain_ratio_err"]
        quantity = f"relative difference of C00 / mu, {nb} over {na}"
        chi2, dof = s["chi2_covariances"], s["dof_covariances"]
        levels = mu.tolist()
    elif test == "trend":
        k = int(np.argmax(np.abs(rho - s["mean_ratio_mean"]) / np.array(s["mean_ratio_sigma"])))
        value, err = float(rho[k] - s["mean_ratio_mean"]), s["mean_ratio_sigma"][k]
        quantity = f"mean ratio {nb}/{na} at one level minus its mean over levels"
        chi2, dof = s["chi2_trend"], s["dof_trend"]
        levels = [float(mu[k])]
    else:
        value, err = s["mean_ratio_mean"], s["mean_ratio_err"]
        quantity = f"mean ratio {nb}/{na} - 1, weighted over levels"
        chi2, dof = (value / err) ** 2, 1
        levels = mu.tolist()
    if detected:
        gbar, gerr, rbar = s["gain_ratio_mean"], s["gain_ratio_err"], s["mean_ratio_mean"]
        if test == "offset":
            if abs(gbar) > 3 * gerr and abs(gbar - rbar) < 3 * gerr:
                cause = "the variances follow the means: a gain difference"
            elif abs(gbar) < 3 * gerr and abs(gbar - rbar) > 3 * gerr:
                cause = "the variances do not follow: illumination or response, not gain"
            else:
                cause = "the variances cannot tell gain from illumination at these errors"
            what = (f"the {nb} half is {abs(rbar) * 100:.3g} % "
                    f"{'brighter' if rbar > 0 else 'dimmer'}"
                    f" than the {na} half (+- {s['mean_ratio_err'] * 100:.2g} %, at every level)")
        elif test == "trend":
            cause = "a non-linearity of one half (or of the illumination with the level)"
            what = (f"the mean ratio {nb}/{na} changes with the level (chi2 {chi2:.1f} for "
                    f"{dof} dof), most at {levels[0]:.4g} ADU ({value * 100:+.2g} %)")
        else:
            cause = "the halves have different covariances (gain or BF of their own)"
            what = (f"the {nb} half's covariances differ from the {na} half's (chi2 {chi2:.0f} "
                    f"for {dof} points)")
        desc = (f"halves: {what}, p = {p:.1e} (Bonferroni over {len(ptests)} tests); "
                f"C00/mu ratio {gbar * 100:+.2g} +- {gerr * 100:.2g} %: {cause}; "
                "the base BF model is the same in every part of the image")
    else:
        desc = (f"halves: consistent (smallest p = {p_min:.2g}, {split} {test}; Bonferroni "
                f"p = {p:.2f}); mean ratios " + ", ".join(
                    f"{SPLITS[k][1]}/{SPLITS[k][0]} {v['mean_ratio_mean'] * 100:+.2g} +- "
                    f"{v['mean_ratio_err'] * 100:.2g} %" for k, v in splits.items()))
    return _finding(name, detected=bool(detected), value=float(value), error=float(err),
                    quantity=quantity, unit="", sign="+" if value > 0 else "-",
                    levels=levels, chi2=float(chi2), dof=int(dof), p_value=p, split=split,
                    test=test, splits=splits, not_measured=reasons, description=desc)


def pair_ratio_finding(mu, mu1, mu2, nvalid, gain, noise, *, p_threshold=1e-3):
    """The second flat of each pair over the first: r = mu2 / mu1 - 1.

    Parameters
    ----------
    mu, mu1, mu2, nvalid, gain, noise
        As :func:`~lsst_bfdrift.ptc.observables.pair_ratios`, which gives r
        and its shot-noise error sqrt(2 V / N) / mu (V the variance of a
        pixel total).
    p_threshold : float, optional

    Returns
    -------
    dict
        The finding with per pair ``ratio`` (r) and ``pull``; ``value`` and
        ``error``: r of the pair with the largest pull, at ``level``; ``mean``
        and ``mean_err``: weighted mean of r.
    """
    name = "pair_ratio"
    mu, r, s = pair_ratios(mu, mu1, mu2, nvalid, gain, noise)
    pull = r / s
    chi2 = float(np.sum(pull**2))
    dof = int(mu.size)
    p = float(stats.chi2.sf(chi2, dof))
    mean, mean_err = weighted_mean(r, s)
    k = int(np.argmax(np.abs(pull)))
    detected = p < p_threshold
    bad = [float(mu[j]) for j in np.flatnonzero(np.abs(pull) > 3.0)] or [float(mu[k])]
    desc = (f"pair ratio: the two flats of a pair differ by more than shot noise (chi2 "
            f"{chi2:.1f} for {dof} pairs, p = {p:.1e}); at {mu[k]:.4g} ADU the second flat is "
            f"{abs(r[k]) * 100:.3g} % {'brighter' if r[k] > 0 else 'dimmer'} (+- "
            f"{s[k] * 100:.2g} %, pull {pull[k]:+.1f}); {len(bad)} pair(s) beyond 3 sigma; a "
            "drifting lamp or a shutter, not BF (the covariances scale the second flat to the "
            "first and do not see it)") if detected else (
        f"pair ratio: the two flats of each pair agree within shot noise (chi2 {chi2:.1f} for "
        f"{dof} pairs, p = {p:.2f}; mean {mean * 100:+.2g} +- {mean_err * 100:.2g} %)")
    return _finding(name, detected=bool(detected), value=float(r[k]), error=float(s[k]),
                    quantity="mu2 / mu1 - 1 of the pair with the largest pull", unit="",
                    level=float(mu[k]), sign="+" if r[k] > 0 else "-", levels=bad, chi2=chi2,
                    dof=dof, p_value=p, mean=mean, mean_err=mean_err, ratio=r.tolist(),
                    pull=pull.tolist(), description=desc)


def turnoff_finding(info, *, unit="ADU"):
    """The break level from :func:`turnoff_cut`'s ``info`` (or an equivalent dict).

    Returns
    -------
    dict
        The finding: ``value`` the break level (the last point kept, ADU),
        ``interval`` (last kept, first excluded), ``excluded`` (the points left
        out of the fit), ``significance`` (the first excluded point's drop in
        units of its error, when the pixel counts are known) and ``p_value``
        (one-sided normal). Detected when points were excluded.
    """
    name = "turnoff"
    if not info["excluded"]:
        return _finding(name, description=f"turn-off: none; the variance rises to the top "
                        f"level ({info['mu_max']:.4g} {unit})", unit=unit,
                        quantity="break level", excluded=[], drop=info["drop"])
    brk = info["break_level"]
    first = info["excluded"][0]
    rel = info.get("rel_error")
    z = p = None
    if rel:
        z = first["drop"] / (np.sqrt(2.0) * rel)
        p = float(stats.norm.sf(z))
    lv = ", ".join(f"{e['mu']:.4g}" for e in info["excluded"][:8])
    more = f" (+{len(info['excluded']) - 8})" if len(info["excluded"]) > 8 else ""
    desc = (f"turn-off: the variance falls {first['drop'] * 100:.0f} % below its running "
            f"maximum above {brk:.4g} {unit} (saturation; threshold {info['drop'] * 100:.0f} %"
            + (f", {z:.0f} sigma" if z is not None else "") + f"); {len(info['excluded'])} "
            f"point(s) left out of the fit at {lv}{more} {unit}")
    return _finding(name, detected=True, value=float(brk), error=None, unit=unit,
                    quantity="break level (last point kept)", sign="-",
                    levels=[e["mu"] for e in info["excluded"]], p_value=p,
                    interval=[float(brk), float(first["mu"])], excluded=info["excluded"],
                    significance=None if z is None else float(z), drop=info["drop"],
                    description=desc)


def assess_observables(obs, *, model=None, sigma=None, gain=None, noise=0.0,
                       p_threshold=1e-3):
    """Every check of :data:`CHECKS` for one input, available or not.

    Parameters
    ----------
    obs : Observations
        Kind 'flats' (the per-pair quantities of
        :func:`~lsst_bfdrift.diagnosis.observations.observations_from_pairs`
        when present), 'ptc' or 'table'.
    model : ndarray, optional
        The base fit's prediction: C_ij, shape (n, L + 1, L + 1) (ADU^2) for
        'flats', a_ij (L + 1, L + 1) (per e) for 'table'.
    sigma : ndarray, optional
        Errors of the covariances (ADU^2, 'flats').
    gain, noise : float, optional
        The base fit's gain (e/ADU) and read noise (e^2), 'flats'.
    p_threshold : float, optional

    Returns
    -------
    dict
        Check name -> finding.
    """
    out = {}
    kind = obs.kind
    if kind == "table":
        out["linearity"] = not_available("linearity", "an a-matrix table has no means or "
                                                      "exposure times")
        if not np.asarray(obs.mask)[0, 0]:
            out["sum_rule"] = not_available("sum_rule", "the table's a00 was set by the sum "
                                                        "rule (left out of the fit)")
        elif model is None:
            out["sum_rule"] = not_available("sum_rule", "no base fit")
        else:
            out["sum_rule"] = table_sum_rule_finding(obs.a, obs.sigma, model, obs.mask,
                                                     p_threshold=p_threshold)
        out["halves"] = not_available("halves", "an a-matrix table has no image halves")
        out["pair_ratio"] = not_available("pair_ratio", "an a-matrix table has no flats")
        out["turnoff"] = not_available("turnoff", "an a-matrix table has no variances "
                                                  "against the signal")
        return out
    if kind == "ptc":
        out["linearity"] = not_available("linearity", "a PTC text file has no exposure times")
        out["sum_rule"] = not_available("sum_rule", "a PTC carries the variance (lag 0) only")
        out["halves"] = not_available("halves", "a PTC carries no image halves")
        out["pair_ratio"] = not_available("pair_ratio", "a PTC carries no means of each flat")
        out["turnoff"] = turnoff_finding(obs.turnoff) if getattr(obs, "turnoff", None) \
            else not_available("turnoff", "no turn-off information")
        return out
    extra = getattr(obs, "pairs", None)
    no_pairs = "statistics given as arrays (Observations.from_flats), not flat pairs"
    t = getattr(obs, "exptime", None)
    if t is not None and extra is not None and gain:
        sig_mu, scatter = pair_mean_errors(obs.mu, extra, gain, noise)
        out["linearity"] = linearity_finding(obs.mu, t, sig_mu, exposure_scatter=scatter,
                                             scatter_dof=len(extra) - 1,
                                             p_threshold=p_threshold)
    else:
        out["linearity"] = not_available("linearity", getattr(obs, "exptime_note", None)
                                         or "no exposure times")
    if model is not None and sigma is not None and gain:
        out["sum_rule"] = sum_rule_finding(obs.mu, obs.cov, model, sigma, gain,
                                           p_threshold=p_threshold)
    else:
        out["sum_rule"] = not_available("sum_rule", "no base fit")
    if extra is not None and gain:
        out["halves"] = halves_finding(obs.mu, obs.cov, obs.npix, [e["halves"] for e in extra],
                                       gain, noise, p_threshold=p_threshold)
        out["pair_ratio"] = pair_ratio_finding(
            obs.mu, [e["mu1"] for e in extra], [e["mu2"] for e in extra],
            [e["nvalid"] for e in extra], gain, noise, p_threshold=p_threshold)
    else:
        out["halves"] = not_available("halves", no_pairs)
        out["pair_ratio"] = not_available("pair_ratio", no_pairs)
    out["turnoff"] = turnoff_finding(obs.turnoff) if getattr(obs, "turnoff", None) \
        else not_available("turnoff", "no turn-off information")
    return out


def credit_findings(findings, library, added):
    """Say which effects move each finding's observable; list the signatures.

    Each finding gets ``moved_by`` (effects of ``library`` whose
    ``observables`` include it), ``explained_by`` (those of ``added``) and
    ``base_model_moves`` (False for every check: the base BF model moves only
    the covariances, :data:`~lsst_bfdrift.simulation.effects.BASE_OBSERVABLES`).

    Parameters
    ----------
    findings : dict
        From :func:`assess_observables` (changed in place).
    library, added : sequence of Effect
        The candidates, and those the diagnosis added.

    Returns
    -------
    list of str
        One sentence per detected finding, for the verdict: its description
        and which effect, if any, could produce it.
    """
    out = []
    for name, f in findings.items():
        f["moved_by"] = [e.name for e in library if name in getattr(e, "observables", ())]
        f["explained_by"] = [e.name for e in added if name in getattr(e, "observables", ())]
        f["base_model_moves"] = name in BASE_OBSERVABLES
        if not f["detected"]:
            continue
        if f["explained_by"]:
            tail = f"moved by the added {', '.join(f['explained_by'])}"
        elif f["moved_by"]:
            tail = (f"not produced by the base BF model; {', '.join(f['moved_by'])} could, but "
                    "the covariance fit did not add it")
        elif name == "turnoff":
            tail = "not a model effect: those points are not fitted"
        else:
            tail = "not produced by the base BF model nor by any effect of the library"
        out.append(f"{f['description']} [{tail}]")
    return out
