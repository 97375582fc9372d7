"""Photon transfer curve: covariances of flat pairs and the Astier et al. 2019 model.

Written from P. Astier et al. 2019, A&A 629, A36, "The shape of the photon
transfer curve of CCD sensors" (no code taken from any implementation).

Conventions
-----------
* Images are indexed ``[y, x]``; a covariance lag is (di, dj) = (serial,
  parallel) and covariance arrays are indexed ``C[di, dj]`` for
  ``0 <= di, dj <= max_lag``. Lags (di, dj) and (di, -dj) are averaged (the
  model is symmetric).
* Signals ``mu`` are in ADU, covariances in ADU^2, gain g in e/ADU, area
  coefficients a_ij and b_ij per electron, noise n_ij in e^2.
* Exponential model (paper eq. 16):
  C00 = (exp(2 a00 mu g) - 1) / (2 a00 g^2) + n00 / g^2.
* The full model to third order in mu g (paper eq. 20), its Jacobian and
  its fit are in :mod:`lsst_bfdrift.ptc.full_model`.
"""

import os

import numpy as np
from astropy.table import Table
from scipy import fft as sp_fft
from scipy.optimize import least_squares
from lsst_bfdrift.images.exposure import read_image
from lsst_bfdrift.utils.errors import FitError, InputError, InputFileError
from lsst_bfdrift.utils.io import open_fits, read_text_rows

__all__ = ["PairCovariance", "pair_covariances", "measure_ptc", "ptc_exponential_model",
           "fit_ptc_exponential", "ptc_turnoff", "read_ptc_text", "read_flat_pair",
           "count_levels", "MIN_LEVELS", "MIN_PTC_POINTS", "MIN_COVARIANCE_LEVELS", "SIGNAL_RANGE",
           "EDGE_BORDER", "edge_border", "edge_mask", "least_squares_line",
           "identical_flats"]

#: Fewest distinct signal levels of any PTC fit.
MIN_LEVELS = 3

#: Fewest valid points of the exponential PTC fit (:func:`fit_ptc_exponential`).
MIN_PTC_POINTS = 4

#: Fewest signal levels of the full covariance model fit
#: (:func:`~lsst_bfdrift.ptc.full_model.fit_covariance_model`).
MIN_COVARIANCE_LEVELS = 5

#: Signals (ADU or e) a PTC point may have: beyond, the fit's arithmetic fails
#: (LAPACK's SVD at ~1e-300, overflow at ~1e150) long before any real sensor.
SIGNAL_RANGE = (1e-6, 1e8)


def count_levels(mu, rtol=1e-3):
    """Number of distinct signal levels in ``mu`` (closer than ``rtol`` relative: one).

    Parameters
    ----------
    mu : array_like
        Signals (finite).
    rtol : float, optional

    Returns
    -------
    int
    """
    m = np.sort(np.asarray(mu, dtype=float))
    if m.size == 0:
        return 0
    return 1 + int(np.sum(np.diff(m) > rtol * np.abs(m[1:])))


def _check_points(m, v):
    """Refuse PTC points no fit can use: out of range, fewer than MIN_LEVELS levels."""
    lo, hi = SIGNAL_RANGE
    if m.min() < lo or m.max() > hi or v.max() > hi**2 or v.min() < lo**2:
        raise InputError(f"PTC signals {m.min():.3g}..{m.max():.3g} or variances "
                         f"{v.min():.3g}..{v.max():.3g} outside the accepted range (signals "
                         f"{lo:g}..{hi:g} ADU or e, variances {lo**2:g}..{hi**2:g})")
    n = count_levels(m)
    if n < MIN_LEVELS:
        raise InputError(f"PTC points span {n} distinct signal level(s) (identical points or all "
                         f"pairs at one level); accepted: at least {MIN_LEVELS} levels, "
                         "differing by more than 0.1 %")


def _fit(resid, start, **kwargs):
    """least_squares with the package's error when the arithmetic fails."""
    try:
        with np.errstate(all="ignore"):
            return least_squares(resid, start, **kwargs)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise FitError(f"PTC fit failed on these points ({exc}); check the signals and "
                       "variances (ADU, ADU^2)") from exc


def _exptime(path):
    with open_fits(path) as hdul:
        for h in hdul:
            if "EXPTIME" in h.header:
                try:
                    return float(h.header["EXPTIME"])
                except (TypeError, ValueError):
                    raise InputError(f"{path}: EXPTIME = {h.header['EXPTIME']!r} is not a "
                                     "number; accepted: the exposure time in seconds") from None
    return None


def read_flat_pair(f1, f2, *, exptime_rtol=1e-3, with_exptime=False):
    """The two images of a flat pair, checked as a lab would.

    Parameters
    ----------
    f1, f2 : str, path-like or ndarray
        FITS files (first 2-d image HDU) or arrays.
    exptime_rtol : float, optional
        Largest relative difference of the two ``EXPTIME`` keywords (files).
    with_exptime : bool, optional
        Also return the pair's exposure time (s): the mean of the two
        ``EXPTIME`` keywords, None for arrays or files without the keyword.

    Returns
    -------
    img1, img2 : ndarray
    exptime : float or None
        Only with ``with_exptime``.

    Raises
    ------
    InputError
        The two have different shapes, different ``EXPTIME`` (beyond
        ``exptime_rtol``), or only one has ``EXPTIME``; the message names
        both files.
    """
    def is_path(f):
        return isinstance(f, (str, bytes)) or hasattr(f, "__fspath__")

    imgs = [read_image(f)[0] if is_path(f) else f for f in (f1, f2)]
    name = [str(f) if is_path(f) else "array" for f in (f1, f2)]
    s1, s2 = np.shape(imgs[0]), np.shape(imgs[1])
    if s1 != s2:
        raise InputError(f"flat pair {name[0]} and {name[1]}: shapes {s1} and {s2} differ; "
                         "accepted: two flats of one size")
    if is_path(f1) and is_path(f2):
        t1, t2 = _exptime(f1), _exptime(f2)
        if (t1 is None) != (t2 is None):
            raise InputError(f"flat pair {name[0]} and {name[1]}: EXPTIME given in only one "
                             "of them; accepted: both or neither")
        if t1 is not None and not abs(t1 - t2) <= exptime_rtol * max(abs(t1), abs(t2)):
            raise InputError(f"flat pair {name[0]} and {name[1]}: EXPTIME {t1} and {t2} differ "
                             f"by more than {exptime_rtol:g} relative; accepted: the two flats "
                             "of a pair have the same exposure time")
        if with_exptime and t1 is not None:
            return imgs[0], imgs[1], 0.5 * (t1 + t2)
    if with_exptime:
        return imgs[0], imgs[1], None
    return imgs[0], imgs[1]


class PairCovariance:
    """Covariances of one flat pair's difference image (halved).

    Attributes
    ----------
    mu : float
        Mean signal of the pair (ADU).
    cov : ndarray, shape (max_lag + 1, max_lag + 1)
        ``cov[di, dj]`` (ADU^2).
    npix : ndarray of int, same shape
        Number of pixel pairs behind each lag.
    nmasked : int
        Pixels masked (input mask, non-finite values, sigma clipping).
    static : ndarray or None
        With ``static=True``: S_ij = (Cov(f1 + f2) - Cov(f1 - f2)) / 4 (ADU^2)
        after scaling f2 to f1's mean, same lags, pixels and weights as
        ``cov``: zero for correlations created while the flats fill, mu^2
        times the autocovariance of a response pattern common to both flats.
    mu1, mu2 : float or None
        Mean of each flat over the pixels used (ADU), before the scaling.
    nvalid : int or None
        Number of pixels behind ``mu1`` and ``mu2`` (after masking, border and
        clipping).
    """

    def __init__(self, mu, cov, npix, nmasked, static=None, mu1=None, mu2=None, nvalid=None):
        self.mu, self.cov, self.npix, self.nmasked = float(mu), cov, npix, int(nmasked)
        self.static = static
        self.mu1, self.mu2, self.nvalid = mu1, mu2, nvalid


def _clip_mask(diff, mask, nsig, iters=3):
    """Extend ``mask`` with |diff - median| > nsig * 1.4826 MAD, iterated."""
    mask = mask.copy()
    for _ in range(iters):
        vals = diff[~mask]
        med = np.median(vals)
        mad = 1.4826 * np.median(np.abs(vals - med))
        if mad == 0:
            break
        new = mask | (np.abs(diff - med) > nsig * mad)
        if new.sum() == mask.sum():
            break
        mask = new
    return mask


def identical_flats(flat1, flat2, *, mask=None, rtol=1e-9):
    """Whether a flat pair has no difference variance, and why.

    Two exposures always differ by their shot noise; a pair whose
    difference (the second flat scaled to the first's mean, as in
    :func:`pair_covariances`) is zero over the valid pixels carries no
    photon transfer information. Its zero variance would otherwise read as
    saturation (:func:`ptc_turnoff`) and drop every brighter pair: readers
    check this first.

    Parameters
    ----------
    flat1, flat2 : array_like, 2-d, of one shape
    mask : array_like of bool, optional
        True for bad pixels (NaN/inf are left out too).
    rtol : float, optional
        A difference whose standard deviation is below ``rtol`` times the
        mean signal is zero.

    Returns
    -------
    None or (str, str)
        None when the difference has a variance (or the pair cannot be
        judged: no valid pixel, a mean not positive); else the kind,
        ``'constant'`` (both images one value: saturated, or not flats) or
        ``'copies'`` (one exposure twice, e.g. a copied file), and a
        sentence saying so.
    """
    a = np.asarray(flat1, dtype=np.float64)
    b = np.asarray(flat2, dtype=np.float64)
    if a.shape != b.shape:
        return None
    good = np.isfinite(a) & np.isfinite(b)
    if mask is not None:
        good &= ~np.asarray(mask, dtype=bool)
    if not good.any():
        return None
    a, b = a[good], b[good]
    mu1, mu2 = a.mean(), b.mean()
    if not (mu1 > 0 and mu2 > 0):
        return None
    if np.std(a - b * (mu1 / mu2)) > rtol * mu1:
        return None
    if np.std(a) <= rtol * mu1 and np.std(b) <= rtol * mu2:
        return "constant", (f"both images are constant ({mu1:.6g} and {mu2:.6g}: zero "
                            "difference variance): saturation, or not flats")
    return "copies", ("the two images are one exposure (identical pixel for pixel after "
                      "scaling to one mean: zero difference variance), e.g. a copied file; a "
                      "pair needs two exposures")


def pair_covariances(flat1, flat2, *, max_lag=8, mask=None, nsig=5.0, min_pixels=1000,
                     static=False, border=None):
    """Covariances of a flat pair's difference image by FFT.

    The second flat is scaled to the first's mean, the difference is
    sigma-clipped, masked pixels get zero weight, and for each lag the mean
    product of (mean-subtracted) differences over valid pixel pairs is
    computed from FFT autocorrelations of the data and of the weights; the
    result is halved (a difference has twice the variance of one flat).

    Parameters
    ----------
    flat1, flat2 : array_like, 2-d
        The two flats (ADU), bias-subtracted.
    max_lag : int, optional
        Largest lag in each direction.
    mask : array_like of bool, optional
        True for bad pixels (NaN/inf are masked too).
    nsig : float, optional
        Clipping threshold on the difference image.
    min_pixels : int, optional
        Smallest number of pixel pairs accepted for any lag.
    static : bool, optional
        Also the static term S_ij of the pair (:class:`PairCovariance`),
        from the same masked, clipped pixels (diagnosis).
    border : int, optional
        Pixels at each image edge left out (default :data:`EDGE_BORDER`, 10;
        images under 160 px keep at least their central three quarters). Pixels near an
        edge see no charge beyond it, so their boundaries move less: a flat
        made by galsim.SiliconSensor is 1.2 % dimmer in its first column at
        80 ke, a static pattern that would bias the static term and the
        diagnosis. LSST's ISR masks the same 10-pixel band as EDGE.

    Returns
    -------
    PairCovariance
    """
    a = np.array(flat1, dtype=np.float64)
    b = np.array(flat2, dtype=np.float64)
    if a.ndim != 2 or a.shape != b.shape:
        raise InputError(f"flats must be 2-d images of equal shape, got {a.shape} and {b.shape}")
    if int(max_lag) != max_lag or max_lag < 0:
        raise InputError(f"max_lag must be a non-negative integer, got {max_lag!r}")
    max_lag = int(max_lag)
    if max_lag >= min(a.shape):
        raise InputError(f"max_lag {max_lag} too large for image shape {a.shape}")
    bad = ~np.isfinite(a) | ~np.isfinite(b)
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != a.shape:
            raise InputError(f"mask shape {mask.shape} does not match flats {a.shape}")
        bad |= mask
    edge = edge_mask(a.shape, border)
    n_edge_bad = int((bad & edge).sum())  # NaN or masked in the border: still counted
    bad |= edge
    if (~bad).sum() < min_pixels:
        raise InputError(f"only {(~bad).sum()} valid pixels, fewer than min_pixels={min_pixels}")
    # Means, difference and clipping, twice: outliers (cosmic rays) must not
    # bias the means that scale the second flat.
    for _ in range(2):
        mu1 = a[~bad].mean()
        mu2 = b[~bad].mean()
        n_mean = int((~bad).sum())
        if not (mu1 > 0 and mu2 > 0):
            raise InputError(f"flat means must be positive, got {mu1:.4g} and {mu2:.4g} ADU")
        diff = np.where(bad, 0.0, a - b * (mu1 / mu2))
        bad = _clip_mask(diff, bad, nsig)
    w = (~bad).astype(np.float64)
    d = np.where(bad, 0.0, diff - diff[~bad].mean())
    ny, nx = d.shape
    shape = (sp_fft.next_fast_len(ny + max_lag), sp_fft.next_fast_len(nx + max_lag))
    L = max_lag
    fw = sp_fft.rfft2(w, shape)
    npairs = _lagged(np.rint(sp_fft.irfft2(fw * np.conj(fw), shape)), L)
    if npairs.min() < 2 * min_pixels:
        raise InputError(f"fewer than min_pixels={min_pixels} pixel pairs at some lag")
    cov = 0.5 * _lagged_products(d, shape, L) / npairs  # halved: var(diff) = 2 var(flat)
    stat = None
    if static:
        tot = np.where(bad, 0.0, a + b * (mu1 / mu2))
        tot = np.where(bad, 0.0, tot - tot[~bad].mean())
        stat = ((_lagged_products(tot, shape, L) / npairs - 2.0 * cov) / 4.0).T.copy()
    # arrays above are [dj, di]; return [di, dj]
    return PairCovariance(0.5 * (mu1 + mu2), cov.T.copy(), (npairs // 2).T.astype(int),
                          int((bad & ~edge).sum()) + n_edge_bad, static=stat,
                          mu1=float(mu1), mu2=float(mu2), nvalid=n_mean)


def least_squares_line(x, y):
    """Unweighted least-squares line y = slope x + intercept.

    Minimum-norm when degenerate (all x equal, or fewer than two points),
    without numpy's RankWarning: the callers need a starting point or a
    slope of noise-free points.

    Parameters
    ----------
    x, y : array_like, shape (n,)

    Returns
    -------
    ndarray, shape (2,)
        (slope, intercept).
    """
    a = np.stack([np.asarray(x, float), np.ones(len(x))], axis=1)
    return np.linalg.lstsq(a, np.asarray(y, float), rcond=None)[0]


#: Pixels left out at each image edge when flat pairs are measured (px).
EDGE_BORDER = 10


def edge_border(shape, border=None):
    """The border (px) left out of an image of ``shape``: ``border`` (default
    :data:`EDGE_BORDER`), reduced so that at least the central three quarters of each
    axis remains."""
    border = EDGE_BORDER if border is None else int(border)
    if border < 0:
        raise InputError(f"border must be >= 0 px, got {border}")
    return min(border, min(shape) // 8)


def edge_mask(shape, border=None):
    """True in the band of :func:`edge_border` pixels along each image edge."""
    edge = np.zeros(shape, bool)
    bd = edge_border(shape, border)
    if bd:
        edge[:bd] = edge[-bd:] = True
        edge[:, :bd] = edge[:, -bd:] = True
    return edge


def _lagged(prod, L):
    """Sum of a circular autocorrelation over the lags (dy, +-dx), [dj, di] <= L."""
    # prod[dy, dx] = sum d(y, x) d(y + dy, x + dx); negative dy wraps to the end
    return prod[:L + 1, :L + 1] + np.roll(prod[::-1, :L + 1], 1, axis=0)[:L + 1]


def _lagged_products(x, shape, L):
    """Sums of lagged products of a zero-padded image (FFT), [dj, di] <= L."""
    fx = sp_fft.rfft2(x, shape)
    return _lagged(sp_fft.irfft2(fx * np.conj(fx), shape), L)

def measure_ptc(pairs, *, max_lag=8, masks=None, **kwargs):
    """Covariances of many flat pairs, sorted by signal.

    Parameters
    ----------
    pairs : sequence of (flat1, flat2)
        Arrays, or FITS paths (first 2-d HDU).
    max_lag : int, optional
        Largest lag.
    masks : sequence of array_like, optional
        One bad-pixel mask per pair.
    **kwargs
        Passed to :func:`pair_covariances`.

    Returns
    -------
    astropy.table.Table
        Columns ``mu`` (ADU), ``cov`` (ADU^2, shape (L+1, L+1) per row),
        ``npix``, ``nmasked``.
    """
    rows = []
    for k, (f1, f2) in enumerate(pairs):
        f1, f2 = read_flat_pair(f1, f2)
        m = None if masks is None else masks[k]
        rows.append(pair_covariances(f1, f2, max_lag=max_lag, mask=m, **kwargs))
    if not rows:
        raise InputError("no flat pairs given")
    rows.sort(key=lambda r: r.mu)
    t = Table()
    t["mu"] = np.array([r.mu for r in rows])
    t["cov"] = np.array([r.cov for r in rows])
    t["npix"] = np.array([r.npix for r in rows])
    t["nmasked"] = np.array([r.nmasked for r in rows])
    t["mu"].unit = "adu"
    return t


def ptc_exponential_model(mu, gain, a00, noise):
    """C00 of Astier et al. 2019 eq. 16 (ADU^2) at signals ``mu`` (ADU)."""
    mu = np.asarray(mu, dtype=float)
    x = 2.0 * a00 * mu * gain
    # expm1(x) / x -> 1 for a00 -> 0
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.where(np.abs(x) > 1e-12, np.expm1(x) / np.where(x == 0, 1, x), 1.0)
    return mu / gain * r + noise / gain**2


def _fit_result(res, names, ndata, *, known_sigma):
    """Parameters, errors and covariance of a least-squares result.

    With ``known_sigma`` the covariance is scaled by chi2/dof only when that
    exceeds 1; without (residuals in arbitrary units) it is always scaled, so
    the errors reflect the scatter of the data.
    """
    dof = max(ndata - len(names), 1)
    chi2 = float(np.sum(res.fun**2))
    # normalise the Jacobian's columns first: parameters span 1e-8 (a_ij) to
    # 10 (noise), and an unscaled pseudo-inverse would drop real directions
    jac = res.jac
    norm = np.linalg.norm(jac, axis=0)
    norm[norm == 0] = 1.0
    js = jac / norm
    cov = np.linalg.pinv(js.T @ js) / np.outer(norm, norm)
    factor = max(chi2 / dof, 1.0) if known_sigma else chi2 / dof
    cov = cov * factor
    err = np.sqrt(np.diag(cov))
    out = {n: float(v) for n, v in zip(names, res.x)}
    out.update({f"{n}_err": float(e) for n, e in zip(names, err)})
    out.update({"chi2": chi2, "dof": dof, "covariance": cov.tolist(),
                "success": bool(res.success)})
    return out


def ptc_turnoff(mu, var, *, drop=0.05):
    """Signal where the PTC turns off (saturation): the last point before the
    variance first falls more than ``drop`` below its running maximum.

    Returns ``inf`` if it never does.
    """
    order = np.argsort(mu)
    m, v = np.asarray(mu, float)[order], np.asarray(var, float)[order]
    running = np.maximum.accumulate(v)
    fall = np.flatnonzero(v < (1.0 - drop) * running)
    return float(m[fall[0] - 1]) if fall.size else float("inf")


def fit_ptc_exponential(mu, var, *, sigma=None, mu_max="auto", p0=None):
    """Fit gain, a00 and noise of the exponential PTC model.

    Parameters
    ----------
    mu, var : array_like
        Mean signal (ADU) and variance (ADU^2) of flat pairs.
    sigma : array_like, optional
        Errors of ``var``; default: equal relative errors of a size set by
        the scatter (parameter errors scaled by sqrt(chi2/dof)). With given
        errors the scaling applies only when chi2/dof > 1.
    mu_max : float, 'auto' or None, optional
        Exclude points above this signal; 'auto' (default) cuts at
        :func:`ptc_turnoff` (saturation), None keeps everything.
    p0 : tuple, optional
        Starting gain (e/ADU), a00 (1/e), noise (e^2); default: the gain from
        the lowest third of the signals, a00 = -1e-6, noise = 0.

    Returns
    -------
    dict
        ``gain``, ``a00``, ``noise`` and their ``*_err``, ``chi2``, ``dof``,
        ``covariance``, ``npoints``.
    """
    mu = np.asarray(mu, dtype=float)
    var = np.asarray(var, dtype=float)
    if mu.shape != var.shape or mu.ndim != 1:
        raise InputError("mu and var must be 1-d arrays of equal length")
    good = np.isfinite(mu) & np.isfinite(var) & (mu > 0) & (var > 0)
    if isinstance(mu_max, str):
        if mu_max != "auto":
            raise InputError(f"mu_max must be a number, 'auto' or None, got {mu_max!r}")
        mu_max = ptc_turnoff(mu[good], var[good])
    if mu_max is not None:
        good &= mu <= mu_max
    if good.sum() < MIN_PTC_POINTS:
        raise InputError(f"need at least {MIN_PTC_POINTS} valid PTC points, got "
                         f"{int(good.sum())}")
    order = np.argsort(mu[good])
    m, v = mu[good][order], var[good][order]
    _check_points(m, v)
    s = v if sigma is None else np.asarray(sigma, float)[good][order]
    if np.any(~(s > 0)):
        raise InputError("sigma must be positive")
    if p0 is None:
        # straight line var = mu / g + n / g^2 through the lowest third
        k = max(3, len(m) // 3)
        slope, icpt = least_squares_line(m[:k], v[:k])  # a start only: no rank warning on ties
        g_est = 1.0 / slope if slope > 0 else 1.0
        start = (g_est, -1e-6, max(icpt, 0.0) * g_est**2)
    else:
        start = tuple(float(v_) for v_ in p0)

    def resid(p):
        return (ptc_exponential_model(m, *p) - v) / s

    res = _fit(resid, start, x_scale=(0.1, 1e-6, 10.0), method="lm")
    out = _fit_result(res, ("gain", "a00", "noise"), len(m), known_sigma=sigma is not None)
    out["npoints"] = int(len(m))
    out["mu_max"] = float(m.max())
    return out


def read_ptc_text(path):
    """Read a two-column PTC text file (mean ADU, variance ADU^2).

    Blank lines, ``#`` comments and header lines (no number in them, before
    the first row) are skipped (:func:`~lsst_bfdrift.utils.io.read_text_rows`).
    Every row holds exactly two numbers: a third column (an error of the
    variance, a pair count, ...) is refused rather than dropped unread.

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    mu, var : ndarray
        Means and variances, sorted by mean.

    Raises
    ------
    InputFileError
        A malformed row, a row of another width, or no rows, naming the file
        (and the line).
    """
    path = os.fspath(path)
    accepted = "two numeric columns (mean ADU, variance ADU^2) per line, '#' comments"
    rows = read_text_rows(path, accepted=accepted)
    if not rows:
        raise InputFileError(f"no PTC rows; accepted: {accepted}", path)
    for n, vals in rows:
        if len(vals) != 2:
            extra = (" (a third column, e.g. an error of the variance, is not read by any "
                     "PTC fit here: remove it)" if len(vals) > 2 else "")
            raise InputFileError(f"{path}:{n}: {len(vals)} column(s); accepted: {accepted}"
                                 + extra, path)
    data = np.array([vals for _, vals in rows], dtype=float)
    order = np.argsort(data[:, 0], kind="stable")
    return data[order, 0], data[order, 1]
