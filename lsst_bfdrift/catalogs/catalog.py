"""Star catalogs of an exposure: photutils detection, flags, adaptive moments.

Steps of :func:`measure_stars`:

1. The exposure is converted to electrons (ADU times gain, like the Task).
   Non-finite and masked pixels are excluded everywhere.
2. Background and its rms: ``photutils.background.Background2D`` (median in
   boxes of ``box_size`` px, 3-sigma clipped, 3 x 3 median filter).
3. Detection: the background-subtracted image is smoothed by a Gaussian of
   ``kernel_fwhm`` px and segmented above ``threshold`` times the background
   rms with at least ``n_pixels`` connected pixels
   (``photutils.segmentation.detect_sources``). A segment with more than one
   significant peak of the smoothed image (``photutils.detection.find_peaks``;
   a secondary peak counts when it rises more than ``threshold`` rms above
   the lowest point on the straight line to the main peak) is a blend; it is
   flagged, not split (photutils' deblender needs scikit-image).
4. Per source, in a ``stamp`` x ``stamp`` cutout centred on the segment's
   centroid: adaptive (elliptical-Gaussian-weighted) moments by
   ``galsim.hsm.FindAdaptiveMom`` with other sources' pixels and masked
   pixels given zero weight; flux in a circular aperture of radius
   ``aperture_radius`` px (other sources' pixels excluded), with its error
   from the background rms and the source's Poisson noise (e).

Moments are adaptive moments (Bernstein & Jarvis 2002; HSM): the second
moments of the best-fitting elliptical Gaussian, at pixel centres, with no
PSF correction. ``T = Ixx + Iyy`` (px^2), ``e1 = (Ixx - Iyy) / T``,
``e2 = 2 Ixy / T`` (distortion convention, x the serial axis). Unweighted
segment moments would be dominated by noise for faint stars.

Flags (bit mask ``flags``; ``use`` is True when ``flags == 0``):

=================  ===  ========================================================
FLAG_SATURATED       1  a pixel of the source at or above ``saturation`` (e; given, the
                        SATURATE keyword, or a flat top: the saturation rule of
                        :mod:`lsst_bfdrift.images.electrons`), or a
                        saturated pixel (``saturated``, or an LSST exposure's SAT
                        plane) within the aperture radius
FLAG_BLENDED         2  several peaks in one segment, segment touching another,
                        or another source's centroid within ``isolation`` px
FLAG_EDGE            4  the measurement stamp leaves the image
FLAG_MASKED          8  masked or non-finite pixel (other than a saturated one) within
                        the aperture radius
FLAG_MOMENTS        16  adaptive moments failed (no convergence, nonsense size)
FLAG_NOT_STAR       32  size off the local stellar locus by more than ``size_tolerance``
                        (galaxy, cosmic ray, artefact)
=================  ===  ========================================================
"""

import warnings

import numpy as np
from astropy import units as u
from astropy.table import QTable
from astropy.utils.exceptions import AstropyUserWarning
from scipy import ndimage
from scipy.signal import fftconvolve

from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["StarDetections", "detect_stars", "measure_stars", "hsm_moments",
           "FLAG_SATURATED", "FLAG_BLENDED", "FLAG_EDGE", "FLAG_MASKED", "FLAG_MOMENTS",
           "FLAG_NOT_STAR", "FLAG_NAMES"]

FLAG_SATURATED = 1
FLAG_BLENDED = 2
FLAG_EDGE = 4
FLAG_MASKED = 8
FLAG_MOMENTS = 16
FLAG_NOT_STAR = 32
#: column name of each flag bit
FLAG_NAMES = {FLAG_SATURATED: "flag_saturated", FLAG_BLENDED: "flag_blended",
              FLAG_EDGE: "flag_edge", FLAG_MASKED: "flag_masked",
              FLAG_MOMENTS: "flag_moments", FLAG_NOT_STAR: "flag_not_star"}


def _saturated_pixels(saturated, from_exposure, shape):
    """The ``saturated`` argument (bool, image shape) or else the exposure's SAT plane."""
    if saturated is None:
        return from_exposure
    saturated = np.asarray(saturated, dtype=bool)
    if saturated.shape != tuple(shape):
        raise InputError(f"saturated shape {saturated.shape} does not match image {tuple(shape)}")
    return saturated


def _background(data, bad, box_size):
    # photutils: heavy (1-2 s to import), only when stars are detected
    from photutils.background import Background2D, MedianBackground

    ny, nx = data.shape
    box = int(max(8, min(box_size, ny // 2, nx // 2)))
    if min(ny, nx) < 16:
        raise InputError(f"image {nx} x {ny} is too small for a star catalog (>= 16 px)")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # photutils warns about boxes excluded by the mask
        bkg = Background2D(data, box, mask=bad, filter_size=(3, 3),
                           bkg_estimator=MedianBackground(), exclude_percentile=50.0)
    rms = np.asarray(bkg.background_rms, float)
    return np.asarray(bkg.background, float), rms


def hsm_moments(stamp, *, weight=None, guess=None, origin=(1, 1), guess_sig=2.0):
    """GalSim HSM adaptive moments of a stamp: the package's one HSM call.

    Parameters
    ----------
    stamp : ndarray
        Background-subtracted pixels (e).
    weight : ndarray of bool, optional
        Pixels to use (default all).
    guess : (float, float), optional
        Centroid guess (x, y) in the stamp's coordinates (``origin`` based).
    origin : (int, int), optional
        (x, y) of the stamp's first pixel (GalSim's ``xmin``, ``ymin``).
    guess_sig : float, optional
        Starting Gaussian sigma (px).

    Returns
    -------
    dict or None
        ``x``, ``y`` (px), ``sigma`` (HSM's det(M)^(1/4), px), ``e1``, ``e2``
        (distortion), ``t_det`` = 2 sigma^2 and ``t`` = Mxx + Myy (px^2), and
        ``mxx``, ``myy``, ``mxy``; None when HSM fails or the shape is
        unphysical.
    """
    import galsim  # galsim: heavy, only for HSM moments

    x0, y0 = origin
    img = galsim.ImageD(np.ascontiguousarray(stamp, dtype=np.float64), xmin=x0, ymin=y0)
    kw = {"guess_sig": guess_sig, "strict": False}
    if weight is not None:
        kw["weight"] = galsim.ImageI(np.ascontiguousarray(np.asarray(weight).astype(np.int32)),
                                     xmin=x0, ymin=y0)
    if guess is not None:
        kw["guess_centroid"] = galsim.PositionD(*guess)
    try:
        m = galsim.hsm.FindAdaptiveMom(img, **kw)
    except (galsim.GalSimError, RuntimeError, ValueError):
        return None
    if m.moments_status != 0 or not m.moments_sigma > 0:
        return None
    e1, e2 = m.observed_shape.e1, m.observed_shape.e2
    esq = e1 * e1 + e2 * e2
    if not esq < 1:
        return None
    t_det = 2.0 * m.moments_sigma ** 2
    t = t_det / np.sqrt(1.0 - esq)  # det(M)^(1/4) = sigma
    return {"x": m.moments_centroid.x, "y": m.moments_centroid.y, "sigma": m.moments_sigma,
            "e1": e1, "e2": e2, "t_det": t_det, "t": t, "mxx": 0.5 * t * (1 + e1),
            "myy": 0.5 * t * (1 - e1), "mxy": 0.5 * t * e2}


def _hsm(stamp, weight, guess, x0, y0):
    """The catalog's row of :func:`hsm_moments` (x, y, mxx, myy, mxy, t, e1, e2, sigma)."""
    m = hsm_moments(stamp, weight=weight, guess=guess, origin=(x0, y0))
    if m is None:
        return None
    return (m["x"], m["y"], m["mxx"], m["myy"], m["mxy"], m["t"], m["e1"], m["e2"], m["sigma"])


class StarDetections:
    """Detections of :func:`detect_stars`, reusable on corrected copies of the image.

    Attributes
    ----------
    labels : ndarray of int
        Segmentation map (0 = no source).
    centroids : ndarray, shape (n, 2)
        (x, y) of each segment's smoothed-image centroid (px), row k for label k + 1.
    blended : set of int
        Labels of segments with several significant peaks.
    background, rms : ndarray
        Background and its rms (e per px).
    bad : ndarray of bool
        Masked or non-finite pixels of the detection image.
    saturation : float or None
        Saturation level (e).
    gain : float
        e/ADU applied to the detection image.
    settings : dict
        Detection settings.
    saturated : ndarray of bool or None
        Pixels known to be saturated whatever their value (the ``saturated``
        argument or the exposure's SAT plane), or None.
    """

    def __init__(self, labels, centroids, blended, background, rms, bad, saturation, gain,
                 settings, saturated=None):
        self.labels = labels
        self.centroids = centroids
        self.blended = blended
        self.background = background
        self.rms = rms
        self.bad = bad
        self.saturation = saturation
        self.gain = gain
        self.settings = settings
        self.saturated = saturated

    @property
    def shape(self):
        """(ny, nx) of the detection image."""
        return self.labels.shape


def detect_stars(exposure, *, gain=None, mask=None, saturation=None, saturated=None,
                 threshold=5.0, n_pixels=9, kernel_fwhm=3.0, box_size=64, deblend=True):
    """Background, segmentation and blend flags of the sources of an exposure.

    Steps 1-3 of the module docstring; :func:`measure_stars` measures the
    sources. Detections of an image can be reused to measure the same
    sources on a corrected copy of it (same stars, same stamps and weights),
    so that the change of each star's moments is the correction's alone.

    Parameters
    ----------
    exposure, gain, mask, saturation, saturated
        See :func:`measure_stars`.
    threshold, n_pixels, kernel_fwhm, box_size, deblend
        See :func:`measure_stars`.

    Returns
    -------
    StarDetections

    Raises
    ------
    ValueError
        For a blank or non-finite image, an image too small, or no detection.
    """
    image = to_electrons(exposure, gain=gain, mask=mask, saturation=saturation)
    image.warn()
    data, bad, sat_e, g, sat_pix = (image.data, image.bad, image.saturation, image.gain,
                                    image.sat_plane)
    return _detect(data, bad, sat_e, g, threshold=threshold, n_pixels=n_pixels,
                   kernel_fwhm=kernel_fwhm, box_size=box_size, deblend=deblend,
                   saturated=_saturated_pixels(saturated, sat_pix, data.shape))


def _detect(data, bad, sat_e, g, *, threshold, n_pixels, kernel_fwhm, box_size, deblend,
            saturated=None):
    """:func:`detect_stars` of an image already in electrons."""
    # photutils: heavy (1-2 s to import), only when stars are detected
    from photutils.segmentation import detect_sources, make_2dgaussian_kernel
    from photutils.utils.exceptions import NoDetectionsWarning

    if bad.all():
        raise InputError("image has no usable pixel (all masked or non-finite)")
    good_vals = data[~bad]
    if np.ptp(good_vals) == 0:
        raise InputError(f"image is blank (every usable pixel equals {good_vals[0]:g}); "
                         "no stars can be measured")
    clean = np.where(bad, 0.0, data)
    bkg, rms = _background(clean, bad, box_size)
    if not np.all(np.isfinite(rms)) or np.median(rms) <= 0:
        raise InputError("background rms is zero or undefined: the image has no noise "
                         "(blank or synthetic?); give a noisy image in electrons")
    sub = np.where(bad, 0.0, data - bkg)
    kernel = np.asarray(make_2dgaussian_kernel(kernel_fwhm, size=2 * int(kernel_fwhm) + 1))
    kernel = kernel / kernel.sum()
    conv = fftconvolve(sub, kernel, mode="same")
    # noise of the smoothed image: rms * sqrt(sum k^2)
    thr = threshold * rms * np.sqrt(np.sum(kernel ** 2))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NoDetectionsWarning)  # reported as an error below
        segm = detect_sources(conv, thr, int(n_pixels), mask=bad)
    if segm is None or segm.n_labels == 0:
        raise InputError(f"no sources detected above {threshold:g} sigma: no stars to measure "
                         "(check the image, its unit/gain and the threshold)")
    labels = segm.data
    split = _multi_peak_segments(conv, labels, thr, bad) if deblend else set()
    cen = ndimage.center_of_mass(np.clip(conv, 0, None), labels,
                                 index=np.arange(1, labels.max() + 1))
    centroids = np.array([[c[1], c[0]] for c in cen], float).reshape(-1, 2)
    return StarDetections(labels, centroids, split, bkg, rms, bad, sat_e, g,
                          dict(threshold=float(threshold), n_pixels=int(n_pixels),
                               kernel_fwhm=float(kernel_fwhm), box_size=int(box_size)),
                          saturated=saturated)


def measure_stars(exposure, *, gain=None, mask=None, saturation=None, saturated=None,
                  threshold=5.0, n_pixels=9, kernel_fwhm=3.0, box_size=64, stamp=25,
                  aperture_radius=10.0, isolation=12.0, size_tolerance=0.3, deblend=True,
                  detections=None, progress=False):
    """Detect stars and measure flux, centroid, adaptive moments and flags.

    Parameters
    ----------
    exposure : ndarray, CCDData, NDData or path
        The image (electrons, or ADU with ``gain``); read by
        :func:`~lsst_bfdrift.images.electrons.to_electrons`.
    gain : float, optional
        e/ADU for images in ADU.
    mask : array_like of bool, optional
        Bad pixels (True = bad).
    saturation : float, optional
        Saturation level in the image's unit (default: SATURATE keyword, else none).
    saturated : array_like of bool, optional
        Pixels known to be saturated whatever their value (True =
        saturated; e.g. an LSST exposure's SAT plane, whose pixels ISR may
        have interpolated over). Default: the SAT plane of an LSST exposure
        or file, else those of ``detections``, else none. Stars with such a
        pixel in their segment or aperture are flagged saturated (not
        masked, though the pixels are not used).
    threshold : float, optional
        Detection threshold in units of the background rms (per smoothed pixel).
    n_pixels : int, optional
        Smallest number of connected pixels of a detection.
    kernel_fwhm : float, optional
        FWHM (px) of the Gaussian smoothing before detection.
    box_size : int, optional
        Background box (px).
    stamp : int, optional
        Side of the measurement cutout (px, odd).
    aperture_radius : float, optional
        Radius of the flux aperture (px).
    isolation : float, optional
        A source with another source's centroid closer than this (px) is blended.
    size_tolerance : float, optional
        Sources whose T differs from the median of their 8 nearest good
        neighbours by more than this fraction are flagged FLAG_NOT_STAR
        (only applied when at least 5 good sources exist).
    deblend : bool, optional
        Look for several peaks in one segment (flagged blended).
    detections : StarDetections, optional
        Detections of this image or of an uncorrected copy of it (same
        shape), from :func:`detect_stars`: the sources are measured where
        they were detected, with that background and those flags
        (detection options are then ignored; ``mask`` and masked pixels of
        ``exposure`` still count).
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    astropy.table.QTable
        One row per detection: ``id``, ``x``, ``y`` (px, 0-based pixel
        centres, x the serial axis), ``flux``, ``flux_err`` (e), ``snr``,
        ``mag`` (instrumental, -2.5 log10 flux/e), ``peak`` (e, with
        background), ``ixx``, ``iyy``, ``ixy``, ``T`` (px^2), ``sigma`` (px,
        det(M)^(1/4)), ``e1``, ``e2``, ``background`` (e/px), ``flags``, one
        boolean column per flag (see the module docstring) and ``use``.
        ``meta`` holds ``gain``, ``saturation`` (e), ``background_rms`` (e,
        median) and the settings.

    Raises
    ------
    ValueError
        For a blank or non-finite image, an image too small, or no detection.

    Examples
    --------
    A GalSim Gaussian star (sigma 1.5 px) with Poisson noise: its adaptive
    moments give T = 2 sigma^2 plus the pixel's 1/6:

    >>> import galsim
    >>> import numpy as np
    >>> from lsst_bfdrift.catalogs.catalog import measure_stars
    >>> star = galsim.Gaussian(sigma=1.5, flux=4e5).drawImage(nx=48, ny=48, scale=1.0)
    >>> img = np.random.default_rng(1).poisson(star.array + 1000.0).astype(float)
    >>> cat = measure_stars(img)
    >>> len(cat), bool(cat["use"][0]), round(float(cat["T"][0].value), 1)
    (1, True, 4.7)
    """
    image = to_electrons(exposure, gain=gain, mask=mask, saturation=saturation)
    image.warn()
    data, bad, sat_e, g, sat_pix = (image.data, image.bad, image.saturation, image.gain,
                                    image.sat_plane)
    sat_pix = _saturated_pixels(saturated, sat_pix, data.shape)
    if detections is None:
        detections = _detect(data, bad, sat_e, g, threshold=threshold, n_pixels=n_pixels,
                             kernel_fwhm=kernel_fwhm, box_size=box_size, deblend=deblend,
                             saturated=sat_pix)
    else:
        if data.shape != detections.shape:
            raise InputError(f"image shape {data.shape} differs from the detections' "
                             f"{detections.shape}")
        bad = bad | detections.bad
        sat_e = detections.saturation if sat_e is None else sat_e
        sat_pix = detections.saturated if sat_pix is None else sat_pix
    labels = detections.labels
    bkg, rms = detections.background, detections.rms
    split = detections.blended
    cen_x, cen_y = detections.centroids[:, 0], detections.centroids[:, 1]
    stamp = int(stamp) | 1
    half = stamp // 2
    sub = np.where(bad, 0.0, data - bkg)
    ny, nx = data.shape
    objs = ndimage.find_objects(labels)
    rows = []
    yy, xx = np.mgrid[-half:half + 1, -half:half + 1]
    with ProgressBar(len(objs), "stars", enabled=progress) as bar:
        for lab, sl in enumerate(objs, start=1):
            bar(1)
            if sl is None:
                continue
            cx, cy = cen_x[lab - 1], cen_y[lab - 1]
            if not (np.isfinite(cx) and np.isfinite(cy)):
                continue
            flags = 0
            own = labels[sl] == lab
            raw = data[sl][own]
            if sat_e is not None and np.nanmax(np.where(np.isfinite(raw), raw, -np.inf)) >= sat_e:
                flags |= FLAG_SATURATED
            if sat_pix is not None and np.any(sat_pix[sl][own]):
                flags |= FLAG_SATURATED
            # blended: deblended child, touching segment, or a close neighbour
            if lab in split:
                flags |= FLAG_BLENDED
            grown = ndimage.binary_dilation(np.pad(own, 1))
            box = labels[max(sl[0].start - 1, 0):sl[0].stop + 1,
                          max(sl[1].start - 1, 0):sl[1].stop + 1]
            gy0 = 1 if sl[0].start - 1 < 0 else 0
            gx0 = 1 if sl[1].start - 1 < 0 else 0
            gsub = grown[gy0:gy0 + box.shape[0], gx0:gx0 + box.shape[1]]
            if np.any((box[gsub] != 0) & (box[gsub] != lab)):
                flags |= FLAG_BLENDED
            d2 = (cen_x - cx) ** 2 + (cen_y - cy) ** 2
            d2[lab - 1] = np.inf
            if np.nanmin(d2) < isolation ** 2:
                flags |= FLAG_BLENDED
            ix, iy = int(np.floor(cx + 0.5)), int(np.floor(cy + 0.5))
            x0, y0 = ix - half, iy - half
            if x0 < 0 or y0 < 0 or ix + half >= nx or iy + half >= ny:
                flags |= FLAG_EDGE
                rows.append(_empty_row(lab, cx, cy, flags | FLAG_MOMENTS))
                continue
            ssl = (slice(y0, y0 + stamp), slice(x0, x0 + stamp))
            st = sub[ssl]
            other = (labels[ssl] != 0) & (labels[ssl] != lab)
            badst = bad[ssl]
            r2 = (xx + ix - cx) ** 2 + (yy + iy - cy) ** 2
            inap = r2 <= aperture_radius ** 2
            satst = np.zeros_like(badst) if sat_pix is None else sat_pix[ssl]
            if np.any(satst & inap & ~other):
                flags |= FLAG_SATURATED
            if np.any(badst & inap & ~satst):  # saturated pixels count as saturation
                flags |= FLAG_MASKED
            if sat_e is not None and np.any((data[ssl] >= sat_e) & inap & ~other):
                flags |= FLAG_SATURATED
            use_pix = inap & ~other & ~badst
            flux = float(st[use_pix].sum())
            var = rms[ssl] ** 2 + np.clip(st, 0, None)
            flux_err = float(np.sqrt(var[use_pix].sum()))
            peak = float(np.max(np.where(np.isfinite(raw), raw, -np.inf)))
            m = _hsm(np.where(badst | other, 0.0, st), ~(badst | other), (cx, cy), x0, y0)
            if m is None or not flux > 0:
                rows.append(_empty_row(lab, cx, cy, flags | FLAG_MOMENTS, flux, flux_err, peak,
                                       float(bkg[iy, ix])))
                continue
            mx, my, ixx, iyy, ixy, t, e1, e2, sig = m
            if not (0.05 < t < stamp ** 2 / 4) or max(abs(mx - cx), abs(my - cy)) > half / 2:
                flags |= FLAG_MOMENTS
            rows.append(dict(id=lab, x=mx, y=my, flux=flux, flux_err=flux_err, peak=peak,
                             ixx=ixx, iyy=iyy, ixy=ixy, T=t, sigma=sig, e1=e1, e2=e2,
                             background=float(bkg[iy, ix]), flags=flags))
    tab = _to_table(rows)
    _flag_locus(tab, size_tolerance)
    for bit, name in FLAG_NAMES.items():
        tab[name] = (np.asarray(tab["flags"]) & bit) != 0
    tab["use"] = np.asarray(tab["flags"]) == 0
    tab.meta.update(gain=g, saturation=sat_e, background_rms=float(np.median(rms)),
                    threshold=detections.settings["threshold"], stamp=stamp,
                    aperture_radius=float(aperture_radius), isolation=float(isolation),
                    moments="galsim.hsm.FindAdaptiveMom (adaptive)",
                    shape=[int(ny), int(nx)])
    return tab


def _multi_peak_segments(conv, labels, thr, bad):
    """Labels of segments holding more than one significant peak (saddle test)."""
    # photutils: heavy (1-2 s to import), only when stars are detected
    from photutils.detection import find_peaks

    peaks = find_peaks(conv, thr, box_size=5, mask=bad)
    if peaks is None or len(peaks) < 2:
        return set()
    xp = np.asarray(peaks["x_peak"], int)
    yp = np.asarray(peaks["y_peak"], int)
    hp = np.asarray(peaks["peak_value"], float)
    lab = labels[yp, xp]
    thr_map = np.broadcast_to(thr, conv.shape)
    out = set()
    for seg in np.unique(lab[lab > 0]):
        idx = np.flatnonzero(lab == seg)
        if idx.size < 2:
            continue
        main = idx[np.argmax(hp[idx])]
        for k in idx:
            if k == main:
                continue
            n = int(max(abs(xp[k] - xp[main]), abs(yp[k] - yp[main]))) * 2 + 2
            xs = np.rint(np.linspace(xp[k], xp[main], n)).astype(int)
            ys = np.rint(np.linspace(yp[k], yp[main], n)).astype(int)
            saddle = conv[ys, xs].min()
            # prominence above the saddle larger than the detection threshold
            if hp[k] - saddle > thr_map[yp[k], xp[k]]:
                out.add(int(seg))
                break
    return out


def _empty_row(lab, cx, cy, flags, flux=np.nan, flux_err=np.nan, peak=np.nan,
               background=np.nan):
    return dict(id=lab, x=cx, y=cy, flux=flux, flux_err=flux_err, peak=peak, ixx=np.nan,
                iyy=np.nan, ixy=np.nan, T=np.nan, sigma=np.nan, e1=np.nan, e2=np.nan,
                background=background, flags=flags)


def _to_table(rows):
    names = ("id", "x", "y", "flux", "flux_err", "peak", "ixx", "iyy", "ixy", "T", "sigma",
             "e1", "e2", "background", "flags")
    cols = {k: np.array([r[k] for r in rows], dtype=np.int64 if k in ("id", "flags")
                        else np.float64) for k in names}
    flux = cols["flux"]
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = np.where(cols["flux_err"] > 0, flux / cols["flux_err"], np.nan)
        mag = np.where(flux > 0, -2.5 * np.log10(np.where(flux > 0, flux, 1.0)), np.nan)
    units = dict(x=u.pix, y=u.pix, flux=u.electron, flux_err=u.electron, peak=u.electron,
                 ixx=u.pix ** 2, iyy=u.pix ** 2, ixy=u.pix ** 2, T=u.pix ** 2, sigma=u.pix,
                 background=u.electron / u.pix ** 2)
    tab = QTable()
    for k in ("id", "x", "y", "flux", "flux_err"):
        tab[k] = cols[k] * units[k] if k in units else cols[k]
    tab["snr"] = snr
    tab["mag"] = mag * u.mag
    for k in ("peak", "ixx", "iyy", "ixy", "T", "sigma", "e1", "e2", "background", "flags"):
        tab[k] = cols[k] * units[k] if k in units else cols[k]
    return tab


def _flag_locus(tab, tol, k=8):
    """Flag sources off the local stellar size locus (median T of k nearest good ones)."""
    if len(tab) == 0:
        return
    t = np.asarray(tab["T"].value)
    x = np.asarray(tab["x"].value)
    y = np.asarray(tab["y"].value)
    flags = np.asarray(tab["flags"]).copy()
    ref = np.flatnonzero((flags == 0) & np.isfinite(t) & (np.asarray(tab["snr"]) > 20))
    if ref.size < 5:
        return
    for i in range(len(tab)):
        if not np.isfinite(t[i]) or flags[i] & (FLAG_EDGE | FLAG_MOMENTS):
            continue
        cand = ref[ref != i]
        d = (x[cand] - x[i]) ** 2 + (y[cand] - y[i]) ** 2
        near = cand[np.argsort(d)[:k]]
        tloc = np.median(t[near])
        if abs(t[i] / tloc - 1.0) > tol:
            flags[i] |= FLAG_NOT_STAR
    tab["flags"] = flags
