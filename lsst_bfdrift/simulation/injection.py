"""Fast flat pairs with injected effects, for testing the diagnosis.

:func:`simulate_flat_pairs` fills periodic images in steps like
:func:`~lsst_bfdrift.simulation.flats.simulate_flats`, with the linearised area
model of the electrostatic template: the area of pixel p is
1 + sum_q a(p - q) Q_q (a_ij per e, signed lags up to L, circular
convolution by FFT), which is the same physics as moving boundaries to first
order in the displacements. Each step adds Poisson(step x area) electrons.

Effects that the fit is not told about can be injected (names from
:data:`~lsst_bfdrift.simulation.effects.EFFECT_NAMES` plus ``echo`` outside the
library):

``charge_cloud`` (var_serial, var_parallel)
    the kernel a is replaced by the cloud-averaged kernel.
``well_filling`` (beta,)
    area term (beta / 2) sum_q D(p - q) Q_q^2, so that d area / dQ =
    a + beta Q D (D = d a / d ln channel depth).
``diffusion`` (sigma_d,)
    every step's new electrons are moved to neighbouring pixels independently
    (3 x 3 pixel-integrated Gaussian of rms sigma_d; drawn as independent
    Poisson numbers per destination, which is the same distribution).
``gain_nonlinearity`` (nu,)
    read-out signal S = s (1 + nu s).
``static_area`` (var_area, length)
    a fixed Gaussian-correlated pattern delta multiplies the areas in every
    flat (same pattern in both flats of a pair).
``cti_serial``, ``cti_parallel`` (eps,)
    read-out deferral out_k = (1 - eps) N_k + eps N_{k-1}.
``echo`` (kappa, lag)
    an electronic echo out_x += kappa N_{x - lag} along the serial axis:
    a pattern nothing in the library produces.
"""

import numpy as np
from scipy import fft as sp_fft

from lsst_bfdrift.simulation.effects import ChargeCloud, full_lags

__all__ = ["simulate_flat_pairs", "INJECTABLE"]

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
    from scipy.special import erf

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


def simulate_flat_pairs(a, levels, *, shape=(256, 256), n_steps=40, gain=1.0, inject=None,
                        depth_derivative=None, seed=0):
    """Flat pairs at the given signal levels, with optional injected effects.

    Parameters
    ----------
    a : array_like, shape (L + 1, L + 1)
        Area coefficients a[i, j] (per e), [serial, parallel].
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

    Returns
    -------
    list of (ndarray, ndarray)
        Flat pairs in ADU, float64, indexed [y, x].
    """
    inject = dict(inject or {})
    bad = [k for k in inject if k not in INJECTABLE]
    if bad:
        raise ValueError(f"cannot inject {bad}; known: {list(INJECTABLE)}")
    a = np.asarray(a, dtype=float)
    if "charge_cloud" in inject:
        a = ChargeCloud().apply_a(a, inject["charge_cloud"], None)
    rng = np.random.default_rng(seed)
    ka = _kernel_fft(a, shape)
    kd = None
    if "well_filling" in inject:
        if depth_derivative is None:
            raise ValueError("well_filling needs depth_derivative")
        kd = _kernel_fft(np.asarray(depth_derivative, float) * 0.5 * inject["well_filling"][0],
                         shape)
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
                area = 1.0 + sp_fft.irfft2(sp_fft.rfft2(q) * ka, shape)
                if kd is not None:
                    area += sp_fft.irfft2(sp_fft.rfft2(q * q) * kd, shape)
                area *= 1.0 + static
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
            out = q.copy()
            for name, axis in (("cti_serial", 1), ("cti_parallel", 0)):
                if name in inject:
                    eps = inject[name][0]
                    prev = np.roll(q, 1, axis=axis)
                    out = (1 - eps) * out + eps * prev
            if "echo" in inject:
                kappa, lag = inject["echo"]
                out = out + kappa * np.roll(q, int(lag), axis=1)
            s = out / gain
            if "gain_nonlinearity" in inject:
                s = s * (1 + inject["gain_nonlinearity"][0] * s)
            pair.append(s)
        pairs.append(tuple(pair))
    return pairs
