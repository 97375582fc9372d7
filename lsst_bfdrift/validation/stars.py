"""Validation of the corrections on sky-like stars drawn by galsim.SiliconSensor.

GalSim's SiliconSensor is an independent brighter-fatter simulator. Each star
is drawn once by photon shooting; sky photons (uniform, Poisson number) are
mixed in at random times, and the photons are accumulated twice with the
same random seed, with ``strength=1`` and ``strength=1e-9`` (identical
diffusion, only the brighter-fatter effect differs; technique of
MODEL_NOTES.md section 8).

The sky must be collected through the sensor like the star: in a real
exposure the star's shrunken pixels collect less sky too, and every
correction (rightly) moves sky flux back along with the star's. Adding the
sky to the images after the BF simulation (``sky_through_sensor=False``)
shifts every correction's residual size slope by about
-4 % of the uncorrected slope for a sky of 1000 e (``docs/benchmarks.rst``).

Every correction method is applied to the BF image, and its adaptive
moments (galsim.hsm) are compared with those of the BF-free twin: the
fractional size change dT/T and the ellipticity change de1, de2 are fitted
against flux (straight lines through the origin, slopes per 1e5 e, errors
from the scatter).
"""

import numpy as np

from lsst_bfdrift.catalogs.catalog import hsm_moments
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.simulation.galsim_twins import accumulate_twins, shoot_stamp_photons, sky_box
from lsst_bfdrift.simulation.stars import make_psf
from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.utils.errors import ComputationError, InputError

__all__ = ["draw_star_pairs", "star_moments", "slope_through_origin", "per_star_residuals",
           "residual_slopes", "validate_stars"]


def draw_star_pairs(n_stars, *, sensor="lsst_itl_50_8", psf="moffat", fwhm=(0.6, 0.9),
                    emax=0.05, flux=(1e4, 1.5e6), sky=1000.0, stamp=41, pixel_scale=0.2,
                    seed=20151, sky_through_sensor=True, sky_radius=8, updates=1000,
                    min_nrecalc=100, progress=False):
    """Stars drawn by galsim.SiliconSensor with and without the BF effect.

    Parameters
    ----------
    n_stars : int
        Number of stars.
    sensor : str, optional
        GalSim sensor name.
    psf : {'moffat', 'kolmogorov', 'gaussian'}, optional
        PSF family.
    fwhm : tuple, optional
        Range of FWHM (arcsec), uniform.
    emax : float, optional
        Largest PSF ellipticity ``|e|`` (random orientation).
    flux : tuple, optional
        Range of fluxes (e), log-uniform.
    sky : float, optional
        Sky level (e per pixel of nominal area).
    sky_through_sensor : bool, optional
        True: sky photons (uniform over the stamp plus a 3-pixel margin, so
        that diffusion is balanced at the border) are accumulated with the
        star's photons in random order, in both twins. False: a Poisson sky
        image is added to both twins after the simulation (no BF on the
        sky; kept to demonstrate the bias it causes).
    sky_radius : int, optional
        With ``sky_through_sensor``, the sky is collected through the sensor
        in the central (2 r + 1)^2 pixels (plus a 3-pixel margin for
        diffusion), where the star's boundary shifts matter (> 1e-4 px^2 of
        swept area), and added as a Poisson image, identical in both twins,
        outside. This keeps GalSim's distortion updates (every ``nrecalc``
        photons, over every charged pixel) affordable; None: everywhere.
        GalSim's boundaries reach 4 pixels from an aggressor, so beyond the
        star's core plus 4 pixels no pixel moves.
    updates : int, optional
        GalSim recomputes the boundaries every ``nrecalc = max(min_nrecalc,
        N / updates)`` photons (N: star plus sky photons). Boundaries lag by
        up to one interval, which weakens the simulated effect by about
        1 / updates relative to continuous accumulation. The default 1000
        (with ``min_nrecalc=100``) is converged: going from 100 to 1000
        updates per exposure shifts every method's residual size slope by
        +0.92 +- 0.04 % of the uncorrected slope, from 1000 to 3000 by only
        +0.05 % more (``benchmarks/correction/probe_validation_cadence_results.txt``).
        It costs about 2.4 times the drawing time of 100 updates.
    min_nrecalc : float, optional
        Smallest ``nrecalc`` (photons). GalSim's own default, 1e4, would
        cap faint stars at a few updates per exposure.
    stamp : int, optional
        Stamp side (pixels).
    pixel_scale : float, optional
        arcsec per pixel.
    seed : int, optional
        Seed of everything.
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    list of dict
        ``bf``, ``truth`` (arrays, e), ``flux``, ``fwhm``.
    """
    if int(n_stars) < 1:
        raise InputError(f"n_stars must be positive, got {n_stars!r}")
    rng = np.random.default_rng(seed)
    out = []
    with ProgressBar(int(n_stars), "galsim stars", enabled=progress) as bar:
        for _ in range(int(n_stars)):
            f = float(np.exp(rng.uniform(np.log(flux[0]), np.log(flux[1]))))
            fw = float(rng.uniform(*fwhm))
            e = float(rng.uniform(0, emax))
            beta = float(rng.uniform(0, 180))
            prof = make_psf(psf, fw, e=e, beta=beta).withFlux(f)
            s1, s2, s3 = (int(v) for v in rng.integers(1, 2**30, 3))
            rng_sky = np.random.default_rng(s3)  # the stars do not depend on the sky
            x, y, fl = shoot_stamp_photons(prof, stamp, pixel_scale=pixel_scale, seed=s1,
                                     offset=rng.uniform(-0.5, 0.5, 2))
            lo, hi, inner = sky_box(stamp, sky_radius)
            images, _ = accumulate_twins(
                x, y, fl, (1.0, 1e-9), sensor=sensor, seed=s2, stamp=stamp,
                pixel_scale=pixel_scale, sky=sky if sky_through_sensor else 0.0, box=(lo, hi),
                rng=rng_sky, updates=updates, min_nrecalc=min_nrecalc)
            noise = rng_sky.poisson(sky, (stamp, stamp)).astype(float)
            if sky_through_sensor:  # outside the region collected through the sensor
                outside = np.ones((stamp, stamp), bool)
                outside[inner, inner] = False
                noise = np.where(outside, noise, 0.0)
            out.append({"bf": images[0] + noise, "truth": images[1] + noise, "flux": f,
                        "fwhm": fw})
            bar(1)
    return out


def star_moments(arr, sky):
    """Adaptive size and ellipticity of a star stamp after its sky.

    Parameters
    ----------
    arr : array_like
        The stamp (e).
    sky : float
        Sky level subtracted first (e per pixel).

    Returns
    -------
    tuple of float or None
        (T_det = 2 sigma^2, e1, e2) of
        :func:`~lsst_bfdrift.catalogs.catalog.hsm_moments`; None when the
        moments fail.
    """
    m = hsm_moments(np.asarray(arr, float) - sky, guess_sig=5.0)
    return None if m is None else (m["t_det"], m["e1"], m["e2"])


def slope_through_origin(x, y):
    """Least-squares slope of y = s x through the origin, and its error from the scatter.

    Parameters
    ----------
    x, y : array_like, shape (n,)

    Returns
    -------
    slope, error : float
        s = sum(x y) / sum(x^2) and sqrt(sum(r^2) / (n - 1) / sum(x^2)), r
        the residuals (n - 1 at least 1).
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    s = np.sum(x * y) / np.sum(x * x)
    r = y - s * x
    err = np.sqrt(np.sum(r * r) / max(len(x) - 1, 1) / np.sum(x * x))
    return float(s), float(err)


def per_star_residuals(pairs, template, *, methods=("coulton18", "astier23", "drift"),
                       sky=1000.0, progress=False):
    """Per-star size and ellipticity residuals before and after each correction.

    Parameters
    ----------
    pairs : list of dict
        From :func:`draw_star_pairs`.
    template : DistortionTemplate
        Green's function used by the corrections.
    methods : sequence of str or dict, optional
        Task methods to compare, or a mapping label -> Task config overrides
        (e.g. ``{"drift mean2": {"method": "drift", "density": "mean2"}}``).
    sky : float, optional
        Sky level subtracted before measuring moments (e).
    progress : bool, optional
        Progress bar.

    Returns
    -------
    fluxes : ndarray, shape (n,)
        Star fluxes per 1e5 e (NaN for a star unmeasurable in any image).
    rows : dict
        For ``uncorrected`` and each label, an (n, 3) array of
        T / T_truth - 1, e1 - e1_truth and e2 - e2_truth (NaN likewise).
    """

    configs = (dict(methods) if isinstance(methods, dict)
               else {m: {"method": m} for m in methods})
    tasks = {k: BrighterFatterDriftTask(
        config=BrighterFatterDriftConfig(compute_geometry=False, **kw), template=template)
        for k, kw in configs.items()}
    rows = {k: [] for k in ("uncorrected",) + tuple(tasks)}
    fluxes = []
    with ProgressBar(len(pairs), "validate", enabled=progress) as bar:
        for p in pairs:
            truth = star_moments(p["truth"], sky)
            meas = {"uncorrected": star_moments(p["bf"], sky)}
            for m, t in tasks.items():
                meas[m] = star_moments(t.run(p["bf"]).exposure, sky)
            bar(1)
            ok = truth is not None and all(v is not None for v in meas.values())
            fluxes.append(p["flux"] / 1e5 if ok else np.nan)
            for k, v in meas.items():
                rows[k].append((v[0] / truth[0] - 1.0, v[1] - truth[1], v[2] - truth[2])
                               if ok else (np.nan,) * 3)
    return np.array(fluxes, float), {k: np.array(v, float).reshape(-1, 3)
                                     for k, v in rows.items()}


def residual_slopes(fluxes, rows):
    """Slopes through the origin of :func:`per_star_residuals` (measurable stars).

    Returns
    -------
    dict
        For each key of ``rows``: ``size_slope`` (fractional change of
        T = Ixx + Iyy per 1e5 e) and ``e_slope`` (change of e1 per 1e5 e),
        ``e2_slope``, their ``*_err``, and ``n_stars`` used; for the keys
        other than ``uncorrected`` and ``astier23`` (when present) also
        ``size_slope_minus_astier23`` and its error, the slope of the per-star
        difference (paired on the same images, so far more precise than the
        difference of the two slopes).
    """
    ok = np.isfinite(fluxes)
    n = int(ok.sum())
    if n < 3:
        raise ComputationError(f"only {n} stars had measurable moments; need >= 3")
    f = fluxes[ok]
    ref = rows["astier23"][ok] if "astier23" in rows else None
    out = {}
    for k, v in rows.items():
        v = v[ok]
        s, se = slope_through_origin(f, v[:, 0])
        e1, e1e = slope_through_origin(f, v[:, 1])
        e2, e2e = slope_through_origin(f, v[:, 2])
        out[k] = {"size_slope": s, "size_slope_err": se, "e_slope": e1, "e_slope_err": e1e,
                  "e2_slope": e2, "e2_slope_err": e2e, "n_stars": n}
        if ref is not None and k not in ("uncorrected", "astier23"):
            # paired: slope of the per-star difference, free of the star-to-star scatter
            d, de = slope_through_origin(f, v[:, 0] - ref[:, 0])
            out[k].update(size_slope_minus_astier23=d, size_slope_minus_astier23_err=de)
    return out


def validate_stars(pairs, template, *, methods=("coulton18", "astier23", "drift"), sky=1000.0,
                   progress=False):
    """Size and ellipticity slopes before and after each correction.

    :func:`per_star_residuals` (whose parameters these are) then
    :func:`residual_slopes`.

    Returns
    -------
    dict
        See :func:`residual_slopes`.
    """
    return residual_slopes(*per_star_residuals(pairs, template, methods=methods, sky=sky,
                                               progress=progress))
