"""Flat-set observations for the diagnosis: the statistics of flat pairs and the edges.

:class:`Observations` holds what :func:`~lsst_bfdrift.diagnosis.effects_fit.diagnose`
fits: an a_ij table, a PTC, or the statistics of flat pairs
(:func:`observations_from_pairs`: per pair the mean, the difference-image
covariances C_ij, the static statistic S_ij of the pair sums and the pixel
counts, from the interior; the rings at the image edges, :func:`edge_profile`,
judged by :func:`edge_signature`; the observables of
:mod:`~lsst_bfdrift.ptc.observables`; EXPTIME when given).
"""

import numpy as np
from scipy import stats

from lsst_bfdrift.ptc.observables import lag_error_factors, pair_observables, turnoff_cut
from lsst_bfdrift.ptc.covariances import (edge_border, identical_flats, pair_covariances,
                                          read_flat_pair)
from lsst_bfdrift.utils.errors import InputError

__all__ = ["Observations", "pair_statistics", "edge_profile", "edge_signature",
           "observations_from_pairs"]


def pair_statistics(flat1, flat2, *, max_lag=3, border=None):
    """mu, C_ij (difference image, halved), S_ij (static) and pixel counts of one pair.

    S_ij = (Cov(f1 + f2) - Cov(f1 - f2)) / 4 after scaling f2 to f1's mean:
    zero for correlations created while the flats fill, mu^2 times the
    autocovariance of a static response pattern. Pixels within
    :data:`~lsst_bfdrift.ptc.covariances.EDGE_BORDER` of the image edges are
    left out (:func:`edge_profile` looks at them).
    """
    pc = _pair_covariance(flat1, flat2, max_lag, border)
    return pc.mu, pc.cov, pc.static, pc.npix


def _pair_covariance(flat1, flat2, max_lag, border):
    f1 = np.asarray(flat1, dtype=float)
    return pair_covariances(f1, flat2, max_lag=max_lag, min_pixels=min(1000, f1.size // 4),
                            static=True, border=border)


def edge_profile(flat1, flat2, *, border=None):
    """Relative signal of the pixel rings at the image edges, and its error.

    Ring k holds the pixels at distance k (0 = the outermost row and column)
    from the nearest edge, for k below the border that the covariances leave
    out (:func:`~lsst_bfdrift.ptc.covariances.edge_border`).

    Returns
    -------
    ratio, sigma : ndarray
        Mean of the pair sum in each ring over its mean in the interior, minus
        1, and the standard error of that number (from the scatter of the
        ring's pixels).
    """
    a = np.asarray(flat1, dtype=float)
    b = np.asarray(flat2, dtype=float)
    tot = a + b
    ny, nx = tot.shape
    bd = edge_border(tot.shape, border)
    yy, xx = np.mgrid[:ny, :nx]
    dist = np.minimum(np.minimum(yy, ny - 1 - yy), np.minimum(xx, nx - 1 - xx))
    good = np.isfinite(tot)
    inner = tot[(dist >= bd) & good]
    m = inner.mean()
    ratio, sigma = np.zeros(bd), np.zeros(bd)
    for k in range(bd):
        ring = tot[(dist == k) & good]
        ratio[k] = ring.mean() / m - 1.0
        sigma[k] = np.hypot(ring.std() / np.sqrt(ring.size), inner.std() / np.sqrt(inner.size)) / m
    return ratio, sigma


def edge_signature(mu, ratio, sigma, *, p_threshold=1e-3):
    """Test of the edge rings against the interior over all pairs.

    Parameters
    ----------
    mu : ndarray, shape (n,)
        Pair means.
    ratio, sigma : ndarray, shape (n, K)
        :func:`edge_profile` of each pair.
    p_threshold : float, optional
        p-value below which the rings differ from the interior.

    Returns
    -------
    dict
        ``chi2``, ``dof``, ``p_value``, ``detected``; ``slope`` (relative
        change per ring and per e of signal, from a fit ratio = c + s mu per
        ring), ``constant`` (the c), ``at_top`` (ratio at the highest signal)
        and ``description``: what the rings show, with the sign and the rings
        involved, e.g. dimmer edges growing with signal (no charge beyond the
        edge pulls the boundaries less: a simulation's or a sensor's edge) or
        a constant offset (illumination or response).
    """
    mu = np.asarray(mu, float)
    ratio = np.asarray(ratio, float)
    sigma = np.asarray(sigma, float)
    pulls = ratio / sigma
    chi2 = float(np.sum(pulls**2))
    dof = int(pulls.size)
    p = float(stats.chi2.sf(chi2, dof))
    K = ratio.shape[1]
    slope, const = np.zeros(K), np.zeros(K)
    for k in range(K):
        w = 1.0 / sigma[:, k] ** 2
        A = np.stack([np.ones_like(mu), mu], axis=1)
        coef = np.linalg.lstsq(A * np.sqrt(w)[:, None], ratio[:, k] * np.sqrt(w), rcond=None)[0]
        const[k], slope[k] = coef
    top = int(np.argmax(mu))
    detected = p < p_threshold
    desc = "edge rings consistent with the interior"
    if detected:
        sig_rings = [k for k in range(K) if np.sqrt(np.sum(pulls[:, k] ** 2)) >
                     np.sqrt(mu.size) + 3.0]
        rings = sig_rings or [int(np.argmax(np.sum(pulls**2, axis=0)))]
        r0 = ratio[top, rings[0]]
        grows = abs(slope[rings[0]] * mu[top]) > abs(const[rings[0]])
        desc = (f"edge signature: pixels {', '.join(str(k) for k in rings)} px from the image "
                f"edge are {abs(r0) * 100:.2g} % {'dimmer' if r0 < 0 else 'brighter'} than the "
                f"interior at {mu[top]:.3g} (ring {rings[0]}; chi2 {chi2:.0f} for {dof} points, "
                f"p = {p:.1e}); "
                + ("it grows with the signal (charge missing beyond the edge: boundaries there "
                   "move less, as in a simulation with open edges or at a sensor's edge)"
                   if grows else "it does not grow with the signal (illumination or response "
                   "at the edges)")
                + f"; these pixels ({K} px band) are left out of the fit")
    return {"chi2": chi2, "dof": dof, "p_value": p, "detected": bool(detected),
            "slope": slope.tolist(), "constant": const.tolist(),
            "at_top": ratio[top].tolist(), "description": desc}


class Observations:
    """Observables of one input, with errors.

    Use the constructors :meth:`from_table`, :meth:`from_ptc` and
    :meth:`from_flats`.
    """

    def __init__(self, kind, **kw):
        if kind not in ("table", "ptc", "flats"):
            raise InputError(f"unknown input kind {kind!r}")
        self.kind = kind
        self.__dict__.update(kw)

    @classmethod
    def from_table(cls, table):
        """From an :class:`~lsst_bfdrift.ptc.acoeffs.AcoeffTable`."""
        return cls("table", a=table.a, sigma=table.sigma, mask=table.mask(),
                   max_lag=table.max_lag, note=table.axis_note,
                   source=table.source or "the a_ij table")

    @classmethod
    def from_ptc(cls, mu, var):
        """From a PTC: means (ADU) and variances (ADU^2)."""
        mu = np.asarray(mu, float)
        var = np.asarray(var, float)
        if mu.shape != var.shape or mu.ndim != 1:
            raise InputError("PTC mean and variance must be 1-d arrays of equal length")
        good = np.isfinite(mu) & np.isfinite(var) & (mu > 0) & (var > 0)
        nbad = int(mu.size - good.sum())
        turnoff = None
        if good.any():  # saturation cut (ptc_turnoff, 5 % drop), the points left out listed
            keep, turnoff = turnoff_cut(mu[good], var[good])
            good[np.flatnonzero(good)[~keep]] = False
        if good.sum() < 6:
            why = [f"{nbad} not finite and positive"] if nbad else []
            if turnoff is not None and turnoff["excluded"]:
                why.append(f"{len(turnoff['excluded'])} past the turn-off at "
                           f"{turnoff['break_level']:.6g} ADU (the variance falls more than "
                           f"{turnoff['drop']:.0%} below its running maximum: saturation)")
            raise InputError(f"need at least 6 valid PTC points, got {int(good.sum())} of "
                             f"{mu.size}" + (f" ({'; '.join(why)})" if why else ""))
        o = np.argsort(mu[good])
        return cls("ptc", mu=mu[good][o], var=var[good][o], max_lag=0, turnoff=turnoff,
                   note=f"{good.sum()} points below the turn-off; errors unknown: "
                        "scaled so that the base fit has chi2/dof = 1")

    @classmethod
    def from_flats(cls, mu, cov, static, npix):
        """From per-pair statistics (see :func:`observations_from_pairs`).

        Pairs above the turn-off (:func:`~lsst_bfdrift.ptc.observables.turnoff_cut`:
        the variance falls below its running maximum by more than 5 % and 5
        sigma) are left out; ``turnoff`` lists them and ``kept`` marks the
        pairs used, in input order.
        """
        mu = np.asarray(mu, float)
        cov = np.asarray(cov, float)
        static = np.asarray(static, float)
        npix = np.asarray(npix, float)
        if cov.ndim != 3 or cov.shape != static.shape or cov.shape != npix.shape or \
                cov.shape[0] != mu.size:
            raise InputError("cov, static and npix must have shape (n, L+1, L+1), n = len(mu)")
        if mu.size < 4:
            raise InputError(f"need at least 4 flat pairs, got {mu.size}")
        if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(static))):
            raise InputError("non-finite covariances")
        kept, turnoff = turnoff_cut(mu, cov[:, 0, 0], npix[:, 0, 0])
        if kept.sum() < 4:
            raise InputError(f"need at least 4 flat pairs, got {int(kept.sum())} below the "
                             f"turn-off at {turnoff['break_level']:.4g} ADU ({mu.size} given)")
        return cls("flats", mu=mu[kept], cov=cov[kept], static=static[kept], npix=npix[kept],
                   max_lag=cov.shape[1] - 1, note="", kept=kept, turnoff=turnoff)

    def data(self):
        """(y, sigma, labels) of the points in chi2; labels are (block, level, i, j)."""
        if self.kind == "table":
            ij = np.argwhere(self.mask)
            return (self.a[self.mask], self.sigma[self.mask],
                    [("a", 0, int(i), int(j)) for i, j in ij])
        if self.kind == "ptc":
            if not hasattr(self, "_sig"):
                self._sig = None
            s = self._sig if self._sig is not None else self.var * 1e-3
            return self.var, s, [("C", k, 0, 0) for k in range(self.mu.size)]
        # Errors of sample covariances of N pixels: lag 0 sqrt(2) V / sqrt(N), on
        # the axes V / sqrt(N), off the axes V / sqrt(2 N) ((i, j) and (i, -j) are
        # independent products), V the variance of the image.
        L1 = self.max_lag + 1
        f = lag_error_factors(self.max_lag)
        c00 = self.cov[:, 0, 0][:, None, None]
        sc = c00 * f / np.sqrt(self.npix)
        # pair sums: noise variance vn = 2 C00 and static variance vp = 4 S00
        vn = 2.0 * c00
        vp = 4.0 * np.clip(self.static[:, 0, 0], 0, None)[:, None, None]
        ss = np.sqrt((4.0 * vp * vn + 2.0 * vn**2) / 16.0) * f / np.sqrt(self.npix)
        n = self.mu.size
        lab = [(b, k, i, j) for b in ("C", "S") for k in range(n) for i in range(L1)
               for j in range(L1)]
        return (np.concatenate([self.cov.ravel(), self.static.ravel()]),
                np.concatenate([sc.ravel(), ss.ravel()]), lab)


def observations_from_pairs(pairs, *, max_lag=3, border=None, exptimes=None):
    """:class:`Observations` of kind 'flats' from flat pairs (arrays or FITS paths).

    Parameters
    ----------
    pairs : sequence of (flat1, flat2)
        Arrays (ADU) or FITS paths.
    max_lag : int, optional
        Largest lag.
    border : int, optional
        Pixels left out at the image edges (default
        :data:`~lsst_bfdrift.ptc.covariances.EDGE_BORDER`); the rings inside
        it are measured by :func:`edge_profile` and tested by :func:`diagnose`.
    exptimes : sequence of float, optional
        Exposure time of each pair (s), in the order of ``pairs``; default:
        the files' ``EXPTIME``. Without either the linearity check is not
        available.

    Returns
    -------
    Observations
        With, beside the fitted statistics, ``pairs`` (per pair the means of
        each flat and the statistics of the image halves,
        :func:`~lsst_bfdrift.ptc.observables.pair_observables`),
        ``exptime`` (s, or None with ``exptime_note`` saying why) and
        ``turnoff`` (the pairs above the turn-off, left out).

    Raises
    ------
    InputError
        A pair of different shapes or ``EXPTIME``, or one exposure twice
        (:func:`~lsst_bfdrift.ptc.covariances.identical_flats`: zero
        difference variance, e.g. a copied file), naming both files; two
        constant images are left to the turn-off (saturation).
    """
    pairs = list(pairs)
    if exptimes is not None:
        exptimes = np.asarray(exptimes, dtype=float)
        if exptimes.shape != (len(pairs),) or not np.all(np.isfinite(exptimes) & (exptimes > 0)):
            raise InputError(f"exptimes must hold one positive exposure time (s) per pair: "
                             f"{len(pairs)} pairs, got {exptimes.tolist()!r}")
    rows = []
    for k, (f1, f2) in enumerate(pairs):
        names = [str(f) if isinstance(f, (str, bytes)) or hasattr(f, "__fspath__") else None
                 for f in (f1, f2)]
        # same shape and EXPTIME, or an error naming both
        f1, f2, t = read_flat_pair(f1, f2, with_exptime=True)
        same = identical_flats(f1, f2)
        if same is not None and same[0] == "copies":  # constant (saturated): the turn-off's
            what = (f"flat pair {names[0]} and {names[1]}" if None not in names
                    else f"flat pair {k} (arrays)")
            raise InputError(f"{what}: {same[1]}; replace one of them by another exposure at "
                             "its level, or leave the pair out")
        pc = _pair_covariance(f1, f2, max_lag, border)
        rows.append((pc.mu, pc.cov, pc.static, pc.npix) + edge_profile(f1, f2, border=border)
                    + (t if exptimes is None else float(exptimes[k]),
                       pair_observables(f1, f2, max_lag=max_lag, border=border, whole=pc)))
    rows.sort(key=lambda r: r[0])
    obs = Observations.from_flats([r[0] for r in rows], [r[1] for r in rows],
                                  [r[2] for r in rows], [r[3] for r in rows])
    rows = [r for r, keep in zip(rows, obs.kept) if keep]
    if rows[0][4].size:  # no rings with border=0
        obs.edge_ratio = np.array([r[4] for r in rows])
        obs.edge_sigma = np.array([r[5] for r in rows])
    obs.pairs = [r[7] for r in rows]
    missing = [k for k, r in enumerate(rows) if r[6] is None]
    bad = [r[6] for r in rows if r[6] is not None and not (np.isfinite(r[6]) and r[6] > 0)]
    obs.exptime = None if missing or bad else np.array([r[6] for r in rows])
    obs.exptime_note = "" if obs.exptime is not None else (
        "no exposure times (arrays without exptimes=, or files without EXPTIME)"
        if len(missing) == len(rows) else
        f"EXPTIME missing for {len(missing)} of {len(rows)} pairs" if missing else
        f"EXPTIME not positive in {len(bad)} pair(s) ({bad[0]!r} s)")
    return obs
