"""Flat-field simulations with moving pixel boundaries (Rasmussen 2015, section 4.3).

A stack of small periodic images is filled in steps: each step adds Poisson
charge with rate proportional to each pixel's current area, then the areas
are re-evaluated from the template (the Green's function) and the collected
charge. Images are periodic, so every pixel sees a full neighbourhood and the
superposition is a circular convolution (the template wraps around images
smaller than itself, which is the periodic superposition).

After each step two estimators of the covariances are computed:

* ``paper``: the paper's statistic, over every unique pair of images, the
  lagged products of the difference image summed and divided by
  2 mu N_pix (so that a Poisson image gives C00 = 1). The sum over pairs is
  done with sum_{a<b} d_ab d_ab' = N sum_a I_a I_a' - S S' (S = sum_a I_a).
* ``pairs``: the per-pair statistic of LSST's PTC code: consecutive images
  form pairs; the covariance of each pair's difference image at each lag,
  halved, averaged over pairs, with the error from their scatter (e^2).
"""

import numpy as np
from astropy.table import Table

from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["PeriodicAreas", "simulate_flats", "simulate_ptc_levels", "template_area_coefficients",
           "with_responsivity"]


class PeriodicAreas:
    """Pixel areas of stacks of periodic images from a template.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    shape : tuple of int
        (ny, nx) of the periodic images.
    """

    def __init__(self, template, shape):
        ny, nx = (int(v) for v in shape)
        if ny < 2 or nx < 2:
            raise ValueError(f"periodic images need at least 2 x 2 pixels, got {shape}")
        self.t = template
        self.shape = (ny, nx)
        c = template.center
        q = 1.0 / template.charge

        def wrap(k):
            # kernel[(row - c) mod ny, (col - c) mod nx] += k[row, col]
            out = np.zeros((ny, nx))
            rows = (np.arange(k.shape[0]) - c) % ny
            cols = (np.arange(k.shape[1]) - c) % nx
            np.add.at(out, (rows[:, None], cols[None, :]), k)
            return np.fft.rfft2(out * q)

        t = template
        self._kc = [wrap(t.corner_d[..., 0]), wrap(t.corner_d[..., 1])]
        self._kv = [wrap(t.vedge_d[..., s]) for s in range(t.edge_samples)]
        self._kh = [wrap(t.hedge_d[..., s]) for s in range(t.edge_samples)]
        self._kvt = None if t.vedge_t is None else [wrap(t.vedge_t[..., s])
                                                     for s in range(t.edge_samples)]
        self._kht = None if t.hedge_t is None else [wrap(t.hedge_t[..., s])
                                                     for s in range(t.edge_samples)]

    def displacements(self, charge):
        """Periodic displacement arrays for a stack ``charge[k, y, x]`` (e).

        Returns corner (dx, dy), vedge (normal), hedge (normal), vedge_t,
        hedge_t, each of shape (k, ny, nx[, ns]); index [J, I] is the corner
        at (I - 1/2, J - 1/2), the left edge and the bottom edge of pixel (I, J).
        """
        ny, nx = self.shape
        fq = np.fft.rfft2(np.asarray(charge, float), axes=(-2, -1))

        def conv(kernels):
            return np.stack([np.fft.irfft2(fq * k, s=(ny, nx), axes=(-2, -1))
                             for k in kernels], axis=-1)
        cd = conv(self._kc)
        v = conv(self._kv)
        h = conv(self._kh)
        vt = None if self._kvt is None else conv(self._kvt)
        ht = None if self._kht is None else conv(self._kht)
        return cd, v, h, vt, ht

    def areas(self, charge):
        """Pixel areas (px^2) of a stack of periodic images ``charge[k, y, x]``.

        Exact shoelace area, accumulated edge by edge: each boundary polyline
        (corner, samples, corner) is summed once and added to the pixel on
        one side and subtracted from the pixel on the other.
        """
        cd, v, h, vt, ht = self.displacements(charge)
        fr = self.t.fractions
        # Vertical polyline of [J, I] (left edge of pixel (I, J)), upwards, in
        # coordinates relative to the corner (I - 1/2, J - 1/2):
        cx0, cy0 = cd[..., 0], cd[..., 1]
        cx1 = np.roll(cd[..., 0], -1, axis=-2)  # corner above
        cy1 = np.roll(cd[..., 1], -1, axis=-2) + 1.0
        vy = fr + (0.0 if vt is None else vt)
        vx = np.concatenate([cx0[..., None], v, cx1[..., None]], axis=-1)
        vyy = np.concatenate([cy0[..., None], np.broadcast_to(vy, v.shape), cy1[..., None]],
                             axis=-1)
        s_v = 0.5 * np.sum(vx[..., 1:] * vyy[..., :-1] - vx[..., :-1] * vyy[..., 1:], axis=-1)
        # Horizontal polyline of [J, I] (bottom edge of pixel (I, J)), rightwards
        dx1 = np.roll(cd[..., 0], -1, axis=-1) + 1.0  # corner to the right
        dy1 = np.roll(cd[..., 1], -1, axis=-1)
        hx = fr + (0.0 if ht is None else ht)
        hxx = np.concatenate([cx0[..., None], np.broadcast_to(hx, h.shape), dx1[..., None]],
                             axis=-1)
        hyy = np.concatenate([cy0[..., None], h, dy1[..., None]], axis=-1)
        s_h = 0.5 * np.sum(hxx[..., 1:] * hyy[..., :-1] - hxx[..., :-1] * hyy[..., 1:],
                           axis=-1)
        # The polylines are in coordinates relative to their own start corner;
        # moving the origin of an open polyline changes its sum by
        # 1/2 (o_y dx - o_x dy) with (dx, dy) its end-to-start chord, so shift
        # each to the pixel's lower-left corner frame before combining.
        # left edge of (I, J): origin already (I-1/2, J-1/2)
        left = s_v
        # right edge: polyline of [J, I+1] starts at (I+1/2, J-1/2): offset (1, 0)
        sv_r = np.roll(s_v, -1, axis=-1)
        chord_vx = np.roll(cx1 - cx0, -1, axis=-1)
        chord_vy = np.roll(cy1 - cy0, -1, axis=-1)
        right = sv_r + 0.5 * (0.0 * chord_vx - 1.0 * chord_vy)
        # bottom edge of (I, J): origin already the lower-left corner
        bottom = s_h
        # top edge: polyline of [J+1, I] starts at (I-1/2, J+1/2): offset (0, 1)
        sh_t = np.roll(s_h, -1, axis=-2)
        chord_hx = np.roll(dx1 - cx0, -1, axis=-2)
        chord_hy = np.roll(dy1 - cy0, -1, axis=-2)
        top = sh_t + 0.5 * (1.0 * chord_hx - 0.0 * chord_hy)
        # clockwise: up the left, right along the top, down the right, left along the bottom
        return left + top - right - bottom


def with_responsivity(template, dlna00_per_e):
    """The same boundary displacements attributed to another aggressor charge.

    Returns a template whose ln A00 / Q equals ``dlna00_per_e`` (1/e, the
    paper's "responsivity", negative): the displacements are kept and the
    charge Q is changed. (:meth:`DistortionTemplate.scaled` multiplies both
    and so keeps the responsivity.)

    Parameters
    ----------
    template : DistortionTemplate
        Source template.
    dlna00_per_e : float
        Target ln A00 / Q (1/e), negative and finite.

    Returns
    -------
    DistortionTemplate
    """
    r = float(dlna00_per_e)
    if not (np.isfinite(r) and r < 0):
        raise ValueError(f"responsivity must be negative and finite, got {dlna00_per_e!r}")
    c = template.center
    own = np.log(template.moments().area[c, c])
    if not own < 0:
        raise ValueError("template's central pixel does not shrink; no responsivity to rescale")
    return type(template)(template.corner_d, template.vedge_d, template.hedge_d,
                          template.fractions, own / r, vedge_t=template.vedge_t,
                          hedge_t=template.hedge_t,
                          meta={**template.meta, "rescaled_responsivity": r})


def template_area_coefficients(template, *, max_lag=3):
    """The template's area coefficients a_ij (1/e) in three definitions.

    Boundary displacements are linear in the aggressor charge Q and a
    polygon's area is quadratic in its vertices, so exactly
    A_ij(Q) = 1 + l_ij Q + q_ij Q^2. The covariance model of Astier et al.
    (2019) uses the linear response ``alpha`` = l_ij = dA_ij/dQ at Q = 0
    (in a uniform flat the mean charge displaces no boundary of a symmetric
    template, so this is also the response at any signal). The template's
    own ``(A_ij - 1) / Q`` and ``ln A_ij / Q`` differ from it by
    O(q_ij Q) in opposite directions.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    max_lag : int, optional
        Largest lag returned (at most the template's half size).

    Returns
    -------
    dict
        ``alpha``, ``linear`` ((A - 1) / Q), ``log`` (ln A / Q), each an
        array [di, dj] (1/e) of lags 0..max_lag, and ``charge`` (Q, e).
    """
    c = template.center
    L = int(max_lag)
    if not 0 <= L <= c:
        raise ValueError(f"max_lag must be in [0, {c}] for this template, got {max_lag!r}")
    q = template.charge
    full = template.moments(charge=q).area
    half = template.moments(charge=0.5 * q).area
    # A(f) = 1 + l f + s f^2 at f = 1 and 1/2: l = 4 (A(1/2) - 1) - (A(1) - 1)
    lin = 4.0 * (half - 1.0) - (full - 1.0)

    def quad(arr):  # [dj + c, di + c] -> [di, dj]
        return np.ascontiguousarray(arr[c:c + L + 1, c:c + L + 1].T)
    return {"alpha": quad(lin) / q, "linear": quad(full - 1.0) / q,
            "log": quad(np.log(full)) / q, "charge": q}


def _circular_autocorr(x, lags):
    """Sum over pixels of x(p) x(p + lag) (periodic) for lags [(di, dj), ...]."""
    f = np.fft.rfft2(x, axes=(-2, -1))
    r = np.fft.irfft2(f * np.conj(f), s=x.shape[-2:], axes=(-2, -1))
    ny, nx = x.shape[-2:]
    out = np.empty(x.shape[:-2] + (len(lags),))
    for k, (di, dj) in enumerate(lags):
        # average of (di, dj) and (di, -dj)
        out[..., k] = 0.5 * (r[..., dj % ny, di % nx] + r[..., (-dj) % ny, di % nx])
    return out


def simulate_flats(template, *, n_images=1024, shape=(16, 16), step=1000.0, n_steps=250,
                   max_lag=3, seed=None, rng=None, progress=False):
    """Fill a stack of periodic flats in steps with moving boundaries.

    Parameters
    ----------
    template : DistortionTemplate
        Green's function (its charge sets the responsivity).
    n_images : int, optional
        Images in the stack (even; consecutive images form the LSST pairs).
    shape : tuple of int, optional
        (ny, nx) of each image.
    step : float, optional
        Mean electrons added per pixel per step.
    n_steps : int, optional
        Number of fill steps.
    max_lag : int, optional
        Largest lag reported.
    seed : int, optional
        Seed of a new numpy Generator (ignored when ``rng`` is given).
    rng : numpy.random.Generator, optional
        Random generator.
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    astropy.table.Table
        One row per step: ``mu`` (e), ``paper`` (C_ij / mu, shape
        (L+1, L+1), indexed [di, dj]), ``pairs`` (C_ij in e^2) and
        ``pairs_err``, ``area_min``, ``area_max``.
    """
    if int(n_images) != n_images or n_images < 4 or n_images % 2:
        raise ValueError(f"n_images must be an even integer >= 4, got {n_images!r}")
    if not (np.isfinite(step) and step > 0):
        raise ValueError(f"step must be positive, got {step!r}")
    if int(n_steps) != n_steps or n_steps < 1:
        raise ValueError(f"n_steps must be a positive integer, got {n_steps!r}")
    rng = np.random.default_rng(seed) if rng is None else rng
    geo = PeriodicAreas(template, shape)
    ny, nx = geo.shape
    n = int(n_images)
    npix = ny * nx
    if max_lag >= min(ny, nx) // 2:
        raise ValueError(f"max_lag {max_lag} too large for {ny} x {nx} periodic images")
    lags = [(di, dj) for di in range(max_lag + 1) for dj in range(max_lag + 1)]
    charge = np.zeros((n, ny, nx))
    area = np.ones((n, ny, nx))
    rows = []
    with ProgressBar(n_steps, "flat-sim", enabled=progress) as bar:
        for _ in range(int(n_steps)):
            charge += rng.poisson(step * area)
            area = geo.areas(charge)
            mu = charge.mean()
            # paper: all unique pairs
            r_each = _circular_autocorr(charge, lags).sum(axis=0)
            r_sum = _circular_autocorr(charge.sum(axis=0), lags)
            npairs = n * (n - 1) / 2
            paper = (n * r_each - r_sum) / (2.0 * mu * npairs * npix)
            # LSST: consecutive pairs, mean-subtracted difference, halved
            d = charge[0::2] - charge[1::2]
            d = d - d.mean(axis=(-2, -1), keepdims=True)
            per_pair = 0.5 * _circular_autocorr(d, lags) / npix
            rows.append((mu, paper.reshape(max_lag + 1, max_lag + 1),
                         per_pair.mean(axis=0).reshape(max_lag + 1, max_lag + 1),
                         (per_pair.std(axis=0, ddof=1) / np.sqrt(per_pair.shape[0]))
                         .reshape(max_lag + 1, max_lag + 1), area.min(), area.max()))
            bar(1)
    t = Table(rows=rows, names=("mu", "paper", "pairs", "pairs_err", "area_min", "area_max"))
    t["mu"].unit = "electron"
    t.meta["template_charge"] = template.charge
    t.meta["n_images"] = n
    t.meta["shape"] = [ny, nx]
    t.meta["step"] = float(step)
    return t


def simulate_ptc_levels(template, levels, *, steps_per_level=40, n_images=1024, shape=(16, 16),
                        max_lag=3, seed=None, progress=False):
    """Independent flat stacks, one per signal level, for a PTC fit.

    :func:`simulate_flats` fills one stack, so its covariances at different
    signals are strongly correlated; a least-squares fit that treats them as
    independent would understate its errors. Here each level is a new stack
    (its own random stream) filled in ``steps_per_level`` equal steps, and
    only its last row is kept, so the levels are statistically independent.

    ``cov`` is the per-pair estimator of :func:`simulate_flats` with its
    mean-subtraction bias removed: subtracting each difference image's mean
    lowers every lag by Var(sum of the image) / N_pix^2 per pixel pair, and
    in a periodic stack whose areas sum to N_pix the summed charge is exactly
    Poisson, so the bias is exactly -mu / N_pix at every lag (added back).

    Filling in n discrete steps (areas updated between steps) gives, to first
    order, C_ij = a_ij mu^2 (1 - 1/n) instead of the continuous a_ij mu^2:
    the charge of step k sees the boundaries of steps < k only. Divide fitted
    a_ij by ``1 - 1/steps_per_level`` (column ``step_factor``) to compare
    with a continuous exposure.

    Parameters
    ----------
    template : DistortionTemplate
        Green's function.
    levels : array_like
        Target mean signals (e per pixel).
    steps_per_level : int, optional
        Fill steps of each stack (step = level / steps_per_level).
    n_images, shape, max_lag : optional
        As in :func:`simulate_flats`.
    seed : int, optional
        Seed of the generator from which each level's stream is spawned.
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    astropy.table.Table
        One row per level: ``mu`` (e), ``cov`` and ``cov_err`` (per-pair
        estimator without its mean-subtraction bias, e^2, [di, dj]), ``paper``
        (C_ij / mu, all pairs),
        ``area_min``, ``area_max``; meta ``step_factor`` = 1 - 1/n.
    """
    levels = np.asarray(levels, dtype=float).ravel()
    if levels.size < 1 or not np.all(np.isfinite(levels) & (levels > 0)):
        raise ValueError("levels must be positive and finite")
    if int(steps_per_level) != steps_per_level or steps_per_level < 2:
        raise ValueError(f"steps_per_level must be an integer >= 2, got {steps_per_level!r}")
    n = int(steps_per_level)
    streams = np.random.SeedSequence(seed).spawn(levels.size)
    rows = []
    with ProgressBar(levels.size, "ptc-levels", enabled=progress) as bar:
        for lev, ss in zip(levels, streams):
            t = simulate_flats(template, n_images=n_images, shape=shape, step=lev / n,
                               n_steps=n, max_lag=max_lag, rng=np.random.default_rng(ss))
            last = t[-1]
            unbiased = last["pairs"] + last["mu"] / (shape[0] * shape[1])
            rows.append((last["mu"], unbiased, last["pairs_err"], last["paper"],
                         last["area_min"], last["area_max"]))
            bar(1)
    out = Table(rows=rows, names=("mu", "cov", "cov_err", "paper", "area_min", "area_max"))
    out["mu"].unit = "electron"
    out.meta.update(template_charge=template.charge, n_images=int(n_images),
                    shape=[int(v) for v in shape], steps_per_level=n,
                    step_factor=1.0 - 1.0 / n)
    return out
