"""The full covariance model of Astier et al. 2019 (eq. 20), its exact Jacobian and its fit.

Written from P. Astier et al. 2019, A&A 629, A36, eq. 20 (no code taken from
any implementation). Conventions as in :mod:`lsst_bfdrift.ptc.covariances`:
quadrant arrays ``q[di, dj]`` (di, dj >= 0) stand for their mirror images at
negative lags, signals in ADU, gain in e/ADU, a_ij and b_ij per electron,
n_ij in e^2:

C = (mu / g) [I + a (mu g) + 2/3 (a*a + ab)(mu g)^2
+ 1/6 (2 a*a*a + 5 a*ab)(mu g)^3] + n / g^2,

with ``*`` the 2-d discrete convolution over signed lags and ``ab`` the
element-wise product.

Every convolution of the model, ``convolve_lags(x, y)``, is linear in ``x``
for a fixed ``y``: a matrix ``M(y)`` of shape ((L+1)^2, (L+1)^2) with
``convolve_lags(x, y).ravel() = M(y) @ x.ravel()`` (:func:`lag_operator`).
The model then costs three matrix-vector products, and its Jacobian with
respect to gain, a_ij, b_ij and n_ij is a few matrix products
(:func:`covariance_model_jacobian`), where a finite-difference Jacobian
evaluates the model once per parameter (3 (L+1)^2 + 1 times: 244 at lag 8).
:func:`fit_covariance_model` uses it.
"""

import numpy as np
from scipy import stats as sp_stats
from scipy.signal import convolve2d

from lsst_bfdrift.ptc.covariances import (MIN_COVARIANCE_LEVELS, _fit, _fit_result,
                                          fit_ptc_exponential, least_squares_line)
from lsst_bfdrift.simulation.effects import full_lags
from lsst_bfdrift.utils.errors import InputError

__all__ = ["convolve_lags", "lag_operator", "covariance_model",
           "covariance_model_jacobian", "fit_covariance_model"]


def convolve_lags(x, y):
    """Convolution of two quadrant arrays on signed lags, on the quadrant of x's size.

    Each array q[di, dj] (di, dj >= 0) stands for its mirror images at
    negative lags (q[-i, j] = q[i, -j] = q[i, j]); the result is the 2-d
    convolution of the two signed-lag arrays, at lags 0 to L of ``x``: the
    a * a terms of :func:`covariance_model`. This is the direct sum (scipy's
    ``convolve2d``), the reference of :func:`lag_operator`.

    Parameters
    ----------
    x, y : ndarray, shape (L + 1, L + 1)
        Quadrant arrays indexed [di, dj].

    Returns
    -------
    ndarray, shape (L + 1, L + 1)
    """
    L = x.shape[0] - 1
    full = convolve2d(full_lags(x), full_lags(y), mode="same")
    return full[L:, L:]


def _signed_offsets(L):
    """Index arrays of :func:`lag_operator`: for each quadrant lag k (or l), its
    distinct signed images s k (s = +1, -1; one image at k = 0) and their weights."""
    k = np.arange(L + 1)
    off = np.stack([k, -k])  # [sign, k]
    w = np.ones((2, L + 1))
    w[1, 0] = 0.0  # -0 is +0: counted once
    return off, w


def lag_operator(y):
    """The matrix of ``x -> convolve_lags(x, y)``.

    ``convolve_lags(x, y)[i, j] = sum_{k, l} M[i, j, k, l] x[k, l]``, where
    ``M[i, j, k, l]`` sums the signed-lag array of ``y`` at (i - s k, j - t l)
    over the distinct signed images (s k, t l) of the lag (k, l). Exact (the
    same sums as :func:`convolve_lags`, in another order).

    Parameters
    ----------
    y : ndarray, shape (L + 1, L + 1)
        Quadrant array indexed [di, dj].

    Returns
    -------
    ndarray, shape ((L + 1)^2, (L + 1)^2)
        ``M`` with (i, j) and (k, l) raveled in C order.
    """
    y = np.asarray(y, dtype=float)
    L = y.shape[0] - 1
    pad = np.zeros((4 * L + 1, 4 * L + 1))
    pad[L:3 * L + 1, L:3 * L + 1] = full_lags(y)  # pad[p + 2L, q + 2L] = y at signed (p, q)
    off, w = _signed_offsets(L)
    i = np.arange(L + 1)
    # rows: i - s k + 2L for sign s and (i, k); shape [s, i, k]
    rows = i[None, :, None] - off[:, None, :] + 2 * L
    m = np.zeros((L + 1, L + 1, L + 1, L + 1))
    for s in range(2):
        for t in range(2):
            # pad[rows[s, i, k], rows[t, j, l]] -> [i, k, j, l]
            blk = pad[rows[s][:, :, None, None], rows[t][None, None, :, :]]
            m += (w[s][None, :, None, None] * w[t][None, None, None, :]) * blk
    n1 = (L + 1) ** 2
    return m.transpose(0, 2, 1, 3).reshape(n1, n1)


def _terms(a, b):
    """Flattened a, ab, aa, aaa, a_ab and the operators M(a), M(aa), M(ab)."""
    n1 = a.size
    pa = lag_operator(a)
    af, bf = a.reshape(n1), np.broadcast_to(b, a.shape).reshape(n1)
    ab = af * bf
    aa = pa @ af
    aaa = pa @ aa  # convolve_lags(aa, a) = convolve_lags(a, aa)
    a_ab = pa @ ab
    return af, bf, ab, aa, aaa, a_ab, pa


def covariance_model(mu, gain, a, b, noise):
    """Full covariance model of Astier et al. 2019 (eq. 20), third order.

    C = (mu / g) [I + a (mu g) + 2/3 (a*a + ab)(mu g)^2
    + 1/6 (2 a*a*a + 5 a*ab)(mu g)^3] + n / g^2, with ``*`` the
    convolution over signed lags (:func:`convolve_lags`, here as the
    matrix of :func:`lag_operator`) and ``ab`` the element-wise product.

    Parameters
    ----------
    mu : array_like, shape (n,)
        Signals (ADU).
    gain : float
        e/ADU.
    a, b, noise : ndarray, shape (L + 1, L + 1)
        a_ij, b_ij (1/e) and n_ij (e^2) indexed [di, dj].

    Returns
    -------
    ndarray, shape (n, L + 1, L + 1)
        C_ij (ADU^2).
    """
    mu = np.atleast_1d(np.asarray(mu, dtype=float))
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    shape = a.shape
    af, _, ab, aa, aaa, a_ab, _ = _terms(a, b)
    x = (mu * gain)[:, None]
    eye = np.zeros(af.size)
    eye[0] = 1.0
    bracket = (eye + af * x + (2.0 / 3.0) * (aa + ab) * x**2
               + (2.0 * aaa + 5.0 * a_ab) * x**3 / 6.0)
    out = mu[:, None] / gain * bracket
    return out.reshape((mu.size,) + shape) + np.asarray(noise, float) / gain**2


def covariance_model_jacobian(mu, gain, a, b, noise):
    """Exact derivatives of :func:`covariance_model` with respect to its parameters.

    Parameters
    ----------
    mu, gain, a, b, noise
        As :func:`covariance_model`.

    Returns
    -------
    ndarray, shape (n, (L + 1)^2, 1 + 3 (L + 1)^2)
        ``J[k, ij, p]`` = d C_ij(mu_k) / d p for the parameters
        p = (gain, a.ravel(), b.ravel(), noise.ravel()) (ADU^2 per e/ADU, per
        1/e, per 1/e and per e^2).
    """
    mu = np.atleast_1d(np.asarray(mu, dtype=float))
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    nf = np.asarray(noise, float).ravel()
    af, bf, ab, aa, aaa, a_ab, pa = _terms(a, b)
    n1 = af.size
    g = float(gain)
    paa = lag_operator(aa.reshape(a.shape))
    pab = lag_operator(ab.reshape(a.shape))
    eye = np.eye(n1)
    # derivatives of the bracket's coefficients with respect to a and b
    d_aa_ab_a = 2.0 * pa + np.diag(bf)           # d(aa + ab)/da
    d_cubic_a = 2.0 * (2.0 * pa @ pa + paa) + 5.0 * (pab + pa * bf[None, :])
    d_aa_ab_b = np.diag(af)                      # d(aa + ab)/db
    d_cubic_b = 5.0 * pa * af[None, :]           # d(2 aaa + 5 a_ab)/db
    x = mu * g
    pre = (mu / g)[:, None, None]
    xs = x[:, None, None]
    jac = np.empty((mu.size, n1, 1 + 3 * n1))
    jac[:, :, 1:1 + n1] = pre * (xs * eye + (2.0 / 3.0) * xs**2 * d_aa_ab_a
                                 + xs**3 / 6.0 * d_cubic_a)
    jac[:, :, 1 + n1:1 + 2 * n1] = pre * ((2.0 / 3.0) * xs**2 * d_aa_ab_b
                                          + xs**3 / 6.0 * d_cubic_b)
    jac[:, :, 1 + 2 * n1:] = eye / g**2
    e0 = np.zeros(n1)
    e0[0] = 1.0
    xv = x[:, None]
    bracket = (e0 + af * xv + (2.0 / 3.0) * (aa + ab) * xv**2
               + (2.0 * aaa + 5.0 * a_ab) * xv**3 / 6.0)
    slope = af + (4.0 / 3.0) * (aa + ab) * xv + 0.5 * (2.0 * aaa + 5.0 * a_ab) * xv**2
    mv = mu[:, None]
    jac[:, :, 0] = -mv / g**2 * bracket + mv**2 / g * slope - 2.0 * nf / g**3
    return jac


def fit_covariance_model(mu, cov, *, sigma=None, npix=None, max_lag=None, mu_max=None,
                         fit_b="auto", gain=None, fit_noise=True, progress=None, jac="exact"):
    """Fit gain, a_ij, b_ij and n_ij of the full model to measured covariances.

    Parameters
    ----------
    mu : array_like, shape (n,)
        Signals (ADU).
    cov : array_like, shape (n, L + 1, L + 1)
        Measured C_ij (ADU^2), indexed [k, di, dj].
    sigma : array_like, same shape as ``cov``, optional
        Errors of the covariances (ADU^2).
    npix : array_like, same shape as ``cov``, optional
        Pixel pairs behind each covariance (from :func:`measure_ptc`); used
        when ``sigma`` is not given: sigma = C00 sqrt(2 / N) at lag 0,
        C00 sqrt(1 / N) on the axes and C00 sqrt(1 / (2 N)) off them (errors of
        sample covariances; off-axis values average two independent products). With
        neither, all points of a signal level get the weight 1 / C00 and the
        parameter errors are scaled to the scatter (sqrt(chi2/dof)).
    max_lag : int, optional
        Fit lags up to this value only.
    mu_max : float, optional
        Exclude signals above (ADU).
    fit_b : bool or 'auto', optional
        Fit b_ij (True), fix them to 0 (False), or let the data decide
        ('auto', the default): b_ij are kept only when they lower chi2 by more
        than the 99th percentile of chi2 with as many degrees of freedom as
        b_ij (a likelihood-ratio test). With a few signal levels b_ij are
        degenerate with a_ij: freed without need they multiply the errors of
        a_ij by 3-4 and bias them (GalSim flats, 12 levels: a01 4.2e-7 +- 7e-8
        against the true 1.95e-7; 2.3e-7 +- 1.9e-8 with b = 0).
    gain : float, optional
        Known gain (e/ADU), held fixed (its error is then 0); default: fitted.
    fit_noise : bool, optional
        Fit n_ij (else fixed to 0, e.g. for noiseless simulations).
    progress : callable, optional
        Called with no argument after each evaluation of the model and of its
        Jacobian (e.g. an :class:`~lsst_bfdrift.utils.progress.Activity`):
        the number of iterations is not known in advance. With b_ij free the
        fit takes most iterations (7 levels of 9 x 9 lags: about 250, each a
        singular value decomposition of the 567 x 244 Jacobian).
    jac : {'exact', '2-point'}, optional
        The Jacobian given to ``least_squares``: 'exact'
        (:func:`covariance_model_jacobian`, the default) or the former
        forward differences, one model evaluation per free parameter (244 at
        lag 8; 7 levels of 9 x 9 lags: 87000 evaluations, 6 times the exact
        fit's time). Both stop where the cost changes by less than 1e-8
        relative: on the same input their a_ij differ by less than 1e-3 of
        their errors (the exact one ends closer to the minimum).

    Returns
    -------
    dict
        ``gain``, ``a``, ``b``, ``noise`` (arrays [di, dj]) with ``*_err``,
        ``chi2``, ``dof``, ``residuals`` (measured - model, ADU^2), and
        ``b_fitted`` (bool) with ``b_test`` (the 'auto' test: ``delta_chi2``,
        ``dof``, ``p_value``; None otherwise).
    """
    if fit_b == "auto":
        kw = dict(sigma=sigma, npix=npix, max_lag=max_lag, mu_max=mu_max, gain=gain,
                  fit_noise=fit_noise, progress=progress, jac=jac)
        without = fit_covariance_model(mu, cov, fit_b=False, **kw)
        with_b = fit_covariance_model(mu, cov, fit_b=True, **kw)
        n_b = int(without["dof"] - with_b["dof"])
        delta = float(without["chi2"] - with_b["chi2"])
        p = float(sp_stats.chi2.sf(delta, max(n_b, 1)))
        best = with_b if p < 0.01 else without
        best["b_test"] = {"delta_chi2": delta, "dof": n_b, "p_value": p}
        return best
    if fit_b not in (True, False):
        raise InputError(f"fit_b must be True, False or 'auto', got {fit_b!r}")
    if jac not in ("exact", "2-point"):
        raise InputError(f"jac must be 'exact' or '2-point', got {jac!r}")
    mu = np.asarray(mu, dtype=float)
    cov = np.asarray(cov, dtype=float)
    if cov.ndim != 3 or cov.shape[0] != mu.size or cov.shape[1] != cov.shape[2]:
        raise InputError(f"cov must have shape (n, L+1, L+1) with n = len(mu), got {cov.shape}")
    L = cov.shape[1] - 1 if max_lag is None else int(max_lag)
    cov = cov[:, :L + 1, :L + 1]
    good = np.isfinite(mu) & np.all(np.isfinite(cov), axis=(1, 2))
    if mu_max is not None:
        good &= mu <= mu_max
    m, c = mu[good], cov[good]
    if m.size < MIN_COVARIANCE_LEVELS:
        raise InputError(f"need at least {MIN_COVARIANCE_LEVELS} signal levels, got {m.size}")
    known = sigma is not None or npix is not None
    if sigma is not None:
        s = np.asarray(sigma, float)[good][:, :L + 1, :L + 1]
    elif npix is not None:
        # errors of sample covariances of N pixel pairs (as the diagnosis): lag 0
        # sqrt(2) V / sqrt(N), on the axes V / sqrt(N), off the axes V / sqrt(2 N)
        # ((i, j) and (i, -j) are averaged: independent products)
        n = np.asarray(npix, float)[good][:, :L + 1, :L + 1]
        s = c[:, 0, 0][:, None, None] * np.sqrt(0.5 / n)
        s[:, 0, :] *= np.sqrt(2.0)
        s[:, :, 0] *= np.sqrt(2.0)
        s[:, 0, 0] *= np.sqrt(2.0)
    else:
        s = np.broadcast_to(c[:, 0, 0][:, None, None], c.shape).copy()
    if np.any(~(s > 0)):
        raise InputError("covariance errors must be positive")
    exp = fit_ptc_exponential(m, c[:, 0, 0], mu_max=None)
    g0 = exp["gain"] if gain is None else float(gain)
    if gain is not None and not (np.isfinite(g0) and g0 > 0):
        raise InputError(f"gain must be positive, got {gain!r}")
    n1 = (L + 1) ** 2
    # start: a_ij from the slope of C_ij / (mu/g) against mu g
    a0 = np.zeros((L + 1, L + 1))
    x = m * g0
    for i in range(L + 1):
        for j in range(L + 1):
            y = c[:, i, j] * g0 / m
            if i == j == 0:
                a0[0, 0] = exp["a00"]
            else:
                a0[i, j] = least_squares_line(x, y)[0] if m.size > 2 else 0.0
    n0 = np.zeros((L + 1, L + 1))
    n0[0, 0] = exp["noise"] if fit_noise else 0.0

    # full vector [gain, a, b, n]; only the free entries are fitted
    free = np.concatenate([[gain is None], np.ones(n1, bool), np.full(n1, bool(fit_b)),
                           np.full(n1, bool(fit_noise))])
    full0 = np.concatenate([[g0], a0.ravel(), np.zeros(n1), n0.ravel()])

    def unpack(q):
        p = full0.copy()
        p[free] = q
        return (p[0], p[1:1 + n1].reshape(L + 1, L + 1),
                p[1 + n1:1 + 2 * n1].reshape(L + 1, L + 1), p[-n1:].reshape(L + 1, L + 1))

    def resid(q):
        g, a, b, nz = unpack(q)
        if progress is not None:
            progress()
        return ((covariance_model(m, g, a, b, nz) - c) / s).ravel()

    s_col = s.reshape(m.size, n1, 1)

    def jacobian(q):
        g, a, b, nz = unpack(q)
        if progress is not None:
            progress()
        jf = covariance_model_jacobian(m, g, a, b, nz)[:, :, free] / s_col
        return jf.reshape(m.size * n1, -1)

    scale = np.concatenate([[0.1], np.full(n1, 1e-7), np.full(n1, 1e-8), np.full(n1, 10.0)])
    res = _fit(resid, full0[free], jac=jacobian if jac == "exact" else "2-point",
               x_scale=scale[free], method="trf")
    names = np.array(["gain"] + [f"a{i}" for i in range(n1)] + [f"b{i}" for i in range(n1)]
                     + [f"n{i}" for i in range(n1)])[free].tolist()
    stats = _fit_result(res, names, c.size, known_sigma=known)
    errs = np.zeros(full0.size)
    errs[free] = np.sqrt(np.diag(np.array(stats["covariance"])))
    g, a, b, nz = unpack(res.x)
    ge, ae, be, ne = (errs[0], errs[1:1 + n1].reshape(L + 1, L + 1),
                      errs[1 + n1:1 + 2 * n1].reshape(L + 1, L + 1),
                      errs[-n1:].reshape(L + 1, L + 1))
    return {"gain": float(g), "gain_err": float(ge), "a": a, "a_err": ae, "b": b,
            "b_err": be, "noise": nz, "noise_err": ne, "chi2": stats["chi2"],
            "dof": stats["dof"], "mu": m, "b_fitted": bool(fit_b), "b_test": None,
            "residuals": c - covariance_model(m, g, a, b, nz)}

