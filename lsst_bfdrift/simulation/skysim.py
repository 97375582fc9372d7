"""Sky-like star fields drawn by galsim.SiliconSensor (test and demonstration data).

A field has a flat sky background with Poisson noise, Gaussian read noise,
and stars with a spatially varying PSF (Moffat, FWHM rising linearly along
x, PSF ellipticity e1 varying linearly along y and e2 along x), fluxes
log-uniform in a range, at random positions at least ``min_separation``
pixels apart. Each star is drawn by photon shooting into its own stamp and
its photons are accumulated by ``galsim.SiliconSensor`` with a chosen BF
``strength`` (1 = GalSim's sensor model; ~0 = no BF); the stamp is then
added to the field. Neighbouring stars are far apart, so drawing them in
separate stamps neglects only the BF interaction between stars. With
``twin=True`` the same photons are also accumulated with ``strength=1e-9``
and the same sensor seed (identical diffusion; MODEL_NOTES section 8), and
the same noise is added, giving a BF-free truth image.

The sky around each star is collected through the sensor with the star's
photons (:func:`lsst_bfdrift.simulation.galsim_twins.accumulate_twins`): in a real
exposure the star's shrunken pixels collect less sky as well, and every
correction (rightly) moves that sky flux back with the star's. Sky added
after the BF simulation is flux the simulation never redistributed, and made
both correction routes over-correct the size slope by 3-4 % on the field of
``benchmarks/stars/validate_sky.py`` (``docs/benchmarks.rst``). Each star's box
covers its central (2 ``sky_radius`` + 1)^2 pixels plus a 3-pixel margin and is
accumulated in its own image, with sky photons spread 3 px beyond it that
diffuse in (those landing outside are dropped), so the sky is uniform up to the
box edge (without this feed, diffusion leaves a -20 % / +20 % ring there). The
same sky photons go into every strength; a pixel's sky is collected once (where
the boxes of close neighbours overlap, which needs ``min_separation`` below the
box side, the shared part is not fed and keeps a weak ring); outside the boxes
the sky is a Poisson image, identical in all strengths (GalSim's boundaries
reach 4 pixels from an aggressor, so no pixel moves there). GalSim recomputes
its boundaries about ``updates`` times per star.
"""

import numpy as np
from astropy import units as u
from astropy.table import QTable

from lsst_bfdrift.simulation.galsim_twins import (SKY_MARGIN, accumulate_twins,
                                                  shoot_stamp_photons, sky_box)
from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.utils.errors import InputError

__all__ = ["simulate_star_field", "scale_template"]

#: strength used for "no BF" (GalSim needs a positive value)
_NULL_STRENGTH = 1e-9


def scale_template(template, strength):
    """Template whose boundary shifts per electron are ``strength`` times larger.

    Matches ``galsim.SiliconSensor(strength=strength)`` when ``template`` is
    the import of the same sensor (strength 1). The aggressor charge is kept.
    """
    s = float(strength)
    if not s > 0:
        raise InputError(f"strength must be positive, got {strength!r}")
    t = template.scaled(s)
    return type(template)(t.corner_d, t.vedge_d, t.hedge_d, t.fractions, template.charge,
                          vedge_t=t.vedge_t, hedge_t=t.hedge_t, meta=template.meta)


def _positions(rng, n, shape, margin, min_sep, max_tries=20000):
    ny, nx = shape
    pts = []
    tries = 0
    while len(pts) < n:
        tries += 1
        if tries > max_tries:
            raise InputError(f"cannot place {n} stars {min_sep} px apart in a {nx} x {ny} field; "
                             "use fewer stars or a smaller min_separation")
        x = rng.uniform(margin, nx - 1 - margin)
        y = rng.uniform(margin, ny - 1 - margin)
        if all((x - a) ** 2 + (y - b) ** 2 >= min_sep ** 2 for a, b in pts):
            pts.append((x, y))
    return np.array(pts)


def simulate_star_field(shape=(512, 512), n_stars=40, *, strength=1.0, twin=False,
                        sensor="lsst_itl_50_8", fwhm=(0.7, 0.95), e_range=0.04,
                        flux=(1e4, 1.5e6), sky=800.0, read_noise=5.0, min_separation=32,
                        stamp=31, pixel_scale=0.2, beta_moffat=3.5, sky_through_sensor=True,
                        sky_radius=8, updates=1000, min_nrecalc=100, seed=20151,
                        progress=False):
    """A star field drawn by galsim.SiliconSensor.

    Parameters
    ----------
    shape : tuple of int, optional
        (ny, nx) of the field (px).
    n_stars : int, optional
        Number of stars.
    strength : float or sequence of float, optional
        ``galsim.SiliconSensor`` strength (1 = nominal BF; 0 means 1e-9, no BF).
        With several strengths the same photons, sensor seeds and noise are
        used for each (paired images, returned in ``images``).
    twin : bool, optional
        Also return the BF-free twin (same photons, same noise).
    sensor : str, optional
        GalSim sensor name.
    fwhm : tuple, optional
        Moffat FWHM (arcsec) at x = 0 and at x = nx - 1 (linear in between).
    e_range : float, optional
        PSF e1 goes from -e_range (y = 0) to +e_range (top); e2 from
        +e_range / 2 (x = 0) to -e_range / 2.
    flux : tuple, optional
        Flux range (e), log-uniform.
    sky : float, optional
        Sky level (e per pixel of nominal area), Poisson.
    read_noise : float, optional
        Gaussian read noise (e rms).
    min_separation : float, optional
        Smallest distance between stars (px).
    stamp : int, optional
        Side of each star's drawing stamp (px).
    pixel_scale : float, optional
        arcsec per px.
    beta_moffat : float, optional
        Moffat index.
    sky_through_sensor : bool, optional
        True: the sky in each star's box is collected through the sensor with
        the star's photons (random order); False: the whole sky is a Poisson
        image added after the BF simulation (no BF on the sky; biases every
        correction's residual, kept to demonstrate it).
    sky_radius : int or None, optional
        Half-side (px) of the box, beyond the central pixel, where the sky is
        collected through the sensor (plus a 3-pixel margin); None: the whole
        stamp (larger values are clipped to the stamp).
    updates : float, optional
        GalSim recomputes the boundaries every ``nrecalc = max(min_nrecalc,
        N / updates)`` photons (N: a star's photons plus its sky photons).
        The default, about 1000 updates per star, is converged
        (``benchmarks/correction/probe_validation_cadence_results.txt``: 100 updates
        weaken the simulated effect by about 1 %).
    min_nrecalc : float, optional
        Smallest ``nrecalc`` (photons).
    seed : int, optional
        Seed of every random number.
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    dict
        ``image`` (e, float64; the first strength), ``images`` (one per
        strength), ``truth_image`` (BF-free twin or None),
        ``stars`` (QTable: ``x``, ``y`` (px), ``flux`` (e), ``fwhm`` (arcsec),
        ``psf_e1``, ``psf_e2``), ``sky`` (e per px), ``strength``.
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    ny, nx = (int(v) for v in shape)
    stamp = int(stamp)
    if ny < stamp or nx < stamp:
        raise InputError(f"field {nx} x {ny} is smaller than one stamp ({stamp} px)")
    if int(n_stars) < 0:
        raise InputError(f"n_stars must be >= 0, got {n_stars!r}")
    req = [float(v) for v in np.atleast_1d(strength)]
    if not req or min(req) < 0:
        raise InputError(f"strength must be >= 0, got {strength}")
    if stamp % 2 != 1:
        raise InputError(f"stamp must be odd, got {stamp}")
    if sky < 0 or not np.isfinite(sky):
        raise InputError(f"sky must be finite and >= 0, got {sky!r}")
    rng = np.random.default_rng(seed)
    half = stamp // 2
    pos = _positions(rng, int(n_stars), (ny, nx), half + 1, float(min_separation))
    strengths = [max(v, _NULL_STRENGTH) for v in req] + ([_NULL_STRENGTH] if twin else [])
    images = [np.zeros((ny, nx)) for _ in strengths]
    collected = np.zeros((ny, nx), bool) if sky_through_sensor and sky > 0 else None
    rows = []
    # accumulate_twins runs GalSim on one OpenMP thread (its threads spin on a busy machine)
    _draw(galsim, pos, rng, images, strengths, rows, progress, nx, ny, fwhm, e_range, flux,
          beta_moffat, stamp, half, pixel_scale, sensor, float(sky), sky_radius, updates,
          min_nrecalc, collected)
    sky_img = rng.poisson(sky, (ny, nx)).astype(float)
    if collected is not None:  # outside the boxes collected through the sensor
        sky_img[collected] = 0.0
    noise = sky_img + rng.normal(0.0, read_noise, (ny, nx))
    arr = np.array(rows, float).reshape(-1, 6)
    stars = QTable([arr[:, 0] * u.pix, arr[:, 1] * u.pix, arr[:, 2] * u.electron,
                    arr[:, 3] * u.arcsec, arr[:, 4], arr[:, 5]],
                   names=("x", "y", "flux", "fwhm", "psf_e1", "psf_e2"))
    out = [im + noise for im in images]
    return {"image": out[0], "images": out[:len(req)], "truth_image": out[-1] if twin else None,
            "stars": stars, "sky": float(sky),
            "strength": req[0] if np.ndim(strength) == 0 else req}


def _field_psf(galsim, x, y, flux, shape, *, fwhm=(0.7, 0.95), e_range=0.04, beta_moffat=3.5):
    """The field's Moffat star at (x, y) px of an image of ``shape`` (ny, nx):
    FWHM (arcsec) linear in x from ``fwhm[0]`` to ``fwhm[1]``, e1 from
    -``e_range`` (y = 0) to +``e_range``, e2 from +``e_range`` / 2 (x = 0) to
    -``e_range`` / 2 (as :func:`simulate_star_field` documents). Returns the
    galsim profile with ``flux`` (e), its FWHM, e1 and e2."""
    ny, nx = shape
    fw = fwhm[0] + (fwhm[1] - fwhm[0]) * x / max(nx - 1, 1)
    e1 = e_range * (2 * y / max(ny - 1, 1) - 1)
    e2 = 0.5 * e_range * (1 - 2 * x / max(nx - 1, 1))
    prof = galsim.Moffat(beta=beta_moffat, fwhm=fw).shear(e1=e1, e2=e2).withFlux(flux)
    return prof, fw, e1, e2


def _draw(galsim, pos, rng, images, strengths, rows, progress, nx, ny, fwhm, e_range, flux,
          beta_moffat, stamp, half, pixel_scale, sensor, sky, sky_radius, updates, min_nrecalc,
          collected):
    """Draw every star into ``images`` (one per strength), appending truth rows.

    With ``collected`` (bool (ny, nx)), the sky in each star's box is collected
    through the sensor and the box is marked in ``collected``.
    """
    lo, hi, inner = sky_box(stamp, sky_radius)
    # the sky photons do not change the stars (positions, fluxes, photons, sensor seeds)
    rng_sky = rng.spawn(1)[0]
    with ProgressBar(len(pos), "galsim field", enabled=progress) as bar:
        for x, y in pos:
            f = float(np.exp(rng.uniform(np.log(flux[0]), np.log(flux[1]))))
            prof, fw, e1, e2 = _field_psf(galsim, x, y, f, (ny, nx), fwhm=fwhm, e_range=e_range,
                                         beta_moffat=beta_moffat)
            ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
            s1, s2 = (int(v) for v in rng.integers(1, 2**30, 2))
            px, py, pf = shoot_stamp_photons(prof, stamp, pixel_scale=pixel_scale, seed=s1,
                                       offset=(x - ix, y - iy))
            win = (slice(iy - half, iy + half + 1), slice(ix - half, ix + half + 1))
            if collected is None:
                ims, _ = accumulate_twins(px, py, pf, strengths, sensor=sensor, seed=s2,
                                          stamp=stamp, pixel_scale=pixel_scale, rng=rng_sky,
                                          updates=updates, min_nrecalc=min_nrecalc)
            else:
                # sky already collected by a closer neighbour's box is not collected twice
                ims, _ = accumulate_twins(px, py, pf, strengths, sensor=sensor, seed=s2,
                                          stamp=stamp, pixel_scale=pixel_scale, sky=sky,
                                          box=(lo, hi), feed=SKY_MARGIN, sky_mask=~collected[win],
                                          rng=rng_sky, updates=updates,
                                          min_nrecalc=min_nrecalc)
                collected[win][inner, inner] = True
            for k, im in enumerate(ims):
                images[k][win] += im
            rows.append((x, y, f, fw, e1, e2))
            bar(1)
