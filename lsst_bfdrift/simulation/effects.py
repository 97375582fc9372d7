"""Library of effects the base electrostatic model lacks.

Each effect is a physical model term with its own parameters (bounds and
typical scales) and a forward model of how it changes the predicted
observables. Three kinds of input are distinguished (see
:mod:`lsst_bfdrift.diagnosis.effects_fit`):

``table``
    A table of area coefficients a_ij (one signal level, unknown).
``ptc``
    A photon transfer curve: mean and variance (C00) against signal.
``flats``
    Flat pairs: difference-image covariances C_ij(mu) at every lag and the
    static statistic S_ij(mu) = (Cov(f1 + f2) - Cov(f1 - f2)) / 4, which is
    zero for signal-driven (dynamic) correlations and mu^2 times the
    autocovariance of any static pixel-response pattern.

Vocabulary (the names used in reports and JSON): ``charge_cloud``,
``well_filling``, ``diffusion``, ``gain_nonlinearity``, ``static_area``,
``cti_serial``, ``cti_parallel``. :data:`EFFECT_NAMES` lists them and
:func:`effect_library` builds one instance of each.

Which input identifies which effect is stated by :meth:`Effect.identifiable`;
the diagnosis only tries identifiable ones and reports the others with the
reason.

Observables
-----------
Each effect also states which observables of a flat set it moves (the
class attribute ``observables``, names from :data:`OBSERVABLES`); the
diagnosis (:mod:`lsst_bfdrift.diagnosis.findings`) uses it to say which
effect could produce a finding, and never credits the base BF model with
one it cannot produce:

``covariances``
    C_ij(mu) of difference images at every lag.
``pair_sums``
    S_ij(mu) of pair sums (static structure).
``edges``
    Signal of the pixel rings at the image edges against the interior.
``linearity``
    Mean signal against exposure time (EXPTIME).
``sum_rule``
    Sum of C_ij over all lags (multiplicity 4/2/1 off-axis/axis/zero) against
    mu / gain: the a-matrix sums to zero because BF moves pixel boundaries
    and conserves the total area.
``halves``
    Means and covariances of the two halves of the image (left/right,
    bottom/top), standing in for amplifiers.
``pair_ratio``
    Mean of the second flat of a pair over the first's.
``turnoff``
    The level at which a pair's variance drops (saturation).

The base BF model (electrostatic a_ij, gain, read noise) moves only
``covariances``: it obeys the sum rule, is linear in exposure time, the same
in both halves and in both flats of a pair, and has no turn-off.
"""

import numpy as np
from lsst_bfdrift.utils.errors import InputError

__all__ = ["Effect", "ChargeCloud", "WellFilling", "Diffusion", "GainNonlinearity",
           "StaticArea", "CTI", "EFFECT_NAMES", "OBSERVABLES", "BASE_OBSERVABLES",
           "effect_library", "full_lags", "quadrant", "cti_filter_covariance"]

#: The documented vocabulary, in library order.
EFFECT_NAMES = ("charge_cloud", "well_filling", "diffusion", "gain_nonlinearity",
                "static_area", "cti_serial", "cti_parallel")

#: Observables of a flat set (module documentation), the vocabulary of
#: :attr:`Effect.observables`.
OBSERVABLES = ("covariances", "pair_sums", "edges", "linearity", "sum_rule", "halves",
               "pair_ratio", "turnoff")

#: The observables the base BF model moves.
BASE_OBSERVABLES = ("covariances",)


def full_lags(q):
    """Extend a quadrant array q[i, j] (i, j >= 0) to signed lags, shape (2L+1, 2L+1).

    Element ``[L + i, L + j]`` of the result is ``q[abs(i), abs(j)]``.
    """
    q = np.asarray(q, dtype=float)
    rows = np.concatenate([q[::-1][:-1], q], axis=0)
    return np.concatenate([rows[:, ::-1][:, :-1], rows], axis=1)


def quadrant(f):
    """The quadrant i, j >= 0 of a signed-lag array (inverse of :func:`full_lags`)."""
    L = (f.shape[0] - 1) // 2
    return f[L:, L:]


class Effect:
    """Base class: an effect with parameters and a forward model.

    Attributes
    ----------
    name : str
        Name from :data:`EFFECT_NAMES`.
    param_names : tuple of str
    bounds : tuple of (float, float)
    start : tuple of float
        Starting values (usually 'no effect').
    scale : tuple of float
        Typical magnitudes (optimiser scaling).
    units : tuple of str
    signature : str
        The residual signature it explains (one sentence).
    observables : tuple of str
        The observables of a flat set it moves (names from :data:`OBSERVABLES`).
    """

    name = ""
    observables = ()
    param_names = ()
    bounds = ()
    start = ()
    scale = ()
    units = ()
    signature = ""
    _identifiable = {}

    def identifiable(self, kind):
        """(bool, reason) for input kind 'table', 'ptc' or 'flats'."""
        return self._identifiable[kind]

    # Forward-model hooks (identity by default).
    def apply_a(self, a, theta, basis):
        """Modified a_ij quadrant (per e)."""
        return a

    def b_term(self, a, theta, basis):
        """Astier b_ij contribution (per e) or None."""
        return None

    def apply_cov(self, cov, theta):
        """Modified covariances, array (n, L+1, L+1) (ADU^2)."""
        return cov

    def measured_signal(self, mu_obs, theta):
        """(linear signal, covariance factor) for observed means (ADU)."""
        return mu_obs, 1.0

    def static(self, mu, L, theta):
        """Contribution to S_ij(mu), shape (n, L+1, L+1) (ADU^2), or None."""
        return None

    def describe(self, theta):
        """'name(p1=v1, ...)' text."""
        return self.name + "(" + ", ".join(f"{n}={v:.4g}" for n, v in
                                           zip(self.param_names, theta)) + ")"


class ChargeCloud(Effect):
    """Finite extent of the collected charge cloud.

    The base model puts the aggressor's collected charge at one point. A cloud
    with rms extents sigma_s (serial) and sigma_p (parallel) in the channel
    acts as the average of point charges displaced by the cloud's density;
    to second order in sigma (sigma well below a pixel) the pattern becomes
    a_ij + sigma_s^2 / 2 d2a/di2 + sigma_p^2 / 2 d2a/dj2, with the second
    derivatives taken as discrete differences over signed lags (the area sum
    is unchanged). Parameters: the variances ``var_serial``, ``var_parallel``
    (px^2).

    Signature: the nearest neighbours lose (they take a fraction of the deep
    negative a00), lag 2 gains; different variances change the anisotropy
    a01/a10 while the far field (r >= 3) is unchanged. Constant in signal.
    """

    name = "charge_cloud"
    #: the area sum is unchanged: the sum rule holds
    observables = ("covariances",)
    param_names = ("var_serial", "var_parallel")
    bounds = ((0.0, 0.5), (0.0, 0.5))
    start = (0.0, 0.0)
    scale = (0.05, 0.05)
    units = ("px^2", "px^2")
    signature = ("near-lag pattern reshaped (nearest neighbours reduced, lag 2 raised), "
                 "anisotropy changed, far field unchanged, constant in signal")
    _identifiable = {
        "table": (True, "changes the spatial pattern of a_ij at lags <= 2"),
        "flats": (True, "changes the spatial pattern of the a_ij slopes"),
        "ptc": (False, "a PTC sees a00 only, which the fit takes as free"),
    }

    def apply_a(self, a, theta, basis):
        vs, vp = theta
        f = full_lags(a)
        pad = np.pad(f, 1)
        d2i = pad[2:, 1:-1] + pad[:-2, 1:-1] - 2 * f
        d2j = pad[1:-1, 2:] + pad[1:-1, :-2] - 2 * f
        return quadrant(f + 0.5 * vs * d2i + 0.5 * vp * d2j)


class WellFilling(Effect):
    """Channel depth changing with the collected charge (well filling).

    As a pixel fills, its charge spreads away from the gates, so the
    effective depth of the collected-charge dipole grows: d_ch(Q) =
    d_ch (1 + beta Q). The pattern then changes with signal as
    a_ij(Q) = a_ij + beta Q D_ij with D_ij = d a_ij / d ln d_ch taken from the
    electrostatic model (the fit's Jacobian). In the covariance model this is
    Astier's b term with a_ij b_ij = beta D_ij. Parameter: ``beta`` (per e).

    Signature: C_ij / mu curves upward (or downward) in mu with the shape of
    D_ij (strongest on the nearest neighbours).
    """

    name = "well_filling"
    #: sum of D_ij over all lags = d(sum of a_ij) / d ln d_ch = 0: the sum rule holds
    observables = ("covariances",)
    param_names = ("beta",)
    bounds = ((-1e-4, 1e-4),)
    start = (0.0,)
    scale = (1e-6,)
    units = ("1/e",)
    signature = "curvature of C_ij/mu in mu with the shape of d a_ij / d ln(channel depth)"
    _identifiable = {
        "table": (False, "one signal level: indistinguishable from the channel depth"),
        "flats": (True, "C_ij/mu curvature at every lag"),
        "ptc": (True, "partly: third-order C00 shape, close to gain_nonlinearity"),
    }

    def b_term(self, a, theta, basis):
        d = basis.dlog_depth(a.shape[0] - 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            b = np.where(np.abs(a) > 1e-14, theta[0] * d / a, 0.0)
        return b


class Diffusion(Effect):
    """Lateral diffusion of the drifting charge (rms ``sigma_d``, px).

    An electron converted at x lands where the drift line from x + e ends, e
    Gaussian. The expected count of a pixel in a uniform flat is the
    integral of its landing probability over x, which is its area whatever
    the diffusion: diffusion of independent electrons keeps a uniform flat
    Poisson and leaves every a_ij unchanged (checked by
    ``tests/diagnosis/test_effects_fit.py`` on simulated flats). Its signature is
    therefore zero in flat-field statistics; it shows in stars and spots
    (PSF width), not here. It stays in the library so that the diagnosis can
    say so.
    """

    name = "diffusion"
    observables = ()
    param_names = ("sigma_d",)
    bounds = ((0.0, 1.0),)
    start = (0.0,)
    scale = (0.1,)
    units = ("px",)
    signature = "none in flat-field statistics (uniform flats stay Poisson)"
    _identifiable = {k: (False, "diffusion leaves flat-field statistics unchanged "
                                "(uniform flats stay Poisson); it needs stars or spots")
                     for k in ("table", "flats", "ptc")}


class GainNonlinearity(Effect):
    """Quadratic non-linearity of the signal chain.

    Measured signal S = s (1 + nu s) for a linear signal s (ADU). The mean
    becomes M = mu (1 + nu mu) and all covariances are multiplied by
    (1 + 2 nu mu)^2. Parameter ``nu`` (per ADU).

    Signature: every C_ij (and C00 above all) grows relative to mu by the same
    mu-dependent factor; at lag 0 this bends the PTC beyond what a00 from the
    area sum rule allows.
    """

    name = "gain_nonlinearity"
    #: the mean bends against exposure time, and the covariances summed over
    #: lags over the mean grow as (1 + 2 nu mu)^2 / (1 + nu mu) ~ 1 + 3 nu mu
    #: (the sum rule breaks)
    observables = ("covariances", "sum_rule", "linearity")
    param_names = ("nu",)
    bounds = ((-5e-6, 5e-6),)
    start = (0.0,)
    scale = (1e-7,)
    units = ("1/ADU",)
    signature = "all covariances scaled by (1 + 2 nu mu)^2; extra C00 curvature"
    _identifiable = {
        "table": (False, "an a_ij table is fitted assuming linearity; the bend is in a00, "
                         "which the table's sum rule sets"),
        "flats": (True, "C00 curvature beyond a00 and common scaling of all lags"),
        "ptc": (True, "partly: third-order C00 shape, degenerate with a00 at second order"),
    }

    def measured_signal(self, mu_obs, theta):
        nu = theta[0]
        mu_obs = np.asarray(mu_obs, float)
        # stable root of nu mu^2 + mu - M = 0 (no cancellation for small nu)
        mu = 2.0 * mu_obs / (1.0 + np.sqrt(np.clip(1.0 + 4.0 * nu * mu_obs, 1e-12, None)))
        return mu, (1.0 + 2.0 * nu * mu) ** 2


class StaticArea(Effect):
    """Static pixel-area variation (tree rings, PRNU-like area structure).

    Pixel areas 1 + delta_xy fixed in time. The pattern is identical in both
    flats of a pair, so it cancels in difference images and appears in the
    pair-sum statistic as S_ij(mu) = mu^2 v_ij, with v_ij the autocovariance
    of delta at lag (i, j) (the realised pattern's, not an ensemble model:
    a single sensor has one pattern). Parameters: ``v_i_j`` for every lag
    0 <= i, j <= L.

    Signature: S_ij growing as mu^2; nothing in C_ij of difference images.
    """

    name = "static_area"
    #: the realised pattern averages to slightly different values over the two
    #: halves and over the edge rings (constant relative offsets)
    observables = ("pair_sums", "halves", "edges")
    signature = "S_ij = mu^2 v_ij in pair-sum statistics; cancels in differences"
    _identifiable = {
        "table": (False, "a_ij come from difference images, where static structure cancels"),
        "flats": (True, "S_ij(mu) of the pair sums"),
        "ptc": (False, "difference-image variances do not see static structure"),
    }

    def __init__(self, max_lag=3):
        self.max_lag = int(max_lag)
        n = (self.max_lag + 1) ** 2
        self.param_names = tuple(f"v_{i}_{j}" for i in range(self.max_lag + 1)
                                 for j in range(self.max_lag + 1))
        self.bounds = ((0.0, 1e-2),) + ((-1e-2, 1e-2),) * (n - 1)
        self.start = (0.0,) * n
        self.scale = (1e-6,) * n
        self.units = ("",) * n

    def static(self, mu, L, theta):
        if L != self.max_lag:
            raise InputError(f"static_area was built for lags <= {self.max_lag}, data has {L}")
        v = np.asarray(theta, float).reshape(L + 1, L + 1)
        return np.asarray(mu, float)[:, None, None] ** 2 * v


def cti_filter_covariance(cov, eps, axis):
    """Covariance after out_k = (1 - eps) N_k + eps N_{k-1} along ``axis``.

    Exact for a stationary field: C'(l) = [(1 - eps)^2 + eps^2] C(l) +
    eps (1 - eps) [C(l - 1) + C(l + 1)] with C(-1) = C(1) (symmetry).

    Parameters
    ----------
    cov : ndarray, shape (..., L + 1, L + 1)
        Quadrant covariances [i, j].
    eps : float
        Fraction deferred by one pixel.
    axis : {0, 1}
        0: serial (i), 1: parallel (j).
    """
    c = np.moveaxis(np.asarray(cov, float), -2 + axis, -1)
    ext = np.concatenate([c[..., 1:2], c, np.zeros(c.shape[:-1] + (1,))], axis=-1)
    out = ((1 - eps) ** 2 + eps**2) * c + eps * (1 - eps) * (ext[..., :-2] + ext[..., 2:])
    return np.moveaxis(out, -1, -2 + axis)


class CTI(Effect):
    """Charge transfer inefficiency along the serial or parallel readout.

    A fraction ``eps`` of each pixel's charge is read out with the next pixel
    (the sum of the per-transfer losses over the transfers, first order).
    Covariances follow :func:`cti_filter_covariance`: the variance drops by
    ~2 eps and the lag-1 covariance along the readout axis gains ~eps mu.

    Signature: a lag-1 covariance along one axis with C/mu constant in mu
    (no mu^2 growth), variance slightly reduced.

    Observables: the covariances only. The filter moves charge to the next
    pixel, so the sum over lags and the mean are kept, and one ``eps`` acts on
    the whole image. A sensor's CTI from traps would also lose charge at low
    signal (linearity) and grow with the number of transfers (halves); this
    model has neither.
    """

    #: the filter keeps the sum over lags ((1 - eps)^2 + eps^2 + 2 eps (1 - eps) = 1)
    #: and the mean; uniform eps: the halves agree
    observables = ("covariances",)
    param_names = ("eps",)
    bounds = ((0.0, 0.05),)
    start = (0.0,)
    scale = (1e-3,)
    units = ("",)
    signature = "lag-1 covariance along the readout axis, C/mu constant in mu"

    def __init__(self, axis):
        if axis not in ("serial", "parallel"):
            raise InputError(f"CTI axis must be 'serial' or 'parallel', got {axis!r}")
        self.axis = axis
        self.name = f"cti_{axis}"
        self._identifiable = {
            "table": (False, "a constant C/mu at lag 1 is absorbed by the covariance fit's "
                             "intercept or by a_01/a_10; not separable in a table"),
            "flats": (True, "lag-1 C/mu constant in mu"),
            "ptc": (False, "the variance reduction is degenerate with the gain"),
        }

    def apply_cov(self, cov, theta):
        return cti_filter_covariance(cov, theta[0], 0 if self.axis == "serial" else 1)


def effect_library(names=None, *, max_lag=3):
    """Instances of the library's effects (all, or those named).

    ``max_lag`` sets the number of parameters of ``static_area``.
    """
    lib = [ChargeCloud(), WellFilling(), Diffusion(), GainNonlinearity(), StaticArea(max_lag),
           CTI("serial"), CTI("parallel")]
    if names is None:
        return lib
    by = {e.name: e for e in lib}
    bad = [n for n in names if n not in by]
    if bad:
        raise InputError(f"unknown effects {bad}; the vocabulary is {list(EFFECT_NAMES)}")
    return [by[n] for n in names]
