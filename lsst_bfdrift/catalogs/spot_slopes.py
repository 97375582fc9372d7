"""Brighter-fatter slopes of a spot series, their errors, and their prediction by a template.

The same spots are seen at many fluxes, so the BF signature is a change of
each spot's moments with its flux. For each quantity q of
:data:`~lsst_bfdrift.catalogs.spots.SPOT_QUANTITIES` (sigma_x, sigma_y in px;
size = ln T; e1; e2), :func:`fit_spot_slope` fits

.. math::

    q_{ki} = a_k + s\\,F_{ki} / 10^5 + \\epsilon_{ki}

over spots k and images i: one intercept per spot (the spots of a projector
differ in size and shape from one another; a_k is spot k's BF-free value,
the faint limit) and one common slope s (per 1e5 e, the unit of the star
slopes, :data:`~lsst_bfdrift.catalogs.slopes.FLUX_UNIT`). There is no term
per image: within an image all spots have nearly the same flux, so such a
term would take the slope itself; common changes of an exposure (focus,
projector) enter through the errors instead. The fit is weighted least
squares with weights ``1 / (err_ki^2 + tau^2)``: ``err_ki`` the propagated
pixel noise of the row (:func:`~lsst_bfdrift.catalogs.spots.fixed_weight_moments`)
and ``tau`` an extra scatter per row, zero unless the residuals scatter
beyond the errors (then chosen so that chi2 per degree of freedom is 1).

The slope's error is the largest of three estimates, each reported:

* ``err_formal``: the weighted least-squares error (with tau);
* ``err_image``: the formal error scaled by the Birge ratio of the images'
  mean residuals (each image's weighted mean residual against its error,
  2 parameters: the slope and the level): a common change of one exposure
  (focus, projector) moves all its spots together, so its residuals do not
  average down over the spots; this is the image-to-image scatter;
* ``err_spot``: the formal error scaled by the Birge ratio of the per-spot
  slopes about the common one (spots with 3 or more rows, 1 parameter):
  spots whose slopes differ from one another, the spot-to-spot scatter.

Both ratios only inflate (:func:`~lsst_bfdrift.catalogs.slopes.birge_scale`,
at least 3 images or spots). On 40 synthetic series of 9 spots and 5
exposures (the generator of ``tests/catalogs/test_spots.py``), the pulls of
the sigma_x, sigma_y and e2 slopes have standard deviations 1.0, 0.8 and
0.8 (the formal error alone: 1.2, 0.9, 0.9); with a common size change per
exposure 20 times the row noise, 1.2 (the formal error alone: 6.8); with the
spots' slopes scattered by 30 %, 1.0 (formal: 2.7).

:func:`predict_spot_slopes` predicts the slopes of the same rows from a
template: each spot's BF-free profile (a pixel-integrated elliptical
Gaussian whose fixed-weight moments equal the spot's intercepts, or the
flux-normalised sum of its faint stamps) is scaled to each row's flux, put
through the drift forward model
(:func:`~lsst_bfdrift.correction.solvers.recorded_image`) and measured with
the same fixed weight; the predicted values are fitted with the measured
rows' weights, so that predicted and measured slopes are the same
functional of the same design.
"""

import numpy as np
from scipy.optimize import brentq

from lsst_bfdrift.catalogs.slopes import FLUX_UNIT, birge_scale
from lsst_bfdrift.catalogs.spots import (SPOT_QUANTITIES, fixed_weight_moments,
                                         spot_flag_counts)
from lsst_bfdrift.correction.settings import RECOMMENDED
from lsst_bfdrift.correction.solvers import recorded_image
from lsst_bfdrift.templates.swept import SweptAreas
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["fit_spot_slope", "spot_slopes", "slope_values", "predict_spot_slopes",
           "compare_slopes", "SPOT_MODELS"]

#: BF-free spot models of :func:`predict_spot_slopes`.
SPOT_MODELS = ("gaussian", "stamp")


def _group_mean(groups, values, w):
    """Weighted mean of ``values`` within each group, returned per element."""
    sw = np.bincount(groups, w)
    sv = np.bincount(groups, w * values)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = sv / sw
    return mean[groups]


def fit_spot_slope(spot, image, flux, q, q_err, *, tau=None, scale_errors=False, min_points=6):
    """Common slope of a spot quantity against flux, one intercept per spot.

    Parameters
    ----------
    spot, image : array_like of int
        Spot and image of each row.
    flux : array_like
        Flux (e) of each row.
    q, q_err : array_like
        The quantity and its error (propagated pixel noise).
    tau : float, optional
        Extra scatter per row (q's unit); default: fitted (0 unless chi2 per
        degree of freedom exceeds 1). Give the measured fit's to weight a
        prediction like the measurement.
    scale_errors : bool, optional
        Scale the row errors by the square root of chi2 per degree of
        freedom, down as well as up (then tau is 0): for rows whose errors
        set only the relative weights, such as differences of paired images
        (BF minus its BF-free twin), whose noise the row errors overstate.
    min_points : int, optional
        Fewest rows.

    Returns
    -------
    dict
        ``slope`` (q per 1e5 e), ``slope_err`` (the largest of
        ``err_formal``, ``err_image``, ``err_spot``), ``z``, ``tau``,
        ``chi2_dof`` (with the row errors alone), ``n_points``, ``n_spots``,
        ``n_images``, ``per_spot`` (``spot``, ``slope``, ``slope_err``,
        ``intercept`` arrays; spots with 3 or more rows get a slope, others
        NaN), ``spread_chi2_dof`` (per-spot slopes about the common one),
        ``image_chi2_scale``, ``spot_chi2_scale`` (the two Birge ratios),
        ``points`` (per row: ``spot``, ``image``, ``regressor`` = flux / 1e5,
        ``detrended`` = q minus the spot's intercept, ``err``).

    Raises
    ------
    InputError
        Fewer than ``min_points`` usable rows, fewer than 2 spots with 2
        rows, or no flux range within the spots.
    """
    spot, image = np.asarray(spot, np.int64), np.asarray(image, np.int64)
    f, q, e = (np.asarray(v, float) for v in (flux, q, q_err))
    ok = np.isfinite(f) & np.isfinite(q) & np.isfinite(e) & (e > 0)
    counts = np.bincount(spot[ok]) if ok.any() else np.zeros(0, int)
    ok &= np.isin(spot, np.flatnonzero(counts >= 2))
    spot, image, f, q, e = spot[ok], image[ok], f[ok], q[ok], e[ok]
    n = int(q.size)
    ids, sp = np.unique(spot, return_inverse=True)
    if n < int(min_points) or ids.size < 2:
        raise InputError(f"only {n} usable rows in {ids.size} spots (with 2 or more images "
                         f"each); need at least {int(min_points)} rows and 2 spots to fit a "
                         "size-flux slope")
    g = f / FLUX_UNIT
    k = ids.size + 1
    dof = n - k
    if dof < 1:
        raise InputError(f"{n} rows for {k} parameters (one intercept per spot and the slope)")

    def solve(tau2):
        w = 1.0 / (e * e + tau2)
        xt = g - _group_mean(sp, g, w)
        yt = q - _group_mean(sp, q, w)
        sxx = float(np.sum(w * xt * xt))
        if not sxx > 0:
            raise InputError("the spots' fluxes do not vary: no slope can be fitted (one "
                             "exposure time?)")
        s = float(np.sum(w * xt * yt) / sxx)
        return w, xt, yt, sxx, s, yt - s * xt

    w, xt, yt, sxx, s, r = solve(0.0)
    chi2_dof0 = float(np.sum(w * r * r) / dof)
    if scale_errors and chi2_dof0 > 0:
        e = e * np.sqrt(chi2_dof0)
        w, xt, yt, sxx, s, r = solve(0.0)
        tau = 0.0
    tau2 = 0.0 if tau is None else float(tau) ** 2
    if tau is None and chi2_dof0 > 1.0:
        for _ in range(30):  # tau^2 with chi2 / dof = 1, the residuals refitted
            hi = max(float(np.max(r * r)), 1e-300)
            new = brentq(lambda t2: np.sum(r * r / (e * e + t2)) - dof, 0.0, hi * n) \
                if np.sum(r * r / e ** 2) > dof else 0.0
            done = abs(new - tau2) <= 1e-6 * max(new, 1e-300)
            tau2 = new
            w, xt, yt, sxx, s, r = solve(tau2)
            if done:
                break
    elif tau is not None:
        w, xt, yt, sxx, s, r = solve(tau2)
    err_formal = float(1.0 / np.sqrt(sxx))
    # per-spot slopes and intercepts (weights with tau)
    sxx_k = np.bincount(sp, w * xt * xt, minlength=ids.size)
    sxy_k = np.bincount(sp, w * xt * yt, minlength=ids.size)
    n_k = np.bincount(sp, minlength=ids.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        slope_k = np.where((n_k >= 3) & (sxx_k > 0), sxy_k / sxx_k, np.nan)
        err_k = np.where((n_k >= 3) & (sxx_k > 0), 1.0 / np.sqrt(sxx_k), np.nan)
    qbar = np.bincount(sp, w * q, minlength=ids.size) / np.bincount(sp, w, minlength=ids.size)
    gbar = np.bincount(sp, w * g, minlength=ids.size) / np.bincount(sp, w, minlength=ids.size)
    intercept = qbar - s * gbar
    good = np.isfinite(slope_k)
    spread = float(np.sum(((slope_k[good] - s) / err_k[good]) ** 2) / max(good.sum() - 1, 1)) \
        if good.sum() >= 2 else float("nan")
    # image-to-image: the weighted mean residual of each image against its error
    im_ids, im = np.unique(image, return_inverse=True)
    sw_i = np.bincount(im, w)
    rbar = np.bincount(im, w * r) / sw_i
    scale_image = birge_scale(rbar, 1.0 / np.sqrt(sw_i), 2, min_points=3)
    scale_spot = birge_scale(slope_k[good] - s, err_k[good], 1, min_points=3)
    err_image, err_spot = err_formal * scale_image, err_formal * scale_spot
    err = float(max(err_formal, err_image, err_spot))
    return {"slope": s, "slope_err": err, "err_formal": err_formal, "err_image": err_image,
            "err_spot": err_spot, "z": s / err if err > 0 else float("inf"),
            "tau": float(np.sqrt(tau2)), "chi2_dof": chi2_dof0, "n_points": n,
            "n_spots": int(ids.size), "n_images": int(np.unique(image).size),
            "per_spot": {"spot": ids, "slope": slope_k, "slope_err": err_k,
                         "intercept": intercept, "n": n_k},
            "spread_chi2_dof": spread, "image_chi2_scale": scale_image,
            "spot_chi2_scale": scale_spot,
            "points": {"spot": spot, "image": image, "regressor": g,
                       "detrended": q - intercept[sp], "err": e}}


def _rows(catalog, use):
    """The rows fitted: ``use`` (default the catalog's) and finite moments."""
    sel = np.asarray(catalog["use"], bool) if use is None else np.asarray(use, bool)
    if sel.shape != (len(catalog),):
        raise InputError(f"use has shape {sel.shape} for {len(catalog)} rows")
    return sel & np.isfinite(np.asarray(catalog["flux"].value))


def _column(catalog, name):
    col = catalog[name]
    return np.asarray(getattr(col, "value", col), float)


def spot_slopes(catalog, *, quantities=SPOT_QUANTITIES, use=None, min_points=6):
    """Slopes of every spot quantity against flux, with their errors and the exclusions.

    Parameters
    ----------
    catalog : QTable
        From :func:`~lsst_bfdrift.catalogs.spots.measure_spots`.
    quantities : sequence of str, optional
        Of :data:`~lsst_bfdrift.catalogs.spots.SPOT_QUANTITIES`.
    use : array_like of bool, optional
        Rows to fit (default the catalog's ``use``: unflagged rows), e.g.
        one half of the spots for a held-out check.
    min_points : int, optional
        See :func:`fit_spot_slope`.

    Returns
    -------
    dict
        One :func:`fit_spot_slope` result per quantity (slopes per 1e5 e:
        px for sigma_x and sigma_y, fractional for size = ln T, change of
        e1 and e2), and ``n_points``, ``n_spots``, ``n_images`` (rows used),
        ``flux_range`` (e), ``weight_sigma`` (px), ``excluded``
        (:func:`~lsst_bfdrift.catalogs.spots.spot_flag_counts` with the
        counts per image).

    Raises
    ------
    InputError
        An unknown quantity, or too few usable rows (with the counts of
        each exclusion).
    """
    bad = [k for k in quantities if k not in SPOT_QUANTITIES]
    if bad or not quantities:
        raise InputError(f"quantities must be among {SPOT_QUANTITIES}, got {list(quantities)}")
    sel = _rows(catalog, use)
    counts = spot_flag_counts(catalog, per_image=True)
    spot, image = np.asarray(catalog["spot"])[sel], np.asarray(catalog["image"])[sel]
    flux = _column(catalog, "flux")[sel]
    out = {}
    for name in quantities:
        try:
            out[name] = fit_spot_slope(spot, image, flux, _column(catalog, name)[sel],
                                       _column(catalog, f"{name}_err")[sel],
                                       min_points=min_points)
        except InputError as exc:
            why = ", ".join(f"{v} {k}" for k, v in counts.items()
                            if k not in ("used", "rows", "images") and v)
            raise InputError(f"{exc} ({counts['used']} of {counts['rows']} rows usable; "
                             f"left out: {why or 'none'})") from None
    first = out[quantities[0]]
    out.update(n_points=first["n_points"], n_spots=first["n_spots"],
               n_images=first["n_images"],
               flux_range=[float(flux.min()), float(flux.max())] if flux.size else None,
               weight_sigma=catalog.meta.get("weight_sigma"), excluded=counts)
    return out


def slope_values(result, *, quantities=None):
    """(slope, error) per quantity of a :func:`spot_slopes` result, as the star route
    holds them (:meth:`lsst_bfdrift.calibration.star_fit.StarField.slopes`).

    Parameters
    ----------
    result : dict
        From :func:`spot_slopes` or :func:`predict_spot_slopes`.
    quantities : sequence of str, optional
        Default: every quantity in ``result``.

    Returns
    -------
    dict
        Quantity -> (slope, error) per 1e5 e (error 0 for a prediction),
        and ``n_stars``: the rows fitted.
    """
    names = [k for k in SPOT_QUANTITIES if k in result] if quantities is None else quantities
    return {k: (result[k]["slope"], result[k].get("slope_err", 0.0)) for k in names} | \
        {"n_stars": result.get("n_points")}


def _spot_intercepts(catalog, rows):
    """Faint-limit (F = 0) moments (Mxx, Myy, Mxy) and mean centroid phase of spot ``k``."""
    f = _column(catalog, "flux")[rows]
    w = 1.0 / np.maximum(_column(catalog, "size_err")[rows], 1e-12) ** 2
    m0 = []
    for name in ("ixx", "iyy", "ixy"):
        v = _column(catalog, name)[rows]
        if np.ptp(f) > 0 and f.size >= 2:
            m0.append(float(np.polynomial.polynomial.polyfit(f, v, 1, w=np.sqrt(w))[0]))
        else:
            m0.append(float(np.average(v, weights=w)))
    x, y = _column(catalog, "x")[rows], _column(catalog, "y")[rows]
    phase = (float(np.mean(x - np.floor(x + 0.5))), float(np.mean(y - np.floor(y + 0.5))))
    return np.array(m0), phase


def _gaussian_unit(m0, phase, side, weight_sigma, radius, n_iter=6):
    """Pixel-integrated elliptical Gaussian (unit flux) whose fixed-weight moments are ``m0``."""
    import galsim  # galsim: heavy, only for the Gaussian spot model

    c = side // 2
    cov = np.array([[m0[0], m0[2]], [m0[2], m0[1]]]) - np.eye(2) / 12.0
    unit = None
    for _ in range(n_iter):
        try:
            lmat = np.linalg.cholesky(cov)
        except np.linalg.LinAlgError:
            return None
        prof = galsim.Gaussian(sigma=1.0).transform(lmat[0, 0], lmat[0, 1], lmat[1, 0],
                                                    lmat[1, 1])
        unit = prof.drawImage(nx=side, ny=side, scale=1.0, offset=phase).array.astype(float)
        unit /= unit.sum()
        m = fixed_weight_moments(unit, weight_sigma=weight_sigma, radius=radius,
                                 center=(c + phase[0], c + phase[1]))
        if m is None:
            return None
        d = m0 - m["m"]
        cov = cov + np.array([[d[0], d[2]], [d[2], d[1]]])
        if np.max(np.abs(d)) < 1e-9 * (m0[0] + m0[1]):
            break
    return unit


def _stamp_unit(exposures, catalog, rows, side, ix, iy):
    """Flux-normalised sum of a spot's background-subtracted stamps in its fainter half."""
    f = _column(catalog, "flux")[rows]
    imgs = np.asarray(catalog["image"])[rows]
    bkg = _column(catalog, "background")[rows]
    faint = f <= np.median(f)
    half = side // 2
    acc = np.zeros((side, side))
    total = 0.0
    for i, b, fl in zip(imgs[faint], bkg[faint], f[faint]):
        ex = exposures[int(i)]
        sl = (slice(iy - half, iy + half + 1), slice(ix - half, ix + half + 1))
        if sl[0].start < 0 or sl[1].start < 0 or sl[0].stop > ex.data.shape[0] \
                or sl[1].stop > ex.data.shape[1]:
            return None
        acc += np.where(ex.bad[sl], 0.0, ex.data[sl] - b)
        total += fl
    return acc / total if total > 0 else None


def predict_spot_slopes(catalog, template, *, exposures=None, model="gaussian", use=None,
                        quantities=SPOT_QUANTITIES, order=RECOMMENDED.order,
                        density=RECOMMENDED.density, measured=None, progress=False):
    """The spot slopes a template predicts for the measured rows (drift forward model).

    Parameters
    ----------
    catalog : QTable
        From :func:`~lsst_bfdrift.catalogs.spots.measure_spots`.
    template : DistortionTemplate
        The template whose brighter-fatter effect is predicted.
    exposures : sequence of SpotExposure, optional
        The images (needed by ``model='stamp'``).
    model : {'gaussian', 'stamp'}, optional
        Each spot's BF-free profile: 'gaussian', the pixel-integrated
        elliptical Gaussian (at the spot's mean centroid phase) whose
        fixed-weight moments equal the spot's faint-limit moments (linear
        fits of Mxx, Myy, Mxy against flux, at zero flux); 'stamp', the
        flux-normalised sum of the spot's stamps in the fainter half of its
        images (any profile; carries their noise and their small BF).
    use : array_like of bool, optional
        Rows (default the catalog's ``use``).
    quantities : sequence of str, optional
        As :func:`spot_slopes`.
    order, density
        Of :func:`~lsst_bfdrift.correction.solvers.recorded_image` (the
        correction's defaults).
    measured : dict, optional
        The measured :func:`spot_slopes` result: its ``tau`` per quantity
        weights the prediction like the measurement (default: computed).
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    dict
        Per quantity: ``slope`` (per 1e5 e), ``chi2_dof`` (non-linearity of
        the predicted values), ``per_spot``; and ``model``, ``n_points``,
        ``n_spots``, ``spots_skipped`` (spots whose model could not be made).

    Raises
    ------
    InputError
        An unknown model, or 'stamp' without the exposures.
    """
    if model not in SPOT_MODELS:
        raise InputError(f"model must be one of {SPOT_MODELS}, got {model!r}")
    if model == "stamp" and exposures is None:
        raise InputError("model='stamp' needs the exposures (the spots' faint stamps)")
    sel = _rows(catalog, use)
    if measured is None:
        measured = spot_slopes(catalog, quantities=quantities, use=sel)
    meta = catalog.meta
    ws, radius = float(meta["weight_sigma"]), float(meta["radius"])
    side = 2 * (int(np.ceil(radius)) + 2 + template.center) + 1
    c = side // 2
    swept = SweptAreas(template, (side, side))
    spots = np.asarray(catalog["spot"])
    flux = _column(catalog, "flux")
    pred = {q: np.full(len(catalog), np.nan) for q in quantities}
    skipped = []
    ids = np.unique(spots[sel])
    with ProgressBar(int(sel.sum()), "predict", enabled=progress) as bar:
        for k in ids:
            rows = sel & (spots == k)
            m0, phase = _spot_intercepts(catalog, rows)
            if model == "gaussian":
                unit = _gaussian_unit(m0, phase, side, ws, radius)
                centre = (c + phase[0], c + phase[1])
            else:
                x, y = _column(catalog, "x_ref")[rows][0], _column(catalog, "y_ref")[rows][0]
                ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
                unit = _stamp_unit(exposures, catalog, rows, side, ix, iy)
                centre = (c + x - ix, c + y - iy)
            if unit is None:
                skipped.append(int(k))
                bar(int(rows.sum()))
                continue
            for r in np.flatnonzero(rows):
                rec = recorded_image(flux[r] * unit, swept, order=order, density=density)
                m = fixed_weight_moments(rec, weight_sigma=ws, radius=radius, center=centre)
                for q in quantities:
                    pred[q][r] = np.nan if m is None else m[q]
                bar(1)
    out = {}
    ok = sel & ~np.isin(spots, skipped)
    for q in quantities:
        fit = fit_spot_slope(spots[ok], np.asarray(catalog["image"])[ok], flux[ok], pred[q][ok],
                             _column(catalog, f"{q}_err")[ok], tau=measured[q]["tau"])
        out[q] = {"slope": fit["slope"], "chi2_dof": fit["chi2_dof"], "per_spot": fit["per_spot"],
                  "points": fit["points"]}
    out.update(model=model, n_points=int(ok.sum()), n_spots=int(ids.size - len(skipped)),
               spots_skipped=skipped, values=pred)
    return out


def compare_slopes(measured, predicted, *, quantities=None):
    """Measured against predicted slopes, quantity by quantity.

    Parameters
    ----------
    measured : dict
        From :func:`spot_slopes`.
    predicted : dict
        From :func:`predict_spot_slopes` (or another :func:`spot_slopes`
        result, e.g. of BF-free twins, whose errors are then combined).
    quantities : sequence of str, optional
        Default: those in both.

    Returns
    -------
    dict
        Quantity -> ``measured``, ``measured_err``, ``predicted``,
        ``predicted_err`` (0 for a prediction), ``ratio`` (measured /
        predicted), ``difference``, ``z`` (difference over the combined error).
    """
    names = [k for k in SPOT_QUANTITIES if k in measured and k in predicted] \
        if quantities is None else quantities
    out = {}
    for k in names:
        m, me = measured[k]["slope"], measured[k]["slope_err"]
        p, pe = predicted[k]["slope"], predicted[k].get("slope_err", 0.0)
        err = float(np.hypot(me, pe))
        out[k] = {"measured": m, "measured_err": me, "predicted": p, "predicted_err": pe,
                  "ratio": m / p if p != 0 else float("nan"),
                  "ratio_err": float(np.hypot(me, m / p * pe) / abs(p))
                  if p != 0 else float("nan"), "difference": m - p,
                  "z": (m - p) / err if err > 0 else float("nan")}
    return out
