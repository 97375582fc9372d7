"""Synthetic flats: one module, two products.

:func:`simulate_flat_pairs` is the one generator of flat *pairs* (the input
of a PTC, a calibration or a diagnosis): levels of paired flats with the
linearised area model of a template's a_ij or with GalSim's own pixel areas
(``engine``), and effects the base model lacks injected on request
(``inject``, :data:`INJECTABLE`); :func:`write_flat_pairs` writes them as
FITS files with ``EXPTIME``. :func:`simulate_flats` is the paper's
experiment (section 4.3) with exact moving boundaries, which reports the
covariance estimators themselves as the stack fills:

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

import os

import numpy as np
from astropy.io import fits
from astropy.table import Table
from scipy import fft as sp_fft
from scipy.ndimage import convolve1d
from scipy.special import erf

from lsst_bfdrift.simulation.effects import ChargeCloud, full_lags
from lsst_bfdrift.templates.refine import template_alpha
from lsst_bfdrift.utils.io import atomic_output
from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.utils.errors import InputError

__all__ = ["simulate_flat_pairs", "write_flat_pairs", "apply_readout_effects", "INJECTABLE",
           "READOUT_EFFECTS", "GALSIM_AREA_BAND", "PeriodicAreas", "engine_acoeffs",
           "simulate_flats", "simulate_ptc_levels", "template_area_coefficients",
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
            raise InputError(f"periodic images need at least 2 x 2 pixels, got {shape}")
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
        raise InputError(f"responsivity must be negative and finite, got {dlna00_per_e!r}")
    c = template.center
    own = np.log(template.moments().area[c, c])
    if not own < 0:
        raise InputError("template's central pixel does not shrink; no responsivity to rescale")
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
        raise InputError(f"max_lag must be in [0, {c}] for this template, got {max_lag!r}")
    q = template.charge
    full = template.moments(charge=q).area

    def quad(arr):  # [dj + c, di + c] -> [di, dj]
        return np.ascontiguousarray(arr[c:c + L + 1, c:c + L + 1].T)
    return {"alpha": quad(template_alpha(template)), "linear": quad(full - 1.0) / q,
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
        raise InputError(f"n_images must be an even integer >= 4, got {n_images!r}")
    if not (np.isfinite(step) and step > 0):
        raise InputError(f"step must be positive, got {step!r}")
    if int(n_steps) != n_steps or n_steps < 1:
        raise InputError(f"n_steps must be a positive integer, got {n_steps!r}")
    rng = np.random.default_rng(seed) if rng is None else rng
    geo = PeriodicAreas(template, shape)
    ny, nx = geo.shape
    n = int(n_images)
    npix = ny * nx
    if max_lag >= min(ny, nx) // 2:
        raise InputError(f"max_lag {max_lag} too large for {ny} x {nx} periodic images")
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
        raise InputError("levels must be positive and finite")
    if int(steps_per_level) != steps_per_level or steps_per_level < 2:
        raise InputError(f"steps_per_level must be an integer >= 2, got {steps_per_level!r}")
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


# -- flat pairs with injected effects -----------------------------------------



#: Names accepted by :func:`simulate_flat_pairs`.
INJECTABLE = ("charge_cloud", "well_filling", "diffusion", "gain_nonlinearity", "static_area",
              "cti_serial", "cti_parallel", "echo")


def _kernel_fft(q, shape):
    """FFT of the signed-lag kernel from quadrant q, placed circularly."""
    f = full_lags(q)
    L = q.shape[0] - 1
    k = np.zeros(shape)
    for di in range(-L, L + 1):
        for dj in range(-L, L + 1):
            k[dj % shape[0], di % shape[1]] += f[L + di, L + dj]  # image [y, x] = [j, i]
    return sp_fft.rfft2(k)


def _diffusion_weights(sigma):
    """3 x 3 pixel-integrated Gaussian of rms ``sigma`` (px), renormalised."""
    edges = np.arange(-1.5, 2.0, 1.0)
    cdf = 0.5 * (1 + erf(edges / (np.sqrt(2) * sigma)))
    p1 = np.diff(cdf)
    p1 /= p1.sum()
    return np.outer(p1, p1)


def _static_pattern(shape, var, length, rng):
    white = rng.standard_normal(shape)
    ky = sp_fft.fftfreq(shape[0])[:, None]
    kx = sp_fft.rfftfreq(shape[1])[None, :]
    sk = length / np.sqrt(2.0)  # smoothing sigma: autocorrelation exp(-r^2 / (2 length^2))
    g = np.exp(-2 * np.pi**2 * sk**2 * (kx**2 + ky**2))
    d = sp_fft.irfft2(sp_fft.rfft2(white) * g, shape)
    return d * np.sqrt(var) / d.std()


def simulate_flat_pairs(model, levels, *, engine="linear", shape=(256, 256), n_steps=40,
                        gain=1.0, inject=None, depth_derivative=None, seed=0, progress=None):
    """Flat pairs at the given signal levels, with optional injected effects.

    Every flat is filled in ``n_steps`` steps; each step adds Poisson(step x
    area) electrons to every pixel, the areas set by the charge collected so
    far:

    * ``engine='linear'``: the linearised area model of the electrostatic
      template, area = 1 + sum_q a(p - q) Q_q (circular convolution by FFT;
      the same physics as moving boundaries to first order), divided by its
      mean: a kernel truncated at lag L does not sum to zero, and the pixels
      must keep the total charge (otherwise the mean signal would depend on
      the charge as a gain non-linearity does);
    * ``engine='galsim'``: GalSim's own pixel areas,
      ``galsim.SiliconSensor(model).calculate_pixel_areas`` of the current
      charge image (an independent simulator's BF; about 0.25 s a step for
      400 x 400 pixels on 2 cores), divided by their mean over the interior
      (:data:`GALSIM_AREA_BAND` px from the edges). GalSim's polygon areas
      shrink to second order in the charge even under uniform charge, where
      every pixel must keep its area (lsst_e2v_50_8: by 4.9e-4 at 80 ke,
      which would make the mean signal non-linear in exposure by 2e-4);
      photon shooting keeps every photon, and so does this engine. The
      edges keep GalSim's open-boundary loss relative to the interior.
      ``charge_cloud`` ``(var_serial, var_parallel)`` (px^2) computes the
      areas from the charge image convolved with the cloud;
      ``well_filling`` ``(beta,)`` (per e) makes each pixel's pull on its
      neighbours' boundaries grow with its own charge: GalSim sees the charge
      Q (1 + beta Q / 2), so a_ij(Q) = a_ij (1 + beta Q). This is the
      library's :class:`~lsst_bfdrift.simulation.effects.WellFilling` with
      GalSim's a_ij in place of d a_ij / d ln(channel depth), which GalSim
      cannot give (in the shipped basis the two agree within 8 % at lags
      <= 1).

    Discrete filling gives covariances C_ij = a_ij mu^2 (1 - 1/n_steps) to
    first order (the charge of a step sees only the boundaries of the
    earlier steps); divide a_ij fitted to these flats by ``1 - 1/n_steps``
    to compare with a continuous exposure (as :func:`simulate_ptc_levels`'
    ``step_factor``).

    Parameters
    ----------
    model : array_like or str
        'linear': area coefficients a[i, j] (per e), [serial, parallel],
        shape (L + 1, L + 1). 'galsim': a GalSim sensor name (e.g.
        ``lsst_itl_50_8``) or path prefix.
    engine : {'linear', 'galsim'}, optional
        How the areas are computed (above).
    levels : sequence of float
        Mean signals (e) of the pairs.
    shape : tuple of int, optional
        Image shape (ny, nx) = (parallel, serial).
    n_steps : int, optional
        Accumulation steps per flat.
    gain : float, optional
        e/ADU of the output.
    inject : dict, optional
        ``{name: parameters}`` with names from :data:`INJECTABLE`.
    depth_derivative : array_like, optional
        D_ij = d a_ij / d ln(channel depth), needed for ``well_filling``.
    seed : int, optional
        Random seed.
    progress : callable, optional
        Called as ``progress(done, total)`` after each pair.

    Returns
    -------
    list of (ndarray, ndarray)
        Flat pairs in ADU, float64, indexed [y, x].
    """
    inject = dict(inject or {})
    bad = [k for k in inject if k not in INJECTABLE]
    if bad:
        raise InputError(f"cannot inject {bad}; known: {list(INJECTABLE)}")
    levels = np.atleast_1d(np.asarray(levels, dtype=float))
    if levels.size == 0 or not np.all(np.isfinite(levels)) or np.any(levels <= 0):
        raise InputError(f"levels must be positive signals (e), got {levels.tolist()!r}")
    shape = tuple(int(v) for v in shape)
    rng = np.random.default_rng(seed)
    if engine == "galsim":
        beta = inject.get("well_filling", (0.0,))[0]
        areas_of = _galsim_areas(model, shape, charge_cloud=inject.get("charge_cloud"),
                                 well_filling=float(beta))
    elif engine == "linear":
        a = np.asarray(model, dtype=float)
        if a.ndim != 2 or a.shape[0] != a.shape[1]:
            raise InputError(f"engine 'linear' needs a square a_ij array, got shape {a.shape}")
        if "charge_cloud" in inject:
            a = ChargeCloud().apply_a(a, inject["charge_cloud"], None)
        ka = _kernel_fft(a, shape)
        kd = None
        if "well_filling" in inject:
            if depth_derivative is None:
                raise InputError("well_filling needs depth_derivative")
            kd = _kernel_fft(np.asarray(depth_derivative, float) * 0.5
                             * inject["well_filling"][0], shape)

        def areas_of(q):
            area = 1.0 + sp_fft.irfft2(sp_fft.rfft2(q) * ka, shape)
            if kd is not None:
                area += sp_fft.irfft2(sp_fft.rfft2(q * q) * kd, shape)
            # a kernel truncated at lag L does not sum to zero: keep the total
            return area / area.mean()
    else:
        raise InputError(f"engine must be 'linear' or 'galsim', got {engine!r}")
    static = 0.0
    if "static_area" in inject:
        static = _static_pattern(shape, *inject["static_area"], np.random.default_rng(seed + 1))
    pairs = []
    for level in levels:
        pair = []
        for _ in range(2):
            q = np.zeros(shape)
            step = float(level) / n_steps
            for _s in range(n_steps):
                area = areas_of(q) * (1.0 + static)
                lam = step * np.clip(area, 0, None)
                if "diffusion" in inject:
                    # each electron moves independently: splitting Poisson(lam) over
                    # destinations gives independent Poisson(lam p_k) (thinning)
                    w = _diffusion_weights(inject["diffusion"][0])
                    for dy in (-1, 0, 1):
                        for dx in (-1, 0, 1):
                            q += np.roll(rng.poisson(lam * w[dy + 1, dx + 1]), (dy, dx),
                                         axis=(0, 1))
                else:
                    q += rng.poisson(lam)
            pair.append(apply_readout_effects(q, inject, gain=gain))
        pairs.append(tuple(pair))
        if progress is not None:
            progress(len(pairs), len(levels))
    return pairs


#: Pixels at each edge that :func:`simulate_flat_pairs` (engine 'galsim')
#: leaves out when it sets the mean area of the interior to 1.
GALSIM_AREA_BAND = 10


#: The effects :func:`apply_readout_effects` applies: they act on the collected
#: charge image after the exposure, not on how it fills.
READOUT_EFFECTS = ("cti_serial", "cti_parallel", "echo", "gain_nonlinearity")


def apply_readout_effects(charge, inject, *, gain=1.0):
    """The read-out of a collected charge image, with the effects that act after
    the exposure.

    Parameters
    ----------
    charge : array_like, 2-d
        Collected electrons, indexed [y, x] (y parallel).
    inject : dict
        ``{name: parameters}``; the names of :data:`READOUT_EFFECTS` act
        (others are ignored): CTI ``(eps,)`` on either axis (a fraction eps
        of each pixel's charge read with the previous pixel's), ``echo``
        ``(kappa, lag)`` (kappa times the charge ``lag`` serial pixels
        earlier added), ``gain_nonlinearity`` ``(nu,)`` (s -> s (1 + nu s),
        nu per ADU).
    gain : float, optional
        e/ADU.

    Returns
    -------
    ndarray
        The image in ADU, float64 (a new array; ``charge`` is not changed).
    """
    q = np.asarray(charge, dtype=float)
    out = q.copy()
    for name, axis in (("cti_serial", 1), ("cti_parallel", 0)):
        if name in inject:
            eps = inject[name][0]
            out = (1 - eps) * out + eps * np.roll(q, 1, axis=axis)
    if "echo" in inject:
        kappa, lag = inject["echo"]
        out = out + kappa * np.roll(q, int(lag), axis=1)
    s = out / gain
    if "gain_nonlinearity" in inject:
        s = s * (1 + inject["gain_nonlinearity"][0] * s)
    return s


def engine_acoeffs(model, inject=None, *, max_lag=3, charge=1e4):
    """The a-matrix that flats of :func:`simulate_flat_pairs` carry, noise-free (1/e).

    What their covariances measure, C_ij = a_ij mu^2 (1 - 1/n_steps) to
    first order, for the fill injections that reshape it: the truth against
    which a fit to such flats is judged.

    * No injection: ``model`` itself (engine 'linear') or GalSim's areas
      around one charged pixel (engine 'galsim': ``charge`` and
      ``charge / 2``; the areas are quadratic in the charge, so
      (4 (A(Q/2) - 1) - (A(Q) - 1)) / Q is the slope at zero charge).
    * ``charge_cloud``: the aggressor's charge spread by the cloud (GalSim:
      the engine's 3-tap kernel before the areas; linear: the library's
      :class:`~lsst_bfdrift.simulation.effects.ChargeCloud`, as the engine
      applies it).
    * ``diffusion`` (rms px): electrons are moved after the areas set where
      they land, each independently, so the flat's noise stays white (a
      thinned Poisson process) while the area response is smoothed once,
      a_eff = w * a with w the engine's 3 x 3 pixel-integrated Gaussian (to
      first order in a the power spectrum grows as dP/dt = 2 r W A P + r).
    * ``well_filling``: a_ij at zero charge, unchanged (they grow as
      a_ij (1 + beta Q)). Read-out effects and ``static_area`` leave the
      a-matrix unchanged.

    Parameters
    ----------
    model : str or array_like
        A GalSim sensor name (engine 'galsim') or a[i, j] (engine 'linear').
    inject : dict, optional
        ``{name: parameters}`` as for :func:`simulate_flat_pairs`.
    max_lag : int, optional
        Largest lag.
    charge : float, optional
        Aggressor charge (e) of the GalSim evaluation.

    Returns
    -------
    ndarray, shape (max_lag + 1, max_lag + 1)
        a[i, j], i serial, j parallel.
    """
    inject = dict(inject or {})
    bad = [k for k in inject if k not in INJECTABLE]
    if bad:
        raise InputError(f"cannot inject {bad}; known: {list(INJECTABLE)}")
    L = int(max_lag)
    n = 2 * L + 2 * GALSIM_AREA_BAND + 21
    c = n // 2
    if isinstance(model, str):
        areas_of = _galsim_areas(model, (n, n), charge_cloud=inject.get("charge_cloud"))
        d = []
        for q0 in (charge, charge / 2):
            q = np.zeros((n, n))
            q[c, c] = q0
            d.append(areas_of(q) - 1.0)
        alpha = (4 * d[1] - d[0]) / charge  # [y, x]
    else:
        a = np.asarray(model, dtype=float)
        if a.ndim != 2 or a.shape[0] != a.shape[1]:
            raise InputError(f"model must be a square a_ij array or a sensor name, "
                             f"got shape {a.shape}")
        if "charge_cloud" in inject:
            a = ChargeCloud().apply_a(a, inject["charge_cloud"], None)
        f = full_lags(a).T  # [dj, di] = [y, x], centred
        m = a.shape[0] - 1
        alpha = np.zeros((n, n))
        k = min(m, c)
        alpha[c - k:c + k + 1, c - k:c + k + 1] = f[m - k:m + k + 1, m - k:m + k + 1]
    if "diffusion" in inject:
        w = _diffusion_weights(float(inject["diffusion"][0]))
        alpha = sum(w[dy + 1, dx + 1] * np.roll(alpha, (dy, dx), axis=(0, 1))
                    for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    return alpha[c:c + L + 1, c:c + L + 1].T.copy()


def _galsim_areas(sensor, shape, *, charge_cloud=None, well_filling=0.0):
    """areas_of(q): GalSim's pixel areas for the charge image q (e).

    ``well_filling`` beta (per e): the boundaries see the charge
    q (1 + beta q / 2), so the area coefficients grow as a_ij (1 + beta Q).

    ``charge_cloud`` ``(var_serial, var_parallel)`` (px^2): each pixel's
    collected charge is a cloud with these variances, so the boundaries see
    the charge image convolved with it. The cloud is the 3-tap kernel
    (v/2, 1 - v, v/2) on each axis: exactly variance v on the pixel grid
    (a sampled Gaussian under-represents a variance below a pixel), which is
    what :class:`~lsst_bfdrift.simulation.effects.ChargeCloud` models to
    second order.
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    blur = None
    if charge_cloud is not None:
        vs, vp = (float(v) for v in charge_cloud)
        if not (0 <= vs <= 1 and 0 <= vp <= 1):
            raise InputError(f"charge_cloud variances must be in [0, 1] px^2, got {(vs, vp)}")
        blur = [(axis, np.array([v / 2, 1 - v, v / 2])) for axis, v in ((1, vs), (0, vp))]
    if not np.isfinite(well_filling) or abs(well_filling) > 1e-4:
        raise InputError(f"well_filling beta must be finite and within +-1e-4 per e, "
                         f"got {well_filling}")

    try:
        sim = galsim.SiliconSensor(str(sensor), diffusion_factor=0.0)
    except OSError as exc:
        raise InputError(f"engine 'galsim': no GalSim sensor {sensor!r} ({exc})") from None
    ny, nx = shape

    by, bx = min(GALSIM_AREA_BAND, ny // 4), min(GALSIM_AREA_BAND, nx // 4)
    band = np.s_[by:ny - by, bx:nx - bx]

    def areas_of(q):
        if well_filling:
            q = np.asarray(q, float)
            q = q * (1.0 + 0.5 * well_filling * q)
        if blur is not None:
            for axis, w in blur:
                q = convolve1d(np.asarray(q, float), w, axis=axis, mode="nearest")
        img = galsim.ImageD(np.ascontiguousarray(q, dtype=np.float64), scale=1.0)
        area = sim.calculate_pixel_areas(img, use_flux=True).array
        # GalSim's polygon areas lose area to second order in the charge even
        # where the charge is uniform (lsst_e2v_50_8: 4.9e-4 of a pixel at 80 ke,
        # where symmetry demands none); photon shooting puts every photon in some
        # pixel, so the interior's total is kept and the edges keep their own
        return area / area[band].mean()
    return areas_of


def write_flat_pairs(pairs, levels, directory, *, exptime_per_e=1e-4, gain=1.0, prefix="flat",
                     overwrite=False):
    """Write flat pairs as FITS files a PTC reader takes as lab data.

    Each flat gets ``EXPTIME`` = level x ``exptime_per_e`` (s), ``GAIN``
    (e/ADU) and ``BUNIT = 'adu'``; files are ``{prefix}_{k:03d}_{a|b}.fits``,
    written atomically.

    Parameters
    ----------
    pairs : sequence of (ndarray, ndarray)
        Flats in ADU (e.g. from :func:`simulate_flat_pairs`).
    levels : sequence of float
        Mean signal (e) of each pair.
    directory : str or os.PathLike
        Existing directory.
    exptime_per_e, gain : float, optional
        Exposure time per electron of signal (s), and e/ADU.
    prefix : str, optional
        File name prefix.
    overwrite : bool, optional
        Replace existing files.

    Returns
    -------
    list of str
        The paths written.
    """
    if len(pairs) != len(levels):
        raise InputError(f"{len(pairs)} pairs but {len(levels)} levels")
    paths = []
    for k, ((f1, f2), level) in enumerate(zip(pairs, levels)):
        for tag, img in (("a", f1), ("b", f2)):
            path = os.path.join(os.fspath(directory), f"{prefix}_{k:03d}_{tag}.fits")
            hdr = fits.Header()
            hdr["EXPTIME"] = (float(level) * exptime_per_e, "s")
            hdr["GAIN"] = (float(gain), "e/ADU")
            hdr["BUNIT"] = "adu"
            with atomic_output(path, overwrite=overwrite) as tmp:
                fits.PrimaryHDU(np.asarray(img, dtype=np.float32), header=hdr).writeto(tmp)
            paths.append(path)
    return paths
