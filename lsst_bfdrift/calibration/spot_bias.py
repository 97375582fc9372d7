"""The drift correction's own error on a spot series' design, from photons.

A spot fit asks the template for the correction that leaves no size, e1 or
e2 slope on the spots. The drift correction is not exact: it estimates the
charge density on each pixel edge from the pixel values around it, and on
spots of about a pixel's sigma, sampled at little more than the Nyquist
rate, that estimate is off. Drawn photon by photon through moving pixel
boundaries (:class:`~lsst_bfdrift.simulation.stars.StarSimulation`) and
corrected with the *same* template, a Gaussian spot of sigma 1 px keeps
about -2 % of its fixed-weight size growth (over-corrected), one of 2 px
about 0 % (``benchmarks/calibration/spots_truth.py``, where GalSim's own
file on GalSim's spots leaves the two sizes 1.8-3.0 % points apart the same
way). A fit that nulls the slopes of small spots then tilts the template by
that much, and the stars, sampled like the 2 px spots, inherit the tilt.

:func:`spot_correction_bias` measures that error for a series: spots of
the series' own faint-limit shape (the median of its spots), at its own
flux levels, drawn with a template (the flats template, the best known
before the fit: the error is a fraction of the effect, so a template a few
% off changes it by a few % of itself), on a grid of sub-pixel centres,
each paired with the same photons on square pixels, corrected by drift with
that template and measured with the series' fixed weight. The slopes of
corrected minus paired truth are the correction's own slopes on that
design; :class:`~lsst_bfdrift.calibration.spot_fit.SpotField` subtracts them
from what a correction leaves on the measured spots (``bias``), so that the
fit asks for what the correction leaves on a right template instead of 0.

This is the package's forward model checked against itself at the pixel
level (a consistency term, not a measurement): it carries no sensor physics
beyond the template's, and it is stated in the fit's record.
"""

import time

import numpy as np
from astropy import units as u
from astropy.nddata import CCDData

from lsst_bfdrift.catalogs.spots import fixed_weight_moments
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.simulation.stars import StarSimulation
from lsst_bfdrift.utils.errors import InputError

__all__ = ["spot_correction_bias", "BIAS_QUANTITIES"]

#: The slopes whose correction error is measured (those a spot fit nulls).
BIAS_QUANTITIES = ("size", "e1", "e2")


def _column(catalog, name):
    return np.asarray(getattr(catalog[name], "value", catalog[name]), float)


def _series_design(series):
    """Flux levels (median flux of each image's used spots, e, ascending) and the
    continuous faint-limit covariance (px^2) of the series' spots."""
    cat = series.catalog
    use = np.asarray(cat["use"], bool)
    if not use.any():
        raise InputError("the spot series has no usable spot row to take its design from")
    image, flux = np.asarray(cat["image"]), _column(cat, "flux")
    levels = np.array(sorted(float(np.median(flux[use & (image == i)]))
                             for i in np.unique(image[use])))
    faint = use & (image == image[use][np.argmin(flux[use])])
    m = [float(np.median(_column(cat, k)[faint])) for k in ("ixx", "iyy", "ixy")]
    # the deweighted moments of a pixelated spot include the pixel's own 1/12 px^2
    cov = np.array([[m[0] - 1 / 12, m[2]], [m[2], m[1] - 1 / 12]])
    if np.any(np.linalg.eigvalsh(cov) <= 0):
        raise InputError(f"the series' faint-limit moments (ixx, iyy, ixy) = {m} px^2 are not "
                         "those of a resolved spot")
    return levels, cov


def spot_correction_bias(series, template, *, centres=3, quantities=BIAS_QUANTITIES,
                         seed=20151, update_every=1000, max_photons=3e7):
    """Slopes the drift correction leaves on a spot series' design drawn with ``template``.

    Parameters
    ----------
    series : SpotSeries
        The measured series: its levels, spot shape, weight and radius.
    template : DistortionTemplate
        Green's function of the simulation and of the correction.
    centres : int, optional
        Spots on a ``centres`` x ``centres`` grid of sub-pixel centres (the
        error depends on the pixel phase).
    quantities : sequence of {'size', 'e1', 'e2'}, optional
        The slopes measured.
    seed : int, optional
        Seed of the photons.
    update_every : int, optional
        Boundary updates every this many conversions at the top level
        (fewer photons per update below it: 1000 updates at most per spot).
    max_photons : float, optional
        Largest number of photons drawn in all (the top levels are kept and
        the faint ones left out beyond it; they weigh little in a slope).

    Returns
    -------
    dict
        Per quantity: (slope, error) per 1e5 e of corrected minus paired
        truth (the correction's own slope on this design; the error is the
        scatter of the per-centre slopes); and ``levels`` (e), ``covariance``
        (px^2, the drawn spots' continuous Gaussian), ``n_spots``, ``seconds``.

    Raises
    ------
    InputError
        ``centres`` below 1, or a series with no usable row or an
        unresolved faint-limit shape.
    """
    if int(centres) != centres or centres < 1:
        raise InputError(f"centres must be a positive integer, got {centres!r}")
    quantities = tuple(quantities)
    t0 = time.perf_counter()
    levels, cov = _series_design(series)
    while levels.size > 1 and levels.sum() * centres ** 2 > max_photons:
        levels = levels[1:]
    grid = series.grid
    side = 2 * (int(np.ceil(grid.radius)) + 2 + template.center) + 1
    c = side // 2
    task = BrighterFatterDriftTask(
        config=BrighterFatterDriftConfig(method="drift", compute_geometry=False),
        template=template)
    rng = np.random.default_rng(seed)
    g = (np.arange(centres) + 0.5) / centres - 0.5
    slopes = {q: [] for q in quantities}
    every = max(1, int(round(levels[-1] / update_every)))
    for ox in g:
        for oy in g:
            diff = {q: [] for q in quantities}
            for level in levels:
                n = int(round(level))
                xy = rng.multivariate_normal((c + ox, c + oy), cov, size=n)
                sim = StarSimulation(template, stamp_size=side, update_every=every)
                sim.add(xy[:, 0], xy[:, 1])
                out = task.run(CCDData(sim.image, unit=u.electron)).exposure
                m = [fixed_weight_moments(a, weight_sigma=grid.weight_sigma, radius=grid.radius,
                                          center=(c + ox, c + oy))
                     for a in (sim.nominal_image, np.asarray(out.data, float))]
                for q in quantities:
                    diff[q].append(m[1][q] - m[0][q])
            f = levels / 1e5
            for q in quantities:  # paired: zero at zero flux, a slope through the origin
                slopes[q].append(float(np.dot(f, diff[q]) / np.dot(f, f)))
    k = centres * centres
    res = {q: (float(np.mean(v)), float(np.std(v, ddof=1) / np.sqrt(k)) if k > 1 else 0.0)
           for q, v in slopes.items()}
    res.update(levels=levels, covariance=cov, n_spots=k, seconds=time.perf_counter() - t0)
    return res
