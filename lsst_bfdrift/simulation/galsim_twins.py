"""Paired galsim.SiliconSensor images of the same photons (BF on / off twins).

The independent brighter-fatter simulations of the package (``validate-stars``,
:mod:`lsst_bfdrift.validation.stars`; the sky-like fields, :mod:`lsst_bfdrift.simulation.skysim`)
draw a star once by photon shooting and accumulate the same photons through
``galsim.SiliconSensor`` at several ``strength`` values with the same sensor
seed: diffusion is identical and only the brighter-fatter effect differs
(MODEL_NOTES.md section 8).

The sky must go through the sensor with the star's photons. In a real
exposure the star's shrunken pixels collect less sky too, and every
correction (rightly, for real data) moves that sky flux back along with the
star's; sky added to the images after the BF simulation is sky the
simulation never redistributed, and biased the residual size slopes of
every correction by 3-5 % of the uncorrected slope (``docs/benchmarks.rst``).
:func:`accumulate_twins` therefore mixes uniform sky photons (Poisson number)
over a box around the star with the star's photons in random order. Outside
the box the caller adds a Poisson sky image that is identical in all twins:
GalSim's boundaries reach 4 pixels from an aggressor, so far from the
star's core no pixel moves, and limiting the box keeps GalSim's boundary
updates (over every charged pixel) affordable.

GalSim recomputes the boundaries every ``nrecalc`` photons; here ``nrecalc =
max(min_nrecalc, N / updates)`` for N photons (star plus sky), i.e. about
``updates`` boundary updates per exposure whatever the flux. Boundaries lag
by up to one interval, which weakens the simulated effect by about
1 / updates relative to a continuous accumulation.
"""

import numpy as np

from lsst_bfdrift.simulation.flats import engine_acoeffs
from lsst_bfdrift.utils.errors import InputError

__all__ = ["shoot_stamp_photons", "sky_box", "accumulate_twins", "galsim_acoeffs"]

#: pixels added on each side of the sky box, so that diffusion is balanced at its border
SKY_MARGIN = 3


def shoot_stamp_photons(profile, stamp, *, pixel_scale, seed, offset=(0.0, 0.0)):
    """Photon-shoot a GalSim profile into a square stamp and return its photons.

    Positions are in the stamp's pixel frame, with the profile's flux
    (unlike :func:`lsst_bfdrift.simulation.stars.shoot_photons`, which returns a given
    number of unit conversions relative to the profile's centre).

    Parameters
    ----------
    profile : galsim.GSObject
        Profile, with its flux (e) set.
    stamp : int
        Stamp side (px).
    pixel_scale : float
        arcsec per px.
    seed : int
        Seed of the photon shooting (``galsim.BaseDeviate``).
    offset : tuple of float, optional
        Offset (px) of the profile centre from the stamp's true centre.

    Returns
    -------
    x, y, flux : ndarray
        Photon positions in the stamp's pixel coordinates (px; GalSim
        convention, pixel ``i`` = 1 .. ``stamp`` spans ``i - 0.5`` to
        ``i + 0.5``) and fluxes (e).
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    img = galsim.ImageD(int(stamp), int(stamp), scale=float(pixel_scale))
    profile.drawImage(img, method="phot", save_photons=True, rng=galsim.BaseDeviate(int(seed)),
                      offset=tuple(float(v) for v in offset))
    ph = img.photons
    cen = img.true_center
    return (np.asarray(ph.x, float) + cen.x, np.asarray(ph.y, float) + cen.y,
            np.asarray(ph.flux, float).copy())


def sky_box(stamp, sky_radius, *, margin=SKY_MARGIN):
    """Box around a stamp's central pixel where the sky is collected through the sensor.

    Parameters
    ----------
    stamp : int
        Stamp side (px).
    sky_radius : int or None
        The box covers the central (2 r + 1)^2 pixels plus ``margin`` on each
        side, clipped to the stamp; None: the whole stamp plus the margin.
    margin : int, optional
        Pixels added on each side (px).

    Returns
    -------
    lo, hi : float
        Box edges in the stamp's pixel coordinates (px, GalSim convention),
        the same along x and y.
    inner : slice
        0-based index range of the pixels inside the box, clipped to the stamp.
    """
    stamp = int(stamp)
    c = (stamp + 1) // 2  # central pixel (1-based)
    r = c - 1 if sky_radius is None else min(int(sky_radius), c - 1)
    if r < 0:
        raise InputError(f"sky_radius must be >= 0 or None, got {sky_radius!r}")
    lo, hi = c - r - 0.5 - margin, c + r + 0.5 + margin
    return lo, hi, slice(max(c - 1 - r - margin, 0), c + r + margin)


def accumulate_twins(x, y, flux, strengths, *, sensor, seed, stamp, pixel_scale, sky=0.0,
                     box=None, feed=0, sky_mask=None, rng=None, updates=100, min_nrecalc=1e4,
                     wavelength=None, sky_wavelength=None):
    """Accumulate the same photons (star plus in-sensor sky) at several BF strengths.

    Parameters
    ----------
    x, y, flux : array_like
        The star's photons: positions in the stamp's pixel coordinates (px,
        GalSim convention) and fluxes (e), e.g. from :func:`shoot_stamp_photons`.
    strengths : sequence of float
        ``galsim.SiliconSensor`` strengths, all positive (1 = the sensor
        file's BF; use a tiny value such as 1e-9 for "no BF").
    sensor : str
        GalSim sensor name (e.g. ``'lsst_itl_50_8'``).
    seed : int
        Sensor seed (``galsim.BaseDeviate``), the same for every strength:
        identical diffusion in all twins.
    stamp : int
        Stamp side (px).
    pixel_scale : float
        arcsec per px.
    sky : float, optional
        Sky level (e per pixel of nominal area) collected through the sensor
        inside ``box``; 0: no sky photons.
    box : tuple of float, optional
        ``(lo, hi)``: the square (px, stamp coordinates, on pixel edges) over
        which the sky photons are spread uniformly (see :func:`sky_box`);
        required when ``sky > 0``.
    feed : int, optional
        0: one accumulation over the stamp; sky photons diffusing out of the
        box are not balanced by sky diffusing in, which leaves a ring at the
        box edge (about -20 % of the sky just inside, +20 % just outside for
        lsst_itl_50_8). > 0: the box's pixels are accumulated in their own
        image, with the sky photons spread ``feed`` px further out (they
        diffuse in; those landing outside the box are dropped), so the sky
        is uniform up to the box edge; the star's photons starting outside
        the box are accumulated on the full stamp with the same strength (no
        boundary shifts from the star's core there) and added. The star's
        photons from inside the box that diffuse out of it are lost (its
        surface brightness at the box edge times about 0.16 px per edge).
    sky_mask : ndarray of bool, optional
        (stamp, stamp); sky photons starting in pixels where it is False are
        dropped (their sky was collected already, e.g. by a neighbouring
        star's box). The star's photons, and sky photons outside the stamp,
        are always kept.
    rng : numpy.random.Generator, optional
        Draws the number, the positions and the random arrival order of the
        sky photons among the star's (required; the star's photons are mixed
        in random order even without sky).
    updates : float, optional
        About this many boundary updates per exposure: ``nrecalc =
        max(min_nrecalc, N / updates)`` for N accumulated photons.
    min_nrecalc : float, optional
        Smallest ``nrecalc`` (photons; GalSim's default 1e4).
    wavelength : array_like, optional
        Wavelength (nm) of each of the star's photons: galsim.SiliconSensor
        then converts each at a depth drawn from silicon's absorption length
        (dropping those that cross the sensor) and scales its boundary
        shifts by its conversion height
        (:mod:`~lsst_bfdrift.simulation.chromatic`). None: every photon
        converts at the entrance window (GalSim's achromatic draw).
        ``feed = 0`` only.
    sky_wavelength : array_like, optional
        With ``wavelength`` and sky: wavelengths (nm) the sky photons' are
        drawn from (uniformly, by ``rng``), e.g. a band's flat-spectrum
        sample; None: the star's.

    Returns
    -------
    images : list of ndarray
        One (stamp, stamp) float64 image (e) per strength.
    n_sky : int
        Number of sky photons accumulated (each of flux 1 e).

    Notes
    -----
    GalSim accumulates on one OpenMP thread here (its threads spin on a busy
    machine; the caller's thread count is restored afterwards). The images
    do not depend on the thread count beyond the rounding of pixel sums.
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    x = np.asarray(x, float)
    y = np.asarray(y, float)
    flux = np.asarray(flux, float)
    if not x.shape == y.shape == flux.shape or x.ndim != 1:
        raise InputError("x, y and flux must be 1-d arrays of one length")
    strengths = [float(s) for s in strengths]
    if not strengths or min(strengths) <= 0:
        raise InputError(f"strengths must be positive, got {strengths}")
    if rng is None:
        raise InputError("rng (numpy Generator) is required: it orders the photons")
    if not float(updates) > 0:
        raise InputError(f"updates must be positive, got {updates!r}")
    feed = int(feed)
    if feed < 0 or (feed and box is None):
        raise InputError(f"feed must be >= 0 and needs a box, got {feed!r}")
    if wavelength is not None:
        wavelength = np.asarray(wavelength, float)
        if wavelength.shape != x.shape or feed:
            raise InputError("wavelength must have one value per photon (and feed = 0)")
        pool = wavelength if sky_wavelength is None else np.asarray(sky_wavelength, float)
        if pool.size == 0 and sky > 0:
            raise InputError("sky_wavelength is empty")
    stamp = int(stamp)
    outer = None
    if feed:
        lo, hi = (float(v) for v in box)
        i0, i1 = max(int(round(lo + 0.5)), 1), min(int(round(hi - 0.5)), stamp)
        if i1 < i0:
            raise InputError(f"box {box} holds no pixel of a {stamp} px stamp")
        ins = (x >= i0 - 0.5) & (x < i1 + 0.5) & (y >= i0 - 0.5) & (y < i1 + 0.5)
        outer = (x[~ins], y[~ins], flux[~ins])
        x, y, flux = x[ins], y[ins], flux[ins]
    n_star = x.size
    n_sky = 0
    if sky > 0:
        if box is None:
            raise InputError("box (lo, hi) is required when sky > 0")
        lo, hi = (float(v) for v in box)
        lo, hi = lo - feed, hi + feed
        n_sky = int(rng.poisson(float(sky) * (hi - lo) ** 2))
    order = rng.permutation(n_star + n_sky)
    xs = np.concatenate([x, rng.uniform(lo, hi, n_sky) if n_sky else np.empty(0)])[order]
    ys = np.concatenate([y, rng.uniform(lo, hi, n_sky) if n_sky else np.empty(0)])[order]
    fl = np.concatenate([flux, np.ones(n_sky)])[order]
    wl = None
    if wavelength is not None:
        wl = np.concatenate([wavelength, rng.choice(pool, n_sky) if n_sky else
                             np.empty(0)])[order]
    if sky_mask is not None and n_sky:
        sky_mask = np.asarray(sky_mask, bool)
        if sky_mask.shape != (stamp, stamp):
            raise InputError(f"sky_mask must have shape {(stamp, stamp)}, got {sky_mask.shape}")
        is_sky = order >= n_star
        ix = np.floor(xs - 0.5).astype(int)
        iy = np.floor(ys - 0.5).astype(int)
        inside = (ix >= 0) & (ix < stamp) & (iy >= 0) & (iy < stamp)
        ok = np.ones(xs.size, bool)  # outside the stamp: kept (may diffuse in)
        ok[inside] = sky_mask[iy[inside], ix[inside]]
        keep = ~is_sky | ok
        xs, ys, fl = xs[keep], ys[keep], fl[keep]
        wl = None if wl is None else wl[keep]
        n_sky = int(keep.sum()) - n_star
    n = xs.size
    images = []
    threads = galsim.utilities.get_omp_threads()
    try:
        # one OpenMP thread (every paired star, field and spot draw comes here): on a
        # stamp GalSim's threads mostly wait at their barriers, and on a busy machine
        # they spin (300 stars took 1059 s instead of 204 s beside one other job); the
        # images differ only by the rounding of the pixel sums (~4e-12 e)
        galsim.utilities.set_omp_threads(1)
        for s in strengths:
            sens = galsim.SiliconSensor(sensor, strength=s, rng=galsim.BaseDeviate(int(seed)),
                                        nrecalc=max(float(min_nrecalc), n / float(updates)))
            if feed:
                im = galsim.ImageD(galsim.BoundsI(i0, i1, i0, i1), scale=float(pixel_scale))
            else:
                im = galsim.ImageD(stamp, stamp, scale=float(pixel_scale))
            sens.accumulate(galsim.PhotonArray(n, x=xs, y=ys, flux=fl, wavelength=wl), im)
            if feed:
                n_out = outer[0].size
                full = galsim.ImageD(stamp, stamp, scale=float(pixel_scale))
                if n_out:
                    sens_out = galsim.SiliconSensor(
                        sensor, strength=s, rng=galsim.BaseDeviate(int(seed) + 1),
                        nrecalc=max(float(min_nrecalc), n_out / float(updates)))
                    sens_out.accumulate(galsim.PhotonArray(n_out, x=outer[0], y=outer[1],
                                                           flux=outer[2]), full)
                full[im.bounds] += im
                im = full
            images.append(im.array.copy())
    finally:
        galsim.utilities.set_omp_threads(threads)
    return images, n_sky


def galsim_acoeffs(sensor, max_lag=8, *, charge=1e4):
    """GalSim's own a-matrix of a sensor: the linear area response per electron.

    ``galsim.SiliconSensor(sensor).calculate_pixel_areas`` of an image with
    one pixel holding ``charge`` and ``charge / 2`` electrons (no
    diffusion); areas are quadratic in the charge (GalSim moves the vertices
    linearly), so alpha = (4 (A(Q/2) - 1) - (A(Q) - 1)) / Q is the exact
    d A / d Q at Q = 0, the a_ij that flats of that sensor measure. The
    flats engine's own evaluation
    (:func:`~lsst_bfdrift.simulation.flats.engine_acoeffs` with no
    injection), which GalSim flats carry.

    Parameters
    ----------
    sensor : str
        GalSim sensor name (e.g. ``lsst_itl_50_8``).
    max_lag : int, optional
        Largest lag.
    charge : float, optional
        Aggressor charge (e) of the evaluation.

    Returns
    -------
    ndarray, shape (max_lag + 1, max_lag + 1)
        a[i, j] (1/e), i serial (x), j parallel (y).
    """
    if int(max_lag) != max_lag or max_lag < 0:
        raise InputError(f"max_lag must be a non-negative integer, got {max_lag!r}")
    if not charge > 0:
        raise InputError(f"charge must be positive, got {charge!r}")
    return engine_acoeffs(str(sensor), max_lag=int(max_lag), charge=float(charge))
