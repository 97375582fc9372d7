"""What a flat set carries beside its covariances, measured per pair.

The covariance fit uses the difference-image covariances C_ij(mu). Each
flat pair also carries the means of its two flats, the pair sums' statistics,
the covariances of image halves (standing in for amplifiers) and, with its
header, the exposure time. This module measures them
(:func:`pair_observables`), finds the PTC turn-off (:func:`turnoff_cut`) and
gives their statistical errors: shot noise of the pixels through the sum rule
(var of a pixel total = mu / gain + read noise, :func:`pair_mean_errors`),
the scatter of the exposures beyond it (:func:`exposure_scatter`) and the
per-lag error factors of the covariances (:func:`lag_error_factors`).
:mod:`~lsst_bfdrift.diagnosis.findings` turns them into findings the base
model cannot absorb.
"""

import numpy as np

from lsst_bfdrift.ptc.covariances import edge_mask, pair_covariances, ptc_turnoff
from lsst_bfdrift.utils.errors import InputError

__all__ = ["SPLITS", "lag_error_factors", "pair_observables",
           "turnoff_cut", "weighted_mean", "pixel_variance", "pair_ratios",
           "exposure_scatter", "pair_mean_errors", "exposure_line"]

#: Image halves compared: split name -> (first half, second half).
SPLITS = {"left_right": ("left", "right"), "bottom_top": ("bottom", "top")}


def lag_error_factors(max_lag):
    """Error of a sample covariance of N pixels in units of V / sqrt(N) (V the
    variance): sqrt(2) at lag 0, 1 on the axes, sqrt(1/2) off them, the errors
    the diagnosis uses."""
    f = np.full((max_lag + 1, max_lag + 1), np.sqrt(0.5))
    f[0, :] = 1.0
    f[:, 0] = 1.0
    f[0, 0] = np.sqrt(2.0)
    return f


def _half_regions(shape):
    """Split name -> the two halves as slices of the image."""
    ny, nx = shape
    return {"left_right": (np.s_[:, :nx // 2], np.s_[:, nx // 2:]),
            "bottom_top": (np.s_[:ny // 2], np.s_[ny // 2:])}


def pair_observables(flat1, flat2, *, max_lag=3, border=None, whole=None):
    """Means of the two flats of a pair and the statistics of each image half.

    Parameters
    ----------
    flat1, flat2 : array_like, 2-d
        The pair (ADU), indexed [y, x] (y parallel).
    max_lag : int, optional
        Largest lag of the per-half covariances.
    border : int, optional
        Pixels left out at the image edges
        (:func:`~lsst_bfdrift.ptc.covariances.edge_border`).
    whole : PairCovariance, optional
        The whole pair's :func:`~lsst_bfdrift.ptc.covariances.pair_covariances`
        (computed when not given).

    Returns
    -------
    dict
        ``mu1``, ``mu2`` (ADU) and ``nvalid`` (pixels) of the whole pair;
        ``halves``: split name (:data:`SPLITS`) -> ``{"mu": (2,) ADU, "nvalid":
        (2,), "cov": (2, L+1, L+1) ADU^2, "npix": (2, L+1, L+1)}``, or a string
        saying why the halves could not be measured.
    """
    a = np.asarray(flat1, dtype=float)
    b = np.asarray(flat2, dtype=float)
    if whole is None:
        whole = pair_covariances(a, b, max_lag=max_lag, min_pixels=min(1000, a.size // 4),
                                 border=border)
    out = {"mu1": whole.mu1, "mu2": whole.mu2, "nvalid": whole.nvalid, "halves": {}}
    # each half on its own cut-out (half the transform of the whole image
    # masked), with the whole image's border band as a mask: the same pixels
    # and pixel pairs as the whole image with the other half masked
    edge = edge_mask(a.shape, border)
    for split, regions in _half_regions(a.shape).items():
        try:
            hs = [pair_covariances(a[r], b[r], max_lag=max_lag, mask=edge[r], border=0,
                                   min_pixels=min(1000, a.size // 16)) for r in regions]
        except InputError as exc:
            out["halves"][split] = f"halves too small or too masked ({exc})"
            continue
        out["halves"][split] = {"mu": np.array([h.mu for h in hs]),
                                "nvalid": np.array([h.nvalid for h in hs], float),
                                "cov": np.array([h.cov for h in hs]),
                                "npix": np.array([h.npix for h in hs], float)}
    return out


def turnoff_cut(mu, c00, npix00=None, *, nsigma=5.0, min_drop=0.05):
    """Pairs below the PTC turn-off, with the drop that defines it.

    The turn-off is :func:`~lsst_bfdrift.ptc.covariances.ptc_turnoff` with a
    drop of at least ``min_drop`` and at least ``nsigma`` standard deviations
    of the difference of two variance estimates (sqrt(2) sqrt(2 / N) relative,
    N the pixels of lag 0), so that noise of small images does not make one.

    Parameters
    ----------
    mu, c00 : array_like, shape (n,)
        Pair means (ADU) and variances (ADU^2).
    npix00 : array_like, shape (n,), optional
        Pixels behind each variance; without them the drop is ``min_drop``.
    nsigma, min_drop : float, optional

    Returns
    -------
    keep : ndarray of bool, shape (n,)
        Pairs at or below the turn-off.
    info : dict
        ``break_level`` (ADU, None without a turn-off), ``drop`` (relative
        threshold used), ``excluded`` (list of ``{"mu", "c00", "drop"}``, the
        relative fall below the running maximum), ``rel_error`` (relative error
        of one variance, None without ``npix00``).
    """
    mu = np.asarray(mu, float)
    c00 = np.asarray(c00, float)
    rel = None
    drop = float(min_drop)
    if npix00 is not None:
        rel = float(np.max(np.sqrt(2.0 / np.asarray(npix00, float))))
        drop = max(drop, nsigma * np.sqrt(2.0) * rel)
    brk = ptc_turnoff(mu, c00, drop=drop)
    keep = mu <= brk
    order = np.argsort(mu)
    running = np.maximum.accumulate(c00[order])
    fall = np.empty_like(c00)
    fall[order] = 1.0 - c00[order] / running
    excluded = [{"mu": float(mu[k]), "c00": float(c00[k]), "drop": float(fall[k])}
                for k in order if not keep[k]]
    return keep, {"break_level": None if not np.isfinite(brk) else float(brk),
                  "drop": float(drop), "excluded": excluded, "rel_error": rel,
                  "mu_max": float(mu.max())}


def weighted_mean(x, s):
    """Inverse-variance weighted mean and its error.

    Parameters
    ----------
    x, s : array_like, shape (n,)
        Values and their errors (> 0).

    Returns
    -------
    mean, error : float
        sum(w x) / sum(w) and 1 / sqrt(sum(w)), w = 1 / s^2.
    """
    w = 1.0 / np.asarray(s, float) ** 2
    return float(np.sum(w * x) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w)))


def pixel_variance(mu, gain, noise):
    """Variance of a pixel total per pixel (ADU^2) from the sum rule: mu / g + n / g^2.

    Parameters
    ----------
    mu : array_like
        Signal (ADU).
    gain, noise : float
        e/ADU and read noise (e^2; negative counts as 0).

    Returns
    -------
    ndarray
    """
    return np.asarray(mu, float) / gain + max(float(noise), 0.0) / gain**2


def pair_ratios(mu, mu1, mu2, nvalid, gain, noise):
    """The second flat of each pair over the first, r = mu2 / mu1 - 1, with its error.

    Parameters
    ----------
    mu, mu1, mu2 : array_like, shape (n,)
        Pair means and the means of each flat (ADU).
    nvalid : array_like, shape (n,)
        Pixels behind the means.
    gain, noise : float
        e/ADU and read noise (e^2).

    Returns
    -------
    mu, r, sigma : ndarray, shape (n,)
        The pair means, r, and its shot-noise error sqrt(2 V / N) / mu (V
        the variance of a pixel total, :func:`pixel_variance`; N ``nvalid``).
    """
    mu, mu1, mu2, n = (np.asarray(v, float) for v in (mu, mu1, mu2, nvalid))
    return mu, mu2 / mu1 - 1.0, np.sqrt(2.0 * pixel_variance(mu, gain, noise) / n) / mu


def exposure_scatter(mu, mu1, mu2, nvalid, gain, noise):
    """Relative scatter of one flat's exposure (lamp, shutter) beyond shot noise.

    From the two flats of each pair: r = mu2 / mu1 - 1 scatters by
    sqrt(2) x the per-flat exposure scatter on top of its shot noise, so
    sigma_f^2 = max(0, (var(r) - mean(s_r^2)) / 2), with var(r) about the
    weighted mean of r (a steady offset between the two flats is the pair
    ratio's finding, not scatter).

    Parameters
    ----------
    mu, mu1, mu2, nvalid, gain, noise
        As :func:`pair_ratios`.

    Returns
    -------
    float
        sigma_f, relative (0 when the pairs agree within shot noise or there
        are fewer than 3 pairs).
    """
    mu, r, s = pair_ratios(mu, mu1, mu2, nvalid, gain, noise)
    if mu.size < 3:
        return 0.0
    mean, _ = weighted_mean(r, s)
    excess = (np.sum((r - mean) ** 2) / (mu.size - 1) - np.mean(s**2)) / 2.0
    return float(np.sqrt(max(excess, 0.0)))


def pair_mean_errors(mu, pairs, gain, noise):
    """Shot-noise errors of the pair means (ADU) and the exposure scatter.

    Parameters
    ----------
    mu : array_like, shape (n,)
        Pair means (ADU).
    pairs : sequence of dict
        Per pair ``mu1``, ``mu2`` and ``nvalid``
        (:func:`pair_observables`).
    gain, noise : float
        e/ADU and read noise (e^2).

    Returns
    -------
    sigma : ndarray
        sqrt(V / (2 N)) per pair, V the pixel variance of the sum rule.
    scatter : float
        :func:`exposure_scatter` of the pairs.
    """
    mu = np.asarray(mu, float)
    n = np.array([e["nvalid"] for e in pairs], float)
    sig = np.sqrt(pixel_variance(mu, gain, noise) / (2.0 * n))
    return sig, exposure_scatter(mu, [e["mu1"] for e in pairs], [e["mu2"] for e in pairs],
                                 n, gain, noise)


def exposure_line(mu, exptime, sigma):
    """Weighted least-squares line mu = k t + c of the pair means.

    Parameters
    ----------
    mu, exptime, sigma : array_like, shape (n,)
        Pair means (ADU), exposure times (s) and the means' errors (ADU).

    Returns
    -------
    coef : ndarray, shape (2,)
        ``(k, c)``: slope (ADU/s) and offset (ADU).
    cov : ndarray, shape (2, 2)
        Their covariance.
    """
    mu, t, s = (np.asarray(v, float) for v in (mu, exptime, sigma))
    A = np.stack([t, np.ones_like(t)], axis=1) / s[:, None]
    coef = np.linalg.lstsq(A, mu / s, rcond=None)[0]
    return coef, np.linalg.inv(A.T @ A)
