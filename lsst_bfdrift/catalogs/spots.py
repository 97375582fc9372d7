"""Spot-projector images: the spots of a grid, measured with one fixed weight across a series.

A spot projector images a grid of identical spots onto the sensor, at a
series of exposure times, so that the same spots are seen at many fluxes
(the way camera test stands measure the brighter-fatter anisotropy). Steps:

1. **Reading** (:func:`read_spot_images`): every image is converted to
   electrons by :func:`~lsst_bfdrift.images.electrons.to_electrons` and its
   unit rule (a file with neither ``BUNIT`` nor a gain is ADU with an
   unknown gain and is refused: state ``BUNIT = 'electron'`` or give the
   gain); each needs its exposure time (``EXPTIME``, s, > 0) and all must
   have one shape (one sensor region).
2. **Finding** (:func:`find_spots`): the spots are detected once, on the
   sum of the background-subtracted images (smoothed by a Gaussian of
   ``kernel_sigma`` px, connected pixels above ``threshold`` times the
   smoothed noise). Their positions are the grid positions: every image is
   measured there, so a spot is the same spot in every image of the series
   (matching by construction; the centroid is refined per image).
3. **Measuring** (:func:`measure_spots`): per spot and image, in a stamp
   around the grid position, the background is the 3-sigma-clipped median of
   an annulus (``radius + 2`` to ``radius + 2 + annulus_width`` px; it also
   removes what is left of a bias pedestal; a pedestal stated in the header
   as ``BIASLVL``, e, as ``bfdrift spot-sim --bias`` writes it, is subtracted
   when the images are read, so that a correction of the images sees only
   the collected charge), and the moments are taken with a **fixed
   circular Gaussian weight** of ``weight_sigma`` px, the same for every
   spot and every image of the series, centred on the weighted centroid
   (iterated) and cut at ``radius`` px (:func:`fixed_weight_moments`).

Why a fixed weight
------------------
Adaptive moments (HSM, the star catalogs') fit the weight to each spot:
the weight then grows with the spot, so with the flux, and a size-flux slope
mixes the spot's change with the weight's, and depends on the noise. An
unweighted aperture is flux-independent too, but its noise grows as the
fourth power of its radius (the background far from the spot dominates the
second moments). A fixed Gaussian weight is a fixed functional of the image:
the change of the measured moments with flux is the spot's own, and a
prediction measured with the same weight (:mod:`~lsst_bfdrift.catalogs.spot_slopes`)
is comparable term by term. By default ``weight_sigma`` is
:data:`WEIGHT_FACTOR` times the median adaptive (HSM) sigma of the spots in
the sum of the unsaturated images, chosen once per series and stored in
:class:`SpotGrid`.

The weighted moments M_w are deweighted as if the spot were Gaussian,
``M = (M_w^-1 - I / weight_sigma^2)^-1``: exact for a Gaussian spot (the
product of two Gaussians), a fixed monotonic map otherwise, so the slopes of
M are still those of a flux-independent measurement. From M (px^2, x the
serial axis): ``sigma_x = sqrt(Mxx)``, ``sigma_y = sqrt(Myy)``,
``T = Mxx + Myy``, ``e1 = (Mxx - Myy) / T``, ``e2 = 2 Mxy / T``. Their
errors are the linear propagation of each pixel's variance (background rms
squared plus the pixel's own electrons), the centroid taken as known (its
error enters at second order for moments about the weighted centroid).

Flags (bit mask ``flags``; ``use`` is True when ``flags == 0``); every flagged
row is left out of the slopes and counted (:func:`spot_flag_counts`):

================  ===  =========================================================
SPOT_SATURATED      1  a pixel within ``radius`` at or above the saturation level
                       (given, SATURATE, or a flat top; the saturation rule of
                       :mod:`lsst_bfdrift.images.electrons`) or in a SAT plane
SPOT_EDGE           2  the stamp (annulus included) leaves the image
SPOT_CROWDED        4  another spot closer than ``radius`` plus the annulus'
                       outer radius (its light reaches the annulus)
SPOT_MASKED         8  a masked or non-finite pixel within ``radius``
SPOT_MOMENTS       16  the moments failed: non-positive weighted flux, a
                       centroid that left the stamp, or a weighted size too
                       close to the weight's to be deweighted
SPOT_FAINT         32  signal-to-noise ratio below ``min_snr``
================  ===  =========================================================

A grid with fewer than ``min_spots`` spots, or an image of the series in
which fewer than ``min_spots`` spots are detected (SNR >= ``detect_snr``), is
an error naming the count.
"""

import dataclasses
import os

import numpy as np
from astropy import units as u
from astropy.table import QTable
from scipy import ndimage

from lsst_bfdrift.catalogs.catalog import hsm_moments
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["SpotExposure", "SpotGrid", "read_spot_images", "find_spots", "measure_spots",
           "fixed_weight_moments", "deweight_moments", "spot_flag_counts", "SPOT_QUANTITIES",
           "WEIGHT_FACTOR", "RADIUS_FACTOR", "MIN_SPOTS", "MIN_SNR", "SPOT_SATURATED",
           "SPOT_EDGE", "SPOT_CROWDED", "SPOT_MASKED", "SPOT_MOMENTS", "SPOT_FAINT",
           "SPOT_FLAG_NAMES"]

SPOT_SATURATED = 1
SPOT_EDGE = 2
SPOT_CROWDED = 4
SPOT_MASKED = 8
SPOT_MOMENTS = 16
SPOT_FAINT = 32
#: column name of each flag bit
SPOT_FLAG_NAMES = {SPOT_SATURATED: "flag_saturated", SPOT_EDGE: "flag_edge",
                   SPOT_CROWDED: "flag_crowded", SPOT_MASKED: "flag_masked",
                   SPOT_MOMENTS: "flag_moments", SPOT_FAINT: "flag_faint"}

#: The measured quantities of a spot (catalog columns; their errors are
#: ``<name>_err``): sigma_x, sigma_y (px), size = ln T (T in px^2), e1, e2.
SPOT_QUANTITIES = ("sigma_x", "sigma_y", "size", "e1", "e2")

#: Default weight sigma, in units of the spots' median adaptive sigma.
WEIGHT_FACTOR = 1.5
#: Default cut of the weight and the flux aperture, in units of the weight sigma.
RADIUS_FACTOR = 4.0
#: Fewest spots of a grid, and fewest detected in every image.
MIN_SPOTS = 5
#: Spots measured below this signal-to-noise ratio are flagged faint.
MIN_SNR = 20.0


@dataclasses.dataclass
class SpotExposure:
    """One image of a spot series, in electrons.

    Attributes
    ----------
    data : ndarray
        Pixels (e, float64).
    bad : ndarray of bool
        Masked or non-finite pixels.
    exptime : float
        Exposure time (s).
    name : str
        The file, or ``image<k>``.
    saturation : float or None
        Saturation level (e).
    saturated : ndarray of bool or None
        Pixels at or above the level, or in a SAT plane.
    gain : float
        e/ADU applied (1 for an image in electrons).
    bias : float
        Bias pedestal (e) subtracted from ``data`` and ``saturation``: the
        header's ``BIASLVL`` (0 without it).
    """

    data: np.ndarray
    bad: np.ndarray
    exptime: float
    name: str
    saturation: float = None
    saturated: np.ndarray = None
    gain: float = 1.0
    bias: float = 0.0

    def with_data(self, data):
        """A copy holding ``data`` (e.g. a corrected image) with this image's mask,
        saturation, time and name."""
        return dataclasses.replace(self, data=np.asarray(data, float))


@dataclasses.dataclass
class SpotGrid:
    """The spots of a series: grid positions and the fixed measurement settings.

    Attributes
    ----------
    x, y : ndarray
        Grid positions (px, 0-based pixel centres, x the serial axis), from
        the sum of the images.
    weight_sigma : float
        Sigma of the fixed Gaussian weight (px).
    radius : float
        Cut of the weight and radius of the flux aperture (px).
    annulus : (float, float)
        Inner and outer radius of the background annulus (px).
    shape : (int, int)
        (ny, nx) of the images.
    crowded : ndarray of bool
        Spots with a neighbour closer than ``radius + annulus[1]``.
    adaptive_sigma : float
        Median adaptive sigma (px) of the spots that set the default weight
        (NaN when the weight was given).
    """

    x: np.ndarray
    y: np.ndarray
    weight_sigma: float
    radius: float
    annulus: tuple
    shape: tuple
    crowded: np.ndarray
    adaptive_sigma: float = float("nan")

    def __len__(self):
        return int(np.size(self.x))

    @property
    def half(self):
        """Half side (px) of a spot's stamp: the annulus plus one pixel."""
        return int(np.ceil(self.annulus[1])) + 1


def read_spot_images(images, *, gain=None, saturation=None, exptimes=None, names=None,
                     gain_name="gain", saturation_name="saturation"):
    """The images of a spot series in electrons, with their exposure times.

    Parameters
    ----------
    images : sequence
        Paths, arrays (electrons), CCDData/NDData or LSST exposures
        (:func:`~lsst_bfdrift.images.electrons.to_electrons`); one path or
        array is a series of one (refused later: a series needs several).
    gain : float or Quantity, optional
        e/ADU of images in ADU without a GAIN keyword.
    saturation : float, optional
        Saturation level in the images' unit (default: SATURATE, else a flat top).
    exptimes : sequence of float or Quantity, optional
        Exposure times (s), one per image; default: each image's ``EXPTIME``.
    names : sequence of str, optional
        Labels (default: the paths, else ``image<k>``).
    gain_name, saturation_name : str, optional
        How messages name the options (``'--gain'`` in the command line).

    Returns
    -------
    list of SpotExposure
        Each image in electrons less its header's ``BIASLVL`` (e; a bias
        pedestal left in the image, as ``bfdrift spot-sim --bias`` states
        it; also taken from the saturation level), on a copy.

    Raises
    ------
    InputError
        No image; a ``BIASLVL`` that is not a finite number; an image in
        ADU without a gain (the message names ``BUNIT = 'electron'`` and
        the gain option); an image without a
        positive ``EXPTIME`` (when ``exptimes`` is not given); images of
        different shapes; ``exptimes`` or ``names`` of another length.
    """
    if isinstance(images, (str, os.PathLike, np.ndarray)):
        images = [images]
    images = list(images)
    if not images:
        raise InputError("no spot images given")
    for what, seq in (("exptimes", exptimes), ("names", names)):
        if seq is not None and len(seq) != len(images):
            raise InputError(f"{what} has {len(seq)} entries for {len(images)} images")
    out = []
    for k, src in enumerate(images):
        name = names[k] if names is not None else (
            os.fspath(src) if isinstance(src, (str, os.PathLike)) else f"image{k}")
        img = to_electrons(src, gain=gain, saturation=saturation, gain_name=gain_name,
                           saturation_name=saturation_name)
        img.warn()
        exptime = _exptime(img, None if exptimes is None else exptimes[k], name)
        bias = _bias_level(img, name)
        if out and img.data.shape != out[0].data.shape:
            (ny0, nx0), (ny, nx) = out[0].data.shape, img.data.shape
            raise InputError(f"spot images differ in shape: {out[0].name} is {nx0} x {ny0} px, "
                             f"{name} is {nx} x {ny} px; a series is one sensor region imaged "
                             "at several exposure times (give images of one shape)")
        sat = img.saturated
        if img.sat_plane is not None:
            sat = img.sat_plane if sat is None else (sat | img.sat_plane)
        data, level = img.data, img.saturation
        if bias != 0.0:
            data = data - bias  # a copy: the input is never modified
            level = None if level is None else level - bias
        out.append(SpotExposure(data=data, bad=img.bad, exptime=exptime, name=name,
                                saturation=level, saturated=sat, gain=img.gain, bias=bias))
    return out


def _bias_level(img, name):
    """The bias pedestal (e) an image's header states as ``BIASLVL`` (0 without it)."""
    exposure = img.exposure
    value = exposure.header_value("BIASLVL") if hasattr(exposure, "header_value") \
        else img.meta.get("BIASLVL")
    if value is None:
        return 0.0
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)) \
            or not np.isfinite(value):
        raise InputError(f"{name}: BIASLVL = {value!r} is not a bias level (e); remove the "
                         "keyword or give the pedestal left in the image in electrons")
    return float(value)


def _exptime(img, given, name):
    """The exposure time (s) of an image read by to_electrons: ``given``, else EXPTIME."""
    if given is None:
        exposure = img.exposure
        value = exposure.header_value("EXPTIME") if hasattr(exposure, "header_value") \
            else img.meta.get("EXPTIME")
        if value is None:
            raise InputError(f"{name}: no EXPTIME keyword; every spot image needs its "
                             "exposure time (EXPTIME, s) to order the series (or give "
                             "exptimes=)")
        what = f"{name}: EXPTIME"
    else:
        value, what = given, f"{name}: exptime"
    if isinstance(value, u.Quantity):
        value = value.to_value(u.s)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)) \
            or not (np.isfinite(value) and value > 0):
        raise InputError(f"{what} = {value!r} is not a positive exposure time (s); a bias "
                         "or dark frame is not a spot image")
    return float(value)


def _robust_level(values, n_iter=3, clip=3.0):
    """3-sigma-clipped median and standard deviation (from the MAD) of ``values``."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return np.nan, np.nan
    med = float(np.median(v))
    sig = 1.4826 * float(np.median(np.abs(v - med)))
    for _ in range(n_iter):
        if not sig > 0:
            break
        keep = np.abs(v - med) <= clip * sig
        if keep.all() or keep.sum() < 5:
            break
        v = v[keep]
        med = float(np.median(v))
        sig = 1.4826 * float(np.median(np.abs(v - med)))
    if not sig > 0 and v.size > 1:
        sig = float(np.std(v))
    return med, sig


def find_spots(exposures, *, threshold=10.0, kernel_sigma=1.0, min_pixels=5, weight_sigma=None,
               weight_factor=WEIGHT_FACTOR, radius_factor=RADIUS_FACTOR, annulus_width=4.0,
               min_spots=MIN_SPOTS):
    """The grid of a spot series: positions on the sum of the images and the fixed weight.

    Parameters
    ----------
    exposures : sequence of SpotExposure
        From :func:`read_spot_images`.
    threshold : float, optional
        Detection threshold in units of the noise of the smoothed sum.
    kernel_sigma : float, optional
        Sigma (px) of the Gaussian smoothing before detection.
    min_pixels : int, optional
        Fewest connected pixels of a detection.
    weight_sigma : float or Quantity, optional
        Sigma of the fixed Gaussian weight (px); default :data:`WEIGHT_FACTOR`
        times the median adaptive sigma of the spots, measured on the sum of
        the images in which the spot has no saturated pixel.
    weight_factor : float, optional
        That factor.
    radius_factor : float, optional
        Cut of the weight and the flux aperture, in weight sigmas (at least 3 px).
    annulus_width : float, optional
        Width (px) of the background annulus, which starts 2 px beyond the radius.
    min_spots : int, optional
        Fewest spots the grid must hold.

    Returns
    -------
    SpotGrid

    Raises
    ------
    InputError
        No image, a blank sum, fewer than ``min_spots`` spots (with the
        count), or a weight that is not a positive number.
    """
    exposures = list(exposures)
    if not exposures:
        raise InputError("no spot images given")
    shape = exposures[0].data.shape
    stack = np.zeros(shape)
    bad_all = np.ones(shape, bool)
    for ex in exposures:
        level, _ = _robust_level(ex.data[~ex.bad])
        if not np.isfinite(level):
            raise InputError(f"{ex.name}: no usable pixel (all masked or non-finite)")
        stack += np.where(ex.bad, 0.0, ex.data - level)
        bad_all &= ex.bad
    _, rms = _robust_level(stack[~bad_all])
    if not rms > 0:
        raise InputError("the sum of the spot images is blank (no noise, no spots); give "
                         "spot images in electrons")
    conv = ndimage.gaussian_filter(stack, float(kernel_sigma), mode="constant")
    # noise of the smoothed sum: rms * sqrt(sum k^2), k the unit Gaussian kernel
    noise = rms / (2.0 * np.sqrt(np.pi) * float(kernel_sigma))
    labels, n = ndimage.label((conv > threshold * noise) & ~bad_all)
    if n:
        sizes = ndimage.sum_labels(np.ones(shape), labels, np.arange(1, n + 1))
        keep = np.flatnonzero(sizes >= int(min_pixels)) + 1
        cen = ndimage.center_of_mass(np.clip(conv, 0, None), labels, keep)
        xy = np.array([[c[1], c[0]] for c in cen], float).reshape(-1, 2)
    else:
        xy = np.zeros((0, 2))
    if len(xy) < int(min_spots):
        raise InputError(f"found {len(xy)} spots in the sum of the {len(exposures)} images "
                         f"(above {threshold:g} sigma); need at least {int(min_spots)} for "
                         "spot-to-spot errors (is this a spot-grid image, in electrons?)")
    adaptive = float("nan")
    if weight_sigma is None:
        adaptive = _median_adaptive_sigma(exposures, xy, kernel_sigma)
        weight_sigma = float(f"{weight_factor * adaptive:.3g}")
    if isinstance(weight_sigma, u.Quantity):
        weight_sigma = weight_sigma.to_value(u.pix)
    if not (np.isfinite(weight_sigma) and weight_sigma > 0):
        raise InputError(f"weight_sigma must be a positive number of pixels, got "
                         f"{weight_sigma!r}")
    radius = max(float(radius_factor) * float(weight_sigma), 3.0)
    annulus = (radius + 2.0, radius + 2.0 + float(annulus_width))
    d2 = (xy[:, 0, None] - xy[None, :, 0]) ** 2 + (xy[:, 1, None] - xy[None, :, 1]) ** 2
    np.fill_diagonal(d2, np.inf)
    crowded = np.min(d2, axis=1) < (radius + annulus[1]) ** 2
    order = np.lexsort((np.round(xy[:, 0], 1), np.round(xy[:, 1], 1)))  # row by row
    xy = xy[order]
    return SpotGrid(x=xy[:, 0].copy(), y=xy[:, 1].copy(), weight_sigma=float(weight_sigma),
                    radius=radius, annulus=annulus, shape=tuple(shape), crowded=crowded[order],
                    adaptive_sigma=adaptive)


def _median_adaptive_sigma(exposures, xy, kernel_sigma):
    """Median HSM sigma of the spots, each on the sum of its unsaturated stamps."""
    half = 12
    sig = []
    ny, nx = exposures[0].data.shape
    for x, y in xy:
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        if ix - half < 0 or iy - half < 0 or ix + half >= nx or iy + half >= ny:
            continue
        sl = (slice(iy - half, iy + half + 1), slice(ix - half, ix + half + 1))
        st = np.zeros((2 * half + 1, 2 * half + 1))
        for ex in exposures:
            if ex.saturated is not None and np.any(ex.saturated[sl]):
                continue
            if np.any(ex.bad[sl]):
                continue
            level, _ = _robust_level(ex.data[sl])
            st += ex.data[sl] - level
        if not st.any():
            continue
        m = hsm_moments(st, guess=(x - ix + half + 1, y - iy + half + 1),
                        guess_sig=max(2.0, kernel_sigma))
        if m is not None:
            sig.append(m["sigma"])
    if not sig:
        raise InputError("no spot could be measured by adaptive moments to set the weight "
                         "(every stamp saturated, masked or at the edge); give weight_sigma")
    return float(np.median(sig))


def deweight_moments(mw, weight_sigma):
    """Moments of a Gaussian whose Gaussian-weighted moments are ``mw``.

    Parameters
    ----------
    mw : array_like, shape (3,)
        Weighted moments (Mxx, Myy, Mxy), px^2.
    weight_sigma : float
        Sigma of the circular Gaussian weight (px).

    Returns
    -------
    m : ndarray, shape (3,) or None
        ``(M_w^-1 - I / weight_sigma^2)^-1`` as (Mxx, Myy, Mxy) px^2; None
        when that matrix is not positive definite with eigenvalues of at most
        ``10 weight_sigma^2`` (a weighted size too close to the weight's).
    jacobian : ndarray, shape (3, 3) or None
        d m / d mw (rows Mxx, Myy, Mxy; columns likewise).
    """
    a, b, c = (float(v) for v in mw)
    mat = np.array([[a, c], [c, b]])
    det = a * b - c * c
    if not (a > 0 and b > 0 and det > 0):
        return None, None
    x = np.linalg.inv(mat) - np.eye(2) / weight_sigma ** 2
    ev = np.linalg.eigvalsh(x)
    if not ev.min() > 1.0 / (10.0 * weight_sigma ** 2):
        return None, None
    m = np.linalg.inv(x)
    amat = m @ np.linalg.inv(mat)  # symmetric: m and mw commute
    jac = np.empty((3, 3))
    for k, e in enumerate((np.array([[1.0, 0.0], [0.0, 0.0]]), np.array([[0.0, 0.0], [0.0, 1.0]]),
                           np.array([[0.0, 1.0], [1.0, 0.0]]))):
        dm = amat @ e @ amat.T
        jac[:, k] = (dm[0, 0], dm[1, 1], dm[0, 1])
    return np.array([m[0, 0], m[1, 1], m[0, 1]]), jac


def fixed_weight_moments(stamp, *, weight_sigma, radius, center, variance=None, bad=None,
                         max_iter=100, tol=1e-9):
    """Second moments of a stamp with a fixed circular Gaussian weight.

    The weight ``exp(-r^2 / (2 weight_sigma^2))``, cut at ``radius``, is
    centred on the weighted centroid (iterated from ``center``); the
    moments about it are deweighted by :func:`deweight_moments`. Exact for
    a Gaussian spot sampled at pixel centres (the weight and the spot
    multiply to a Gaussian).

    Parameters
    ----------
    stamp : ndarray
        Background-subtracted pixels (e); pixel ``[j, i]`` is centred at (i, j).
    weight_sigma : float
        Sigma of the weight (px).
    radius : float
        Cut of the weight and radius of the flux aperture (px).
    center : (float, float)
        Starting centroid (x, y), stamp coordinates.
    variance : ndarray, optional
        Per-pixel variance (e^2): gives the errors.
    bad : ndarray of bool, optional
        Pixels left out (weight 0).
    max_iter : int, optional
        Centroid iterations.
    tol : float, optional
        Convergence of the centroid (px).

    Returns
    -------
    dict or None
        ``x``, ``y`` (px), ``flux`` (unweighted sum within ``radius``, e),
        ``flux_w`` (weighted sum), ``mw`` and ``m`` (weighted and deweighted
        (Mxx, Myy, Mxy), px^2), ``sigma_x``, ``sigma_y`` (px), ``T`` (px^2),
        ``size`` (ln T), ``e1``, ``e2``; with ``variance``: ``flux_err`` and
        ``<quantity>_err`` for each of :data:`SPOT_QUANTITIES`. None when the
        weighted flux is not positive, the centroid leaves the stamp (moves
        by more than ``radius / 2``), or the moments cannot be deweighted.
    """
    img = np.asarray(stamp, float)
    ny, nx = img.shape
    jj, ii = np.mgrid[:ny, :nx]
    ok = np.ones(img.shape, bool) if bad is None else ~np.asarray(bad, bool)
    img = np.where(ok, img, 0.0)
    w2 = 2.0 * float(weight_sigma) ** 2
    x0, y0 = (float(v) for v in center)
    xc, yc = x0, y0
    for _ in range(int(max_iter)):
        r2 = (ii - xc) ** 2 + (jj - yc) ** 2
        wgt = np.where(ok & (r2 <= radius ** 2), np.exp(-r2 / w2), 0.0)
        d = float(np.sum(wgt * img))
        if not d > 0:
            return None
        xn, yn = float(np.sum(wgt * img * ii) / d), float(np.sum(wgt * img * jj) / d)
        if max(abs(xn - x0), abs(yn - y0)) > 0.5 * radius:
            return None
        done = max(abs(xn - xc), abs(yn - yc)) < tol
        xc, yc = xn, yn
        if done:
            break
    dx, dy = ii - xc, jj - yc
    r2 = dx * dx + dy * dy
    inap = ok & (r2 <= radius ** 2)
    wgt = np.where(inap, np.exp(-r2 / w2), 0.0)
    d = float(np.sum(wgt * img))
    if not d > 0:
        return None
    basis = (dx * dx, dy * dy, dx * dy)
    mw = np.array([np.sum(wgt * img * b) / d for b in basis])
    m, jac = deweight_moments(mw, float(weight_sigma))
    if m is None:
        return None
    t = m[0] + m[1]
    out = {"x": xc, "y": yc, "flux": float(np.sum(img[inap])), "flux_w": d, "mw": mw, "m": m,
           "sigma_x": float(np.sqrt(m[0])), "sigma_y": float(np.sqrt(m[1])), "T": float(t),
           "size": float(np.log(t)), "e1": float((m[0] - m[1]) / t), "e2": float(2 * m[2] / t)}
    if variance is not None:
        var = np.where(ok, np.asarray(variance, float), 0.0)
        # per-pixel gradients of the weighted moments, then of the deweighted ones
        gw = np.array([wgt * (b - mw[k]) / d for k, b in enumerate(basis)])
        gm = np.tensordot(jac, gw, axes=1)
        grads = {"sigma_x": gm[0] / (2 * out["sigma_x"]), "sigma_y": gm[1] / (2 * out["sigma_y"]),
                 "size": (gm[0] + gm[1]) / t,
                 "e1": (gm[0] - gm[1]) / t - out["e1"] * (gm[0] + gm[1]) / t,
                 "e2": 2 * gm[2] / t - out["e2"] * (gm[0] + gm[1]) / t}
        for k, g in grads.items():
            out[f"{k}_err"] = float(np.sqrt(np.sum(g * g * var)))
        out["flux_err"] = float(np.sqrt(np.sum(var[inap])))
    return out


def measure_spots(exposures, grid, *, min_snr=MIN_SNR, detect_snr=5.0, min_spots=MIN_SPOTS,
                  progress=False):
    """Measure every spot of the grid in every image (the per-spot rows of a series).

    Parameters
    ----------
    exposures : sequence of SpotExposure
        The images (:func:`read_spot_images`), or corrected copies of them
        (:meth:`SpotExposure.with_data`).
    grid : SpotGrid
        From :func:`find_spots`: positions and the fixed weight.
    min_snr : float, optional
        Rows below this signal-to-noise ratio are flagged faint.
    detect_snr : float, optional
        A spot counts as detected in an image at this SNR.
    min_spots : int or None, optional
        Fewest spots detected in every image (None: no check).
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    astropy.table.QTable
        One row per image and spot: ``image`` (index), ``name``, ``exptime``
        (s), ``spot`` (index in the grid), ``x_ref``, ``y_ref`` (grid
        position), ``x``, ``y`` (weighted centroid; px, 0-based pixel
        centres), ``flux``, ``flux_err`` (e, within ``radius``), ``snr``,
        ``peak`` (e, largest pixel within ``radius``, background included),
        ``background``, ``background_rms`` (e per px), ``ixx_w``, ``iyy_w``,
        ``ixy_w`` (weighted moments), ``ixx``, ``iyy``, ``ixy``, ``T``
        (deweighted, px^2), ``sigma_x``, ``sigma_y`` (px), ``size`` (ln T),
        ``e1``, ``e2`` and their ``_err``, ``flags``, one boolean column per
        flag and ``use``. ``meta`` holds the grid's settings, ``min_snr``,
        the image names and exposure times.

    Raises
    ------
    InputError
        An image of another shape than the grid's, or one in which fewer
        than ``min_spots`` spots are detected (with the count).
    """
    exposures = list(exposures)
    rows = []
    half = grid.half
    ny, nx = grid.shape
    jj, ii = np.mgrid[-half:half + 1, -half:half + 1]
    r_ann = np.hypot(ii, jj)
    with ProgressBar(len(exposures) * len(grid), "spots", enabled=progress) as bar:
        for i, ex in enumerate(exposures):
            if ex.data.shape != tuple(grid.shape):
                raise InputError(f"{ex.name}: shape {ex.data.shape} differs from the grid's "
                                 f"{tuple(grid.shape)}")
            for k in range(len(grid)):
                bar(1)
                rows.append(_measure_one(ex, i, k, grid, half, ii, jj, r_ann, nx, ny, min_snr))
    tab = _spot_table(rows)
    for bit, name in SPOT_FLAG_NAMES.items():
        tab[name] = (np.asarray(tab["flags"]) & bit) != 0
    tab["use"] = np.asarray(tab["flags"]) == 0
    tab.meta.update(weight_sigma=grid.weight_sigma, radius=grid.radius,
                    annulus=list(grid.annulus), adaptive_sigma=grid.adaptive_sigma,
                    min_snr=float(min_snr), detect_snr=float(detect_snr), n_spots=len(grid),
                    names=[ex.name for ex in exposures],
                    exptimes=[ex.exptime for ex in exposures], shape=list(grid.shape),
                    moments=f"fixed circular Gaussian weight, sigma {grid.weight_sigma:g} px, "
                            f"cut at {grid.radius:g} px, deweighted as a Gaussian")
    if min_spots is not None:
        snr = np.asarray(tab["snr"], float)
        edge = np.asarray(tab["flag_edge"])
        img = np.asarray(tab["image"])
        for i, ex in enumerate(exposures):
            sel = img == i
            n_det = int(np.sum((np.nan_to_num(snr[sel]) >= detect_snr) & ~edge[sel]))
            if n_det < int(min_spots):
                n_edge = int(np.sum(edge[sel]))
                at_edge = f", {n_edge} more at the image edge, not measured" if n_edge else ""
                raise InputError(f"{ex.name}: {n_det} of the grid's {len(grid)} spots detected "
                                 f"(SNR >= {detect_snr:g}{at_edge}); need at least "
                                 f"{int(min_spots)} per image (a dark, bias or misaligned frame "
                                 "in the series?)")
    return tab


def _measure_one(ex, i, k, grid, half, ii, jj, r_ann, nx, ny, min_snr):
    """The row of spot ``k`` in image ``i``."""
    xr, yr = float(grid.x[k]), float(grid.y[k])
    row = {"image": i, "name": ex.name, "exptime": ex.exptime, "spot": k, "x_ref": xr,
           "y_ref": yr, "flags": SPOT_CROWDED if grid.crowded[k] else 0}
    ix, iy = int(np.floor(xr + 0.5)), int(np.floor(yr + 0.5))
    if ix - half < 0 or iy - half < 0 or ix + half >= nx or iy + half >= ny:
        row["flags"] |= SPOT_EDGE
        return row
    sl = (slice(iy - half, iy + half + 1), slice(ix - half, ix + half + 1))
    raw, bad = ex.data[sl], ex.bad[sl]
    ann = (r_ann >= grid.annulus[0]) & (r_ann <= grid.annulus[1]) & ~bad
    level, rms = _robust_level(raw[ann])
    if not np.isfinite(level):
        row["flags"] |= SPOT_MASKED | SPOT_MOMENTS
        return row
    rms = rms if rms > 0 else 0.0
    sub = raw - level
    var = rms ** 2 + np.clip(np.where(bad, 0.0, sub), 0, None)
    centre = (xr - ix + half, yr - iy + half)
    row.update(background=level, background_rms=rms)
    m = fixed_weight_moments(sub, weight_sigma=grid.weight_sigma, radius=grid.radius,
                             center=centre, variance=var, bad=bad)
    cx, cy = (centre if m is None else (m["x"], m["y"]))
    region = np.hypot(ii + half - cx, jj + half - cy) <= grid.radius
    region |= np.hypot(ii + half - centre[0], jj + half - centre[1]) <= grid.radius
    sat = np.zeros_like(bad) if ex.saturated is None else ex.saturated[sl]
    if np.any(sat & region):  # saturated pixels count as saturation, masked or not
        row["flags"] |= SPOT_SATURATED
    if np.any(bad & region & ~sat):
        row["flags"] |= SPOT_MASKED
    if m is None:
        row["flags"] |= SPOT_MOMENTS
        return row
    inap = region & ~bad
    peak = float(np.max(raw[inap])) if inap.any() else np.nan
    snr = m["flux"] / m["flux_err"] if m["flux_err"] > 0 else np.inf
    if not snr >= min_snr:
        row["flags"] |= SPOT_FAINT
    row.update(x=m["x"] + ix - half, y=m["y"] + iy - half, flux=m["flux"],
               flux_err=m["flux_err"], snr=snr, peak=peak, ixx_w=m["mw"][0], iyy_w=m["mw"][1],
               ixy_w=m["mw"][2], ixx=m["m"][0], iyy=m["m"][1], ixy=m["m"][2], T=m["T"])
    for q in SPOT_QUANTITIES:
        row[q] = m[q]
        row[f"{q}_err"] = m[f"{q}_err"]
    return row


#: Columns of the spot table, and their units.
_COLUMNS = (("image", None), ("name", None), ("exptime", u.s), ("spot", None), ("x_ref", u.pix),
            ("y_ref", u.pix), ("x", u.pix), ("y", u.pix), ("flux", u.electron),
            ("flux_err", u.electron), ("snr", None), ("peak", u.electron),
            ("background", u.electron / u.pix ** 2), ("background_rms", u.electron / u.pix ** 2),
            ("ixx_w", u.pix ** 2), ("iyy_w", u.pix ** 2), ("ixy_w", u.pix ** 2),
            ("ixx", u.pix ** 2), ("iyy", u.pix ** 2), ("ixy", u.pix ** 2), ("T", u.pix ** 2),
            ("sigma_x", u.pix), ("sigma_y", u.pix), ("size", None), ("e1", None), ("e2", None),
            ("sigma_x_err", u.pix), ("sigma_y_err", u.pix), ("size_err", None),
            ("e1_err", None), ("e2_err", None), ("flags", None))


def _spot_table(rows):
    tab = QTable()
    for name, unit in _COLUMNS:
        if name == "name":
            tab[name] = np.array([r[name] for r in rows], dtype=str)
            continue
        ints = name in ("image", "spot", "flags")
        col = np.array([r.get(name, np.nan) for r in rows],
                       dtype=np.int64 if ints else np.float64)
        tab[name] = col * unit if unit is not None else col
    return tab


def spot_flag_counts(catalog, *, per_image=False):
    """How many rows of a spot table each flag excludes.

    Parameters
    ----------
    catalog : QTable
        From :func:`measure_spots`.
    per_image : bool, optional
        Also the counts of every image.

    Returns
    -------
    dict
        Flag name (``saturated``, ``edge``, ...) -> rows with it (a row may
        have several), ``used`` -> rows used, ``rows``; with ``per_image``,
        ``images``: a list of such dicts, one per image (with ``name``).
    """
    flags = np.asarray(catalog["flags"])

    def counts(sel):
        out = {n[5:]: int(np.sum((flags[sel] & b) != 0)) for b, n in SPOT_FLAG_NAMES.items()}
        out.update(used=int(np.sum(flags[sel] == 0)), rows=int(np.sum(sel)))
        return out

    out = counts(np.ones(flags.size, bool))
    if per_image:
        img = np.asarray(catalog["image"])
        names = catalog.meta.get("names") or [str(i) for i in np.unique(img)]
        out["images"] = [{"name": names[i], **counts(img == i)} for i in range(len(names))]
    return out
