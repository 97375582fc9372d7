"""Brighter-fatter slopes of a star field without truth: size and shape against flux.

The brighter-fatter effect makes bright stars larger (and slightly more
elongated along the parallel axis) than faint stars with the same PSF. On a
real image there is no BF-free truth, but every star samples the same PSF
field, so the BF signature is a dependence of star size and shape on flux at
fixed position. For each star catalog (:func:`~lsst_bfdrift.catalogs.catalog.measure_stars`)
and each quantity q in (ln T, e1, e2), :func:`fit_flux_slope` fits

.. math::

    q_i = \\sum_k a_k P_k(x_i, y_i) + s\\,F_i / 10^5 + b / \\nu_i^2 + c\\,10^5 / F_i

where P_k are the monomials of a 2-d polynomial of order ``poly_order`` in
the star position (the PSF's variation over the field), F_i the flux (e),
``s`` the slope (per 1e5 e; for ln T the fractional size change), and
``b / nu^2 + c 10^5 / F`` absorbs the noise bias of adaptive moments
(nu = signal-to-noise ratio): the sky's noise and the star's own photon
noise bias the moments with coefficients of their own (1 / nu^2 = (F + sky
variance in the aperture) / F^2 mixes them in a fixed ratio), so both terms
are fitted when the fluxes are given. With the 1 / nu^2 term alone, 36
BF-free GalSim fields of 800 stars (photons binned on square pixels, sky
1000 e) gave a size slope of +3.9e-5 +- 0.6e-5 per 1e5 e (6 sigma; 5 % of
GalSim ITL's brighter-fatter slope); with both, +0.2e-5 +- 0.9e-5
(``benchmarks/stars/star_slope_bias.py``). The price is a slope error 1.4 times
larger. Stars are weighted by
``1 / (alpha^2 / nu_i^2 + beta^2 / F_i + tau^2)``: measurement noise of
adaptive moments falling as 1 / SNR, an extra term of the star's own photon
noise (it sits in the core, where the moment weight is largest, so at the
same SNR a source-dominated star measures its size less well than a
sky-dominated one: 1.0 / SNR against 1.7 / SNR on the GalSim ITL field of
``benchmarks/stars/calibrate_stars.py``), and an intrinsic scatter tau
(PSF-model residuals), with alpha, beta and tau fitted to the squared
residuals (non-negative least squares; beta only when the fluxes are given);
outliers are down-weighted by Huber iteratively reweighted least squares
(c = 1.345), and the formal errors are scaled by the reduced chi^2. With at
least 30 stars the slope error is the larger of the formal error and a
seeded bootstrap over stars (robust spread of the bootstrap slopes).
LSST's verification quotes the slope of size against magnitude; the same
fit with the magnitude instead of the flux is reported as ``size_mag``
(fractional T per magnitude; BF makes it negative).

The star-field calibration (:mod:`~lsst_bfdrift.calibration.star_fit`) fits
the template so that these slopes vanish after correction; the sky validation
(:func:`~lsst_bfdrift.validation.sky.validate_sky`) reports them before and
after.
"""

import numpy as np
from scipy.optimize import nnls

from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.catalogs.catalog import FLAG_NAMES

__all__ = ["FLUX_UNIT", "birge_scale", "fit_flux_slope", "select_stars", "shape_flux_relations"]

#: Flux unit (e) of the slopes: slopes are per 1e5 e.
FLUX_UNIT = 1e5


def _design(x, y, poly_order, regressor, snr, noise_term, frame, flux=None):
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
        if flux is not None and noise_term != "snr":
            cols.append(FLUX_UNIT / np.asarray(flux, float))
            names.append("source_bias")
    return np.column_stack(cols), names


def _wls(a, q, w):
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(a * sw[:, None], q * sw, rcond=None)
    return coef


def _robust_fit(a, q, snr, huber, max_iter=30, flux=None):
    """Huber IRLS with the noise model alpha^2 / snr^2 (+ beta^2 / flux) + tau^2
    fitted to the residuals.

    Returns coef, cov (scaled by the reduced chi^2), (alpha, beta, tau), Huber
    weights, chi^2/dof.
    """
    n, p = a.shape
    inv2 = 1.0 / snr ** 2
    cols = [inv2, np.ones(n)] if flux is None else [inv2, 1.0 / flux, np.ones(n)]
    basis = np.column_stack(cols)
    hw = np.ones(n)
    coef = _wls(a, q, 1.0 / inv2)
    var = inv2.copy()
    pars = np.zeros(basis.shape[1])
    for it in range(max_iter):
        r = q - a @ coef
        # variance model from the squared residuals (outliers clipped), dof-corrected
        r2 = np.minimum(r * r, 25.0 * np.median(r * r / var) * var) * n / max(n - p, 1)
        pars, _ = nnls(basis * np.sqrt(hw)[:, None], r2 * np.sqrt(hw))
        if not np.any(pars > 0):
            pars[0] = float(np.median(r2 / inv2)) or 1e-30
        var = basis @ pars
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
    alpha, tau = float(np.sqrt(pars[0])), float(np.sqrt(pars[-1]))
    beta = float(np.sqrt(pars[1])) if flux is not None else 0.0
    return coef, cov * chi2, (alpha, beta, tau), hw, chi2


def fit_flux_slope(x, y, regressor, q, snr, *, flux=None, poly_order=2, noise_term=True,
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
    flux : array_like, optional
        Flux of each star (e): adds the source-noise term beta^2 / flux to
        the noise model (beta fitted) and, with ``noise_term``, a
        source-noise bias term c 1e5 / flux. Default: no such terms.
    poly_order : int, optional
        Order of the 2-d position polynomial (lowered automatically when
        there are too few stars: at least 4 more stars than parameters).
    noise_term : bool or 'snr', optional
        Fit the noise-bias terms: 1/snr^2, and 1e5/flux when ``flux`` is given
        (True); 'snr': the 1/snr^2 term alone (biased when the sky's and the
        star's noise bias the moments differently; for comparisons); False:
        none.
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
        weight < 1), ``alpha``, ``beta`` (noise model), ``tau`` (intrinsic
        scatter), ``noise_bias`` and ``source_bias`` (the coefficients b and c
        of the noise-bias terms; None when not fitted), ``chi2_dof``, ``poly_order``,
        ``intercept`` (q at the frame centre, faint limit), ``points`` (per-star
        arrays for plots: ``detrended`` = q minus the position polynomial,
        ``trend`` = fitted flux and noise-bias terms, the design ``coef``).

    Raises
    ------
    ValueError
        With fewer than 6 usable stars.
    """
    x, y, g, q, snr = (np.asarray(v, float) for v in (x, y, regressor, q, snr))
    fl = np.ones_like(x) if flux is None else np.asarray(flux, float)
    ok = np.isfinite(x) & np.isfinite(y) & np.isfinite(g) & np.isfinite(q) & np.isfinite(snr) \
        & (snr > 0) & np.isfinite(fl) & (fl > 0)
    x, y, g, q, snr, fl = x[ok], y[ok], g[ok], q[ok], snr[ok], fl[ok]
    fl = None if flux is None else fl
    n = x.size
    if n < 6:
        raise InputError(f"only {n} usable stars; need at least 6 to fit a size-flux slope")
    if np.ptp(g) == 0:
        raise InputError("all stars have the same flux: no slope can be fitted")
    if frame is None:
        frame = (0.5 * (x.min() + x.max()), 0.5 * (y.min() + y.max()),
                 max(0.5 * np.ptp(x), 1.0), max(0.5 * np.ptp(y), 1.0))
    order = int(poly_order)
    if noise_term not in (True, False, "snr"):
        raise InputError(f"noise_term must be True, False or 'snr', got {noise_term!r}")
    n_bias = 0 if not noise_term else 1 if fl is None or noise_term == "snr" else 2
    while order > 0 and (order + 1) * (order + 2) // 2 + 1 + n_bias + 4 > n:
        order -= 1
    a, names = _design(x, y, order, g, snr, noise_term, frame, flux=fl)
    if a.shape[1] + 2 > n:
        raise InputError(f"only {n} usable stars for {a.shape[1]} parameters")
    coef, cov, (alpha_fit, beta_fit, tau), hw, chi2 = _robust_fit(a, q, snr, huber, flux=fl)
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
                c, *_ = _robust_fit(a[idx], q[idx], snr[idx], huber, max_iter=8,
                                    flux=None if fl is None else fl[idx])
            except np.linalg.LinAlgError:
                continue
            boots.append(c[k])
        if len(boots) > 10:
            b = np.asarray(boots)
            # robust spread (normalised interquartile range) of the bootstrap slopes
            err_boot = float(np.subtract(*np.percentile(b, [75, 25])) / 1.349)
    err = max(err_formal, err_boot)
    kb = [names.index(b) for b in ("noise_bias", "source_bias") if b in names]
    trend = a[:, [k] + kb] @ coef[[k] + kb]  # fitted flux and noise-bias terms
    # per-star value with the position polynomial removed (for plots): q - P(x, y)
    detrended = q - (a @ coef - trend)
    points = {"x": x, "y": y, "regressor": g, "detrended": detrended, "trend": trend,
              "snr": snr, "huber_weight": hw, "coef": coef, "names": names, "frame": frame}
    return {"points": points, "slope": float(coef[k]), "slope_err": err, "err_formal": err_formal,
            "err_boot": err_boot, "z": float(coef[k] / err) if err > 0 else float("inf"),
            "n_stars": int(n), "n_downweighted": int(np.sum(hw < 1)), "tau": float(tau),
            "alpha": alpha_fit, "beta": beta_fit,
            "chi2_dof": chi2, "poly_order": order, "intercept": float(coef[0]),
            "noise_bias": float(coef[names.index("noise_bias")]) if noise_term else None,
            "source_bias": float(coef[names.index("source_bias")])
            if "source_bias" in names else None}


def birge_scale(residuals, errors, n_params, *, min_points=6):
    """Factor by which a set of errors understates the scatter of its residuals (Birge ratio).

    Parameters
    ----------
    residuals, errors : array_like
        Residuals of a fit and their errors (same unit); points with an
        infinite or non-positive error carry no weight and are not counted.
    n_params : float
        Parameters the fit took from these points (e.g. the trace of their
        block of the hat matrix).
    min_points : int, optional
        Fewest weighted points for an estimate.

    Returns
    -------
    float
        ``sqrt(chi2 / (n - n_params))`` when it exceeds 1, with at least
        ``min_points`` points and one degree of freedom; otherwise 1 (errors
        are only ever inflated).
    """
    r, e = np.asarray(residuals, float), np.asarray(errors, float)
    ok = np.isfinite(e) & (e > 0) & np.isfinite(r)
    dof = ok.sum() - float(n_params)
    if ok.sum() < min_points or dof < 1:
        return 1.0
    return float(max(1.0, np.sqrt(np.sum((r[ok] / e[ok]) ** 2) / dof)))


def select_stars(catalog, min_snr):
    """Usable stars of a catalog: unflagged, SNR >= ``min_snr``, finite positive T."""
    ok = np.asarray(catalog["use"], bool) & (np.asarray(catalog["snr"], float) >= min_snr)
    ok &= np.isfinite(np.asarray(catalog["T"].value)) & (np.asarray(catalog["T"].value) > 0)
    return ok


def shape_flux_relations(catalog, *, min_snr=30.0, poly_order=2, noise_term=True, n_boot=200,
                         seed=20151, frame=None):
    """Size and ellipticity against flux (and size against magnitude) of a catalog.

    Parameters
    ----------
    catalog : QTable
        From :func:`~lsst_bfdrift.catalogs.catalog.measure_stars` (optionally corrected).
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
        When the catalog has too few usable stars (with the reason).
    """
    n_all = len(catalog)
    if n_all == 0:
        raise InputError("the catalog is empty: no stars detected")
    ok = select_stars(catalog, min_snr)
    if ok.sum() < 6:
        flags = np.asarray(catalog["flags"])
        why = ", ".join(f"{int(np.sum((flags & b) != 0))} {n[5:]}" for b, n in FLAG_NAMES.items()
                        if np.any(flags & b))
        raise InputError(f"only {int(ok.sum())} of {n_all} detections are usable stars with "
                         f"SNR >= {min_snr:g} (flagged: {why or 'none'}); need at least 6")
    x = catalog["x"].value[ok]
    y = catalog["y"].value[ok]
    f = catalog["flux"].value[ok]
    snr = np.asarray(catalog["snr"], float)[ok]
    t = catalog["T"].value[ok]
    kw = dict(flux=f, poly_order=poly_order, noise_term=noise_term, n_boot=n_boot, seed=seed,
              frame=frame)
    out = {"size": fit_flux_slope(x, y, f / FLUX_UNIT, np.log(t), snr, **kw),
           "e1": fit_flux_slope(x, y, f / FLUX_UNIT, np.asarray(catalog["e1"])[ok], snr, **kw),
           "e2": fit_flux_slope(x, y, f / FLUX_UNIT, np.asarray(catalog["e2"])[ok], snr, **kw),
           "size_mag": fit_flux_slope(x, y, -2.5 * np.log10(f), np.log(t), snr, **kw),
           "n_stars": int(ok.sum()), "flux_range": [float(f.min()), float(f.max())]}
    return out


