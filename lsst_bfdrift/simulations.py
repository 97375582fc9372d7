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

from .progress import ProgressBar

__all__ = ["PeriodicAreas", "simulate_flats"]


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
