"""Sky validation without truth: is there a brighter-fatter slope in a star field?

The brighter-fatter effect makes bright stars larger (and slightly more
elongated along the parallel axis) than faint stars with the same PSF. On a
real image there is no BF-free truth, but every star samples the same PSF
field, so the BF signature is a dependence of star size and shape on flux at
fixed position. For each star catalogue (:func:`~lsst_bfdrift.validation.catalog.measure_stars`)
and each quantity q in (ln T, e1, e2), :func:`fit_flux_slope` fits

.. math::

    q_i = \\sum_k a_k P_k(x_i, y_i) + s\\,F_i / 10^5 + b / \\nu_i^2

where P_k are the monomials of a 2-d polynomial of order ``poly_order`` in
the star position (the PSF's variation over the field), F_i the flux (e),
``s`` the slope (per 1e5 e; for ln T the fractional size change), and
``b / nu^2`` absorbs the noise bias of adaptive moments of faint stars
(nu = signal-to-noise ratio). Stars are weighted by
``1 / (alpha^2 / nu_i^2 + tau^2)``: measurement noise of adaptive moments
falling as 1 / SNR plus an intrinsic scatter tau (PSF-model residuals), with
alpha and tau fitted to the squared residuals (non-negative least squares);
outliers are down-weighted by Huber iteratively reweighted least squares
(c = 1.345), and the formal errors are scaled by the reduced chi^2. With at
least 30 stars the slope error is the larger of the formal error and a
seeded bootstrap over stars (robust spread of the bootstrap slopes).
LSST's verification quotes the slope of size against magnitude; the same
fit with the magnitude instead of the flux is reported as ``size_mag``
(fractional T per magnitude; BF makes it negative).

:func:`validate_sky` measures the slopes before and after correction: the
catalogue-level correction (:func:`~lsst_bfdrift.validation.shape_correction.correct_catalog`),
the pixel-level Task (:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask`)
followed by a new catalogue, or both. ``residual_bf_detected`` is True when
any after-correction slope (size, e1 or e2) differs from zero by more than
``z_crit`` standard errors (default 3: a false-alarm probability of about
0.8 % for the three tests together under Gaussian errors).
"""

import numpy as np
from lsst_bfdrift.utils.errors import InputError

__all__ = ["fit_flux_slope", "shape_flux_relations", "validate_sky", "SkyValidation"]

_FLUX_UNIT = 1e5


def _design(x, y, poly_order, regressor, snr, noise_term, frame):
    x0, y0, sx, sy = frame
    u = (np.asarray(x) - x0) / sx
    v = (np.asarray(y) - y0) / sy
    cols = [u ** i * v ** (k - i) for k in range(poly_order + 1) for i in range(k + 1)]
    names = [f"p{i}{k - i}" for k in range(poly_order + 1) for i in range(k + 1)]
    cols.append(np.asarray(regressor, float))
    names.append("slope")
    if noise_term:
        cols.append(1.0 / np.asarray(snr, float) ** 2)
        names.append("noise_bias")
    return np.column_stack(cols), names


def _wls(a, q, w):
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(a * sw[:, None], q * sw, rcond=None)
    return coef


def _robust_fit(a, q, snr, huber, max_iter=30):
    """Huber IRLS with the noise model alpha^2 / snr^2 + tau^2 fitted to the residuals.

    Returns coef, cov (scaled by the reduced chi^2), alpha, tau, Huber weights, chi^2/dof.
    """
    from scipy.optimize import nnls

    n, p = a.shape
    inv2 = 1.0 / snr ** 2
    hw = np.ones(n)
    coef = _wls(a, q, 1.0 / inv2)
    var = inv2.copy()
    alpha2 = tau2 = 0.0
    for it in range(max_iter):
        r = q - a @ coef
        # variance model from the squared residuals (outliers clipped), dof-corrected
        r2 = np.minimum(r * r, 25.0 * np.median(r * r / var) * var) * n / max(n - p, 1)
        (alpha2, tau2), _ = nnls(np.column_stack([inv2, np.ones(n)]) * np.sqrt(hw)[:, None],
                                 r2 * np.sqrt(hw))
        if alpha2 <= 0 and tau2 <= 0:
            alpha2 = float(np.median(r2 / inv2)) or 1e-30
        var = alpha2 * inv2 + tau2
        z = np.abs(r) / np.sqrt(var)
        hw = np.where(z <= huber, 1.0, huber / np.maximum(z, 1e-300))
        coef_new = _wls(a, q, hw / var)
        done = np.max(np.abs(coef_new - coef)) < 1e-9 * (1 + np.max(np.abs(coef)))
        coef = coef_new
        if done and it > 2:
            break
    w = hw / var
    cov = np.linalg.pinv((a * w[:, None]).T @ a)
    r = q - a @ coef
    chi2 = float(np.sum(w * r * r) / max(n - p, 1))
    return coef, cov * chi2, float(np.sqrt(alpha2)), float(np.sqrt(tau2)), hw, chi2


def fit_flux_slope(x, y, regressor, q, snr, *, poly_order=2, noise_term=True,
                   huber=1.345, n_boot=200, seed=20151, frame=None):
    """Robust slope of a star quantity against flux (or magnitude) at fixed position.

    Parameters
    ----------
    x, y : array_like
        Star positions (px).
    regressor : array_like
        Flux / 1e5 e (or magnitude) of each star.
    q : array_like
        The quantity (ln T, e1 or e2).
    snr : array_like
        Signal-to-noise ratio of each star (measurement error alpha / snr,
        alpha fitted).
    poly_order : int, optional
        Order of the 2-d position polynomial (lowered automatically when
        there are too few stars: at least 4 more stars than parameters).
    noise_term : bool, optional
        Fit a 1/snr^2 noise-bias term.
    huber : float, optional
        Huber threshold (standardised residual).
    n_boot : int, optional
        Bootstrap resamples for the slope error (0: formal error only).
    seed : int, optional
        Bootstrap seed.
    frame : tuple, optional
        (x0, y0, sx, sy) normalising the positions; default from the data.

    Returns
    -------
    dict
        ``slope``, ``slope_err`` (max of ``err_formal`` and ``err_boot``),
        ``z`` (slope / slope_err), ``n_stars``, ``n_downweighted`` (Huber
        weight < 1), ``tau`` (intrinsic scatter), ``chi2_dof``, ``poly_order``,
        ``intercept`` (q at the frame centre, faint limit), ``points`` (per-star
        arrays for plots: ``detrended`` = q minus the position polynomial,
        ``trend`` = fitted flux and noise-bias terms, the design ``coef``).

    Raises
    ------
    ValueError
        With fewer than 6 usable stars.
    """
    x, y, g, q, snr = (np.asarray(v, float) for v in (x, y, regressor, q, snr))
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(g) & np.isfinite(q) & np.isfinite(snr) \
        & (snr > 0)
    x, y, g, q, snr = x[ok], y[ok], g[ok], q[ok], snr[ok]
    n = x.size
    if n < 6:
        raise InputError(f"only {n} usable stars; need at least 6 to fit a size-flux slope")
    if np.ptp(g) == 0:
        raise InputError("all stars have the same flux: no slope can be fitted")
    if frame is None:
        frame = (0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max()),
                 max(0.5 * np.ptp(x), 1.0), max(0.5 * np.ptp(y), 1.0))
    order = int(poly_order)
    while order > 0 and (order + 1) * (order + 2) // 2 + 1 + int(noise_term) + 4 > n:
        order -= 1
    a, names = _design(x, y, order, g, snr, noise_term, frame)
    if a.shape[1] + 2 > n:
        raise InputError(f"only {n} usable stars for {a.shape[1]} parameters")
    coef, cov, alpha_fit, tau, hw, chi2 = _robust_fit(a, q, snr, huber)
    k = names.index("slope")
    err_formal = float(np.sqrt(cov[k, k]))
    err_boot = 0.0
    if n_boot and n >= 30:
        rng = np.random.default_rng(seed)
        boots = []
        for _ in range(int(n_boot)):
            idx = rng.integers(0, n, n)
            if np.ptp(g[idx]) == 0:
                continue
            try:
                c, *_ = _robust_fit(a[idx], q[idx], snr[idx], huber, max_iter=8)
            except np.linalg.LinAlgError:
                continue
            boots.append(c[k])
        if len(boots) > 10:
            b = np.asarray(boots)
            # robust spread (normalised interquartile range) of the bootstrap slopes
            err_boot = float(np.subtract(*np.percentile(b, [75, 25])) / 1.349)
    err = max(err_formal, err_boot)
    k_nb = names.index("noise_bias") if noise_term else None
    trend = coef[k] * g + (coef[k_nb] / snr ** 2 if noise_term else 0.0)
    # per-star value with the position polynomial removed (for plots): q - P(x, y)
    detrended = q - (a @ coef - a[:, k] * coef[k] - (a[:, k_nb] * coef[k_nb] if noise_term else 0))
    points = {"x": x, "y": y, "regressor": g, "detrended": detrended, "trend": trend,
              "snr": snr, "huber_weight": hw, "coef": coef, "names": names, "frame": frame}
    return {"points": points,"slope": float(coef[k]), "slope_err": err, "err_formal": err_formal,
            "err_boot": err_boot, "z": float(coef[k] / err) if err > 0 else float("inf"),
            "n_stars": int(n), "n_downweighted": int(np.sum(hw < 1)), "tau": float(tau),
            "alpha": alpha_fit,
            "chi2_dof": chi2, "poly_order": order, "intercept": float(coef[0]),
            "noise_bias": float(coef[names.index("noise_bias")]) if noise_term else None}


def _select(catalog, min_snr):
    ok = np.asarray(catalog["use"], bool) & (np.asarray(catalog["snr"], float) >= min_snr)
    ok &= np.isfinite(np.asarray(catalog["T"].value)) & (np.asarray(catalog["T"].value) > 0)
    return ok


def shape_flux_relations(catalog, *, min_snr=30.0, poly_order=2, noise_term=True, n_boot=200,
                         seed=20151, frame=None):
    """Size and ellipticity against flux (and size against magnitude) of a catalogue.

    Parameters
    ----------
    catalog : QTable
        From :func:`~lsst_bfdrift.validation.catalog.measure_stars` (optionally corrected).
    min_snr : float, optional
        Stars below this signal-to-noise ratio are not used.
    poly_order, noise_term, n_boot, seed, frame
        See :func:`fit_flux_slope`.

    Returns
    -------
    dict
        ``size`` (slope of ln T: fractional T change per 1e5 e), ``e1``, ``e2``
        (change per 1e5 e), ``size_mag`` (fractional T per magnitude), each a
        :func:`fit_flux_slope` result; ``n_stars``, ``flux_range`` (e).

    Raises
    ------
    ValueError
        When the catalogue has too few usable stars (with the reason).
    """
    n_all = len(catalog)
    if n_all == 0:
        raise InputError("the catalogue is empty: no stars detected")
    ok = _select(catalog, min_snr)
    if ok.sum() < 6:
        flags = np.asarray(catalog["flags"])
        from lsst_bfdrift.validation.catalog import FLAG_NAMES
        why = ", ".join(f"{int(np.sum((flags & b) != 0))} {n[5:]}" for b, n in FLAG_NAMES.items()
                        if np.any(flags & b))
        raise InputError(f"only {int(ok.sum())} of {n_all} detections are usable stars with "
                         f"SNR >= {min_snr:g} (flagged: {why or 'none'}); need at least 6")
    x = catalog["x"].value[ok]
    y = catalog["y"].value[ok]
    f = catalog["flux"].value[ok]
    snr = np.asarray(catalog["snr"], float)[ok]
    t = catalog["T"].value[ok]
    kw = dict(poly_order=poly_order, noise_term=noise_term, n_boot=n_boot, seed=seed, frame=frame)
    out = {"size": fit_flux_slope(x, y, f / _FLUX_UNIT, np.log(t), snr, **kw),
           "e1": fit_flux_slope(x, y, f / _FLUX_UNIT, np.asarray(catalog["e1"])[ok], snr, **kw),
           "e2": fit_flux_slope(x, y, f / _FLUX_UNIT, np.asarray(catalog["e2"])[ok], snr, **kw),
           "size_mag": fit_flux_slope(x, y, -2.5 * np.log10(f), np.log(t), snr, **kw),
           "n_stars": int(ok.sum()), "flux_range": [float(f.min()), float(f.max())]}
    return out


class SkyValidation:
    """Result of :func:`validate_sky`.

    Attributes
    ----------
    summary : dict
        JSON-ready: ``before`` and ``after`` (per route) relations, verdict
        fields ``bf_detected_before``, ``residual_bf_detected``,
        ``significance_before``, ``significance_after`` (absolute z of the size
        slope), ``removed_fraction`` and ``verdict`` (a sentence).
    catalog : QTable
        Catalogue of the recorded image.
    corrected : dict of QTable
        Corrected catalogue per route (``catalog``, ``pixel``).
    fits : dict
        Relations per catalogue name (``before``, and each route).
    """

    def __init__(self, summary, catalog, corrected, fits):
        self.summary = summary
        self.catalog = catalog
        self.corrected = corrected
        self.fits = fits


def _compact(rel):
    out = {}
    for k in ("size", "e1", "e2", "size_mag"):
        r = rel[k]
        out[k] = {"slope": r["slope"], "slope_err": r["slope_err"], "z": r["z"],
                  "err_formal": r["err_formal"], "err_boot": r["err_boot"], "tau": r["tau"],
                  "alpha": r["alpha"],
                  "chi2_dof": r["chi2_dof"], "n_downweighted": r["n_downweighted"],
                  "poly_order": r["poly_order"]}
    out["n_stars"] = rel["n_stars"]
    out["flux_range_e"] = rel["flux_range"]
    return out


def validate_sky(exposure, *, gain=None, mask=None, saturation=None, template=None,
                 route="catalog", method="drift", z_crit=3.0, min_snr=30.0, poly_order=2,
                 noise_term=True, n_boot=200, seed=20151, history=0.5, catalog_kwargs=None,
                 progress=False):
    """Size- and ellipticity-flux slopes of the stars of an image, before and after correction.

    Parameters
    ----------
    exposure : ndarray, CCDData, NDData or path
        The image (electrons, or ADU with ``gain`` / GAIN keyword). Never modified.
    gain : float, optional
        e/ADU.
    mask : array_like of bool, optional
        Bad pixels.
    saturation : float, optional
        Saturation level in the image unit (default: SATURATE keyword).
    template : DistortionTemplate, optional
        Green's function of the corrections (default: the bundled template).
    route : {'catalog', 'pixel', 'both', 'none'}, optional
        Correction route(s) to validate.
    method : str, optional
        Task method for the pixel route.
    z_crit : float, optional
        Significance (standard errors) at which a slope counts as detected.
    min_snr, poly_order, noise_term, n_boot, seed
        See :func:`shape_flux_relations`.
    history : float, optional
        History factor of the catalogue-level correction.
    catalog_kwargs : dict, optional
        Extra options of :func:`~lsst_bfdrift.validation.catalog.measure_stars`.
    progress : bool, optional
        Progress messages on stderr.

    Returns
    -------
    SkyValidation
    """
    from astropy import units as u
    from astropy.nddata import CCDData

    from lsst_bfdrift.validation.catalog import load_electrons, measure_stars
    from lsst_bfdrift.validation.shape_correction import correct_catalog

    if route not in ("catalog", "pixel", "both", "none"):
        raise InputError(f"route must be catalog, pixel, both or none, got {route!r}")
    if not z_crit > 0:
        raise InputError(f"z_crit must be positive, got {z_crit}")
    data, bad, sat_e, g = load_electrons(exposure, gain=gain, mask=mask, saturation=saturation)
    ckw = dict(catalog_kwargs or {})
    cat = measure_stars(data, mask=bad, saturation=sat_e, progress=progress, **ckw)
    ny, nx = data.shape
    frame = (0.5 * (nx - 1), 0.5 * (ny - 1), 0.5 * nx, 0.5 * ny)
    kw = dict(min_snr=min_snr, poly_order=poly_order, noise_term=noise_term, n_boot=n_boot,
              seed=seed, frame=frame)
    fits = {"before": shape_flux_relations(cat, **kw)}
    corrected = {}
    if route != "none" and template is None:
        from lsst_bfdrift.templates.template import load_default_template
        template = load_default_template()
    if route in ("catalog", "both"):
        corrected["catalog"] = correct_catalog(cat, data, template=template, mask=bad,
                                               history=history)
        fits["catalog"] = shape_flux_relations(corrected["catalog"], **kw)
    if route in ("pixel", "both"):
        from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
        cfg = BrighterFatterDriftConfig(method=method, compute_geometry=False,
                                        saturation=sat_e)
        res = BrighterFatterDriftTask(config=cfg, template=template).run(
            CCDData(data, unit=u.electron, mask=bad))
        corrected["pixel"] = measure_stars(np.asarray(res.exposure.data), mask=bad,
                                           saturation=sat_e, **ckw)
        fits["pixel"] = shape_flux_relations(corrected["pixel"], **kw)
    before = fits["before"]
    z_before = abs(before["size"]["z"])
    summary = {"image_shape": [int(ny), int(nx)], "gain": g, "route": route,
               "z_crit": float(z_crit), "min_snr": float(min_snr),
               "n_detections": len(cat), "n_stars_used": before["n_stars"],
               "units": {"size": "fractional change of T = Ixx + Iyy per 1e5 e",
                         "e1": "change of e1 per 1e5 e", "e2": "change of e2 per 1e5 e",
                         "size_mag": "fractional change of T per magnitude"},
               "before": _compact(before),
               "bf_detected_before": bool(z_before > z_crit),
               "significance_before": z_before}
    routes = [r for r in ("catalog", "pixel") if r in fits]
    summary["after"] = {r: _compact(fits[r]) for r in routes}
    if routes:
        zs = {r: max(abs(fits[r][k]["z"]) for k in ("size", "e1", "e2")) for r in routes}
        worst = max(routes, key=lambda r: zs[r])
        summary["residual_bf_detected"] = bool(zs[worst] > z_crit)
        summary["significance_after"] = {r: abs(fits[r]["size"]["z"]) for r in routes}
        summary["max_significance_after"] = {r: zs[r] for r in routes}
        s0 = before["size"]["slope"]
        summary["removed_fraction"] = {r: (1 - fits[r]["size"]["slope"] / s0) if s0 else None
                                       for r in routes}
        summary["verdict"] = _verdict(summary, fits, routes, z_crit)
    else:
        summary["residual_bf_detected"] = bool(z_before > z_crit)
        summary["verdict"] = ("BF slope detected (uncorrected image)" if z_before > z_crit
                              else "no BF slope detected (uncorrected image)") \
            + f": size slope z = {before['size']['z']:+.1f}"
    return SkyValidation(summary, cat, corrected, fits)


def _verdict(summary, fits, routes, z_crit):
    before = fits["before"]["size"]
    parts = []
    if summary["bf_detected_before"]:
        parts.append(f"BF size-flux slope detected before correction "
                     f"({before['slope']:+.2e} +- {before['slope_err']:.1e} per 1e5 e, "
                     f"z = {before['z']:+.1f})")
    else:
        parts.append(f"no significant BF slope before correction (z = {before['z']:+.1f}); "
                     "the stars cannot show whether a correction works")
    for r in routes:
        s = fits[r]["size"]
        bad = [k for k in ("size", "e1", "e2") if abs(fits[r][k]["z"]) > z_crit]
        if bad:
            what = ", ".join(f"{k} z = {fits[r][k]['z']:+.1f}" for k in bad)
            # BF makes stars grow with flux: a positive residual size slope is BF left over
            kind = ("under-corrected" if s["slope"] > 0 else "over-corrected") \
                if "size" in bad else "residual shape slope"
            parts.append(f"{r} route: residual BF slope remains ({what}; {kind})")
        else:
            parts.append(f"{r} route: BF removed, residual size slope {s['slope']:+.2e} +- "
                         f"{s['slope_err']:.1e} (z = {s['z']:+.1f}) and e1/e2 slopes within "
                         f"{z_crit:g} sigma")
    return "; ".join(parts)
