"""Spot-projector series drawn by galsim.SiliconSensor (validation and acquisition planning).

A regular grid of identical spots (Gaussian or Moffat of ``sigma`` px; a
Moffat has the FWHM of that Gaussian) is imaged at a series of exposure
times whose mean spot fluxes run geometrically from ``flux_min`` to the
flux whose peak pixel reaches ``peak_max`` (near full well). Each spot's
photons are shot by GalSim into a stamp of its own and accumulated by
``galsim.SiliconSensor`` (:func:`~lsst_bfdrift.simulation.galsim_twins.accumulate_twins`,
about ``updates`` boundary updates per spot and exposure); spots are far
apart, so drawing them separately neglects only the BF interaction between
spots. The photon count is Poisson (GalSim's photon shooting). The spots
keep their place and sub-pixel phase in every exposure (a fixed
projector), and their fluxes differ by a fixed factor ``1 + flux_scatter
N(0, 1)`` (the projector's illumination).

Then, the same in every twin: a uniform ``background`` (e per px, Poisson,
added after the BF step: not redistributed; lab spot backgrounds are low),
Gaussian read noise, and a bias pedestal (stated in the header as
``BIASLVL``; the spot measurement's local background removes it). With
``full_well``, pixels are clipped at ``full_well + bias`` (no blooming) and
the level is written as ``SATURATE``. With ``twin=True`` the same photons
are also accumulated with ``strength=1e-9`` and the same sensor seed
(identical diffusion, only the BF effect differs) and receive the same
noise: a paired image without brighter-fatter, for a benchmark's truth only.

:func:`write_spot_series` writes each exposure as a FITS file with
``EXPTIME`` (s) and ``BUNIT`` (electron, or adu with ``GAIN``), atomically.
"""

import os

import numpy as np
from astropy import units as u
from astropy.io import fits
from astropy.table import QTable

from lsst_bfdrift.simulation.galsim_twins import accumulate_twins, shoot_stamp_photons
from lsst_bfdrift.utils.errors import InputError, OutputExistsError
from lsst_bfdrift.utils.io import atomic_output, check_output
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["simulate_spot_series", "write_spot_series", "spot_profile", "peak_fraction",
           "SPOT_PROFILES", "NULL_STRENGTH"]

#: Spot profiles of :func:`simulate_spot_series`.
SPOT_PROFILES = ("gaussian", "moffat")
#: ``galsim.SiliconSensor`` strength of the twin without brighter-fatter (GalSim needs > 0).
NULL_STRENGTH = 1e-9
#: Gaussian FWHM per sigma.
_FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))


def spot_profile(profile, sigma, *, beta_moffat=3.5):
    """A unit-flux GalSim spot of ``sigma`` px (pixel scale 1).

    Parameters
    ----------
    profile : {'gaussian', 'moffat'}
        A Gaussian of ``sigma``, or a Moffat of index ``beta_moffat`` with the
        same FWHM.
    sigma : float
        px, > 0.
    beta_moffat : float, optional
        Moffat index.

    Returns
    -------
    galsim.GSObject
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"sigma must be a positive number of pixels, got {sigma!r}")
    if profile == "gaussian":
        return galsim.Gaussian(sigma=float(sigma))
    if profile == "moffat":
        return galsim.Moffat(beta=float(beta_moffat), fwhm=float(sigma) * _FWHM_PER_SIGMA)
    raise InputError(f"profile must be one of {SPOT_PROFILES}, got {profile!r}")


def peak_fraction(profile):
    """Fraction of a spot's flux in its peak pixel when centred on a pixel.

    Parameters
    ----------
    profile : galsim.GSObject
        Unit-flux spot (pixel scale 1).

    Returns
    -------
    float
    """
    img = profile.withFlux(1.0).drawImage(nx=15, ny=15, scale=1.0)
    return float(img.array.max())


def _check(grid, pitch, n_images, flux_min, peak_max, read_noise, bias, background,
           full_well, flux_scatter, updates):
    gx, gy = (int(v) for v in grid)
    if gx < 1 or gy < 1:
        raise InputError(f"grid must be two positive numbers of spots, got {grid!r}")
    if not pitch > 0:
        raise InputError(f"pitch must be positive (px), got {pitch!r}")
    if int(n_images) < 2:
        raise InputError(f"n_images must be at least 2, got {n_images!r}")
    if not (flux_min > 0 and peak_max > 0):
        raise InputError(f"flux_min and peak_max must be positive (e), got {flux_min!r}, "
                         f"{peak_max!r}")
    for name, v in (("read_noise", read_noise), ("bias", bias), ("background", background),
                    ("flux_scatter", flux_scatter)):
        if not (np.isfinite(v) and v >= 0):
            raise InputError(f"{name} must be finite and >= 0, got {v!r}")
    if full_well is not None and not full_well > 0:
        raise InputError(f"full_well must be positive (e), got {full_well!r}")
    if not updates > 0:
        raise InputError(f"updates must be positive, got {updates!r}")
    return gx, gy


def simulate_spot_series(*, sensor="lsst_itl_50_8", grid=(5, 5), pitch=40.0, sigma=1.5,
                         profile="gaussian", beta_moffat=3.5, n_images=8, flux_min=1e4,
                         peak_max=9e4, flux_scatter=0.05, rate=1e5, read_noise=5.0, bias=0.0,
                         background=0.0, full_well=None, twin=False, strength=1.0,
                         updates=300, min_nrecalc=100, seed=20151, progress=False):
    """A spot-grid series drawn by galsim.SiliconSensor, optionally with BF-free twins.

    Parameters
    ----------
    sensor : str, optional
        GalSim sensor name (``lsst_itl_50_8``, ``lsst_e2v_50_8``, ``lsst_itl_50_32``, ...).
    grid : (int, int), optional
        Spots along x and y.
    pitch : float, optional
        Spacing of the spots (px).
    sigma : float, optional
        Spot sigma (px; 1-3 px as spot projectors give).
    profile : {'gaussian', 'moffat'}, optional
        Spot profile (:func:`spot_profile`).
    beta_moffat : float, optional
        Moffat index.
    n_images : int, optional
        Exposures in the series.
    flux_min : float, optional
        Mean spot flux of the shortest exposure (e).
    peak_max : float, optional
        Peak pixel (e) of a pixel-centred mean spot in the longest exposure,
        without BF: the longest exposure's mean flux is ``peak_max`` over
        :func:`peak_fraction`.
    flux_scatter : float, optional
        Relative rms of the spots' fixed flux factors (clipped to 0.5-1.5).
    rate : float, optional
        Mean spot flux per second (e/s): ``EXPTIME = level / rate``.
    read_noise : float, optional
        Gaussian read noise (e rms).
    bias : float, optional
        Bias pedestal (e) left in the images and stated as ``BIASLVL``.
    background : float, optional
        Uniform background (e per px), Poisson, added after the BF step.
    full_well : float, optional
        Clip pixels at ``full_well + bias`` (e) and state ``SATURATE``.
    twin : bool, optional
        Also the BF-free twins (same photons and noise, strength 1e-9).
    strength : float, optional
        ``galsim.SiliconSensor`` strength of the BF images.
    updates : float, optional
        Boundary updates per spot and exposure (``nrecalc = max(min_nrecalc,
        N / updates)``); 300 weakens the effect by about 0.3 % against a
        continuous accumulation (1000 is converged).
    min_nrecalc : float, optional
        Smallest ``nrecalc`` (photons).
    seed : int, optional
        Seed of every random number.
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    dict
        ``images`` (list of (ny, nx) float64 arrays, e, bias included),
        ``twins`` (the BF-free twins, or None), ``exptimes`` (s, Quantity),
        ``levels`` (mean spot flux of each exposure, e), ``spots`` (QTable:
        ``spot``, ``x``, ``y`` (px, 0-based pixel centres), ``flux_factor``),
        ``header`` (the cards common to every file) and ``settings``.

    Raises
    ------
    InputError
        A setting out of range, an unknown profile, or a grid of spots that
        does not fit in the image.
    """
    gx, gy = _check(grid, pitch, n_images, flux_min, peak_max, read_noise, bias, background,
                    full_well, flux_scatter, updates)
    if not strength > 0:
        raise InputError(f"strength must be positive, got {strength!r}")
    unit = spot_profile(profile, sigma, beta_moffat=beta_moffat)
    flux_max = float(peak_max) / peak_fraction(unit)
    if flux_max <= flux_min:
        raise InputError(f"peak_max {peak_max:g} e is reached at {flux_max:.3g} e, below "
                         f"flux_min {flux_min:g} e")
    levels = np.geomspace(float(flux_min), flux_max, int(n_images))
    stamp = 2 * int(np.ceil(max(8.0 * sigma, 10.0))) + 1
    half = stamp // 2
    margin = max(0.5 * pitch, half + 2.0)
    nx = int(np.ceil(2 * margin + (gx - 1) * pitch)) + 1
    ny = int(np.ceil(2 * margin + (gy - 1) * pitch)) + 1
    rng = np.random.default_rng(seed)
    xs = margin + pitch * np.arange(gx) + rng.uniform(-0.5, 0.5, (gy, gx))
    ys = margin + pitch * np.arange(gy)[:, None] + rng.uniform(-0.5, 0.5, (gy, gx))
    xs, ys = xs.ravel(), ys.ravel()
    factor = np.clip(1.0 + float(flux_scatter) * rng.normal(size=xs.size), 0.5, 1.5)
    strengths = [float(strength)] + ([NULL_STRENGTH] if twin else [])
    images = [[np.zeros((ny, nx)) for _ in strengths] for _ in levels]
    # accumulate_twins runs GalSim on one OpenMP thread (small stamps: threads only spin)
    with ProgressBar(len(levels) * xs.size, "spot-sim", enabled=progress) as bar:
        for i, level in enumerate(levels):
            for k in range(xs.size):
                ix, iy = int(np.floor(xs[k] + 0.5)), int(np.floor(ys[k] + 0.5))
                s1, s2 = (int(v) for v in rng.integers(1, 2 ** 30, 2))
                px, py, pf = shoot_stamp_photons(unit.withFlux(level * factor[k]), stamp,
                                                 pixel_scale=1.0, seed=s1,
                                                 offset=(xs[k] - ix, ys[k] - iy))
                ims, _ = accumulate_twins(px, py, pf, strengths, sensor=sensor, seed=s2,
                                          stamp=stamp, pixel_scale=1.0, rng=rng,
                                          updates=updates, min_nrecalc=min_nrecalc)
                win = (slice(iy - half, iy + half + 1), slice(ix - half, ix + half + 1))
                for im, acc in zip(ims, images[i]):
                    acc[win] += im
                bar(1)
    bf, nobf = [], []
    for acc in images:
        noise = rng.normal(0.0, float(read_noise), (ny, nx)) + float(bias)
        if background > 0:
            noise += rng.poisson(float(background), (ny, nx))
        out = [a + noise for a in acc]
        if full_well is not None:
            out = [np.minimum(a, float(full_well) + float(bias)) for a in out]
        bf.append(out[0])
        if twin:
            nobf.append(out[1])
    exptimes = levels / float(rate)
    spots = QTable([np.arange(xs.size), xs * u.pix, ys * u.pix, factor],
                   names=("spot", "x", "y", "flux_factor"))
    header = {"SENSOR": (sensor, "galsim.SiliconSensor model"),
              "SPOTPROF": (profile, "spot profile"), "SPOTSIG": (float(sigma), "spot sigma (px)"),
              "BFSTRNGT": (float(strength), "SiliconSensor strength of the BF images"),
              "RDNOISE": (float(read_noise), "read noise (e rms)"),
              "BIASLVL": (float(bias), "bias pedestal left in the image (e)"),
              "BKGLVL": (float(background), "uniform background (e/px)"),
              "NSPOTS": (int(xs.size), "spots in the grid"), "SIMSEED": (int(seed), "seed")}
    if full_well is not None:
        header["SATURATE"] = (float(full_well) + float(bias), "saturation level (e)")
    settings = dict(sensor=sensor, grid=[gx, gy], pitch=float(pitch), sigma=float(sigma),
                    profile=profile, beta_moffat=float(beta_moffat), n_images=int(n_images),
                    flux_min=float(flux_min), peak_max=float(peak_max), flux_max=flux_max,
                    flux_scatter=float(flux_scatter), rate=float(rate),
                    read_noise=float(read_noise), bias=float(bias),
                    background=float(background), full_well=full_well,
                    strength=float(strength), updates=float(updates),
                    min_nrecalc=float(min_nrecalc), seed=int(seed), shape=[ny, nx],
                    stamp=stamp)
    return {"images": bf, "twins": nobf if twin else None, "exptimes": exptimes * u.s,
            "levels": levels * u.electron, "spots": spots, "header": header,
            "settings": settings}


def write_spot_series(series, directory, *, prefix="spot", gain=None, overwrite=False):
    """Write a :func:`simulate_spot_series` result as FITS files, one per exposure.

    Files ``<prefix>_<k>.fits`` (the BF images), ``<prefix>_<k>_nobf.fits``
    (the twins, when simulated; ``IMAGETYP = 'SPOT NOBF TRUTH'``), and
    ``<prefix>_truth.ecsv`` (the spots' positions and flux factors), each
    written atomically.

    Parameters
    ----------
    series : dict
        From :func:`simulate_spot_series`.
    directory : str or path-like
        Created if needed.
    prefix : str, optional
        File name prefix.
    gain : float, optional
        Write ADU (``BUNIT = 'adu'``, ``GAIN`` = e/ADU, ``SATURATE`` in ADU)
        instead of electrons.
    overwrite : bool, optional
        Replace existing files.

    Returns
    -------
    dict
        ``images``, ``twins`` (lists of paths; empty without twins) and ``truth``.

    Raises
    ------
    OutputExistsError
        A file exists and ``overwrite`` is False (checked before any is written).
    """
    directory = os.fspath(directory)
    if gain is not None and not (np.isfinite(gain) and gain > 0):
        raise InputError(f"gain must be a positive number of e/ADU, got {gain!r}")
    n = len(series["images"])
    width = max(3, len(str(n - 1)))
    names = [f"{prefix}_{k:0{width}d}" for k in range(n)]
    paths = {"images": [os.path.join(directory, f"{s}.fits") for s in names],
             "twins": [os.path.join(directory, f"{s}_nobf.fits") for s in names]
             if series["twins"] is not None else [],
             "truth": os.path.join(directory, f"{prefix}_truth.ecsv")}
    for p in paths["images"] + paths["twins"] + [paths["truth"]]:
        try:
            check_output(p, overwrite=overwrite)
        except OutputExistsError as exc:
            raise OutputExistsError(f"{exc} (spot-sim writes into {directory})") from None
    os.makedirs(directory, exist_ok=True)
    scale = 1.0 if gain is None else 1.0 / float(gain)
    times = series["exptimes"].to_value(u.s)
    levels = series["levels"].to_value(u.electron)
    for k in range(n):
        for kind, arrays in (("images", series["images"]), ("twins", series["twins"])):
            if arrays is None:
                continue
            hdr = fits.Header()
            hdr["EXPTIME"] = (float(times[k]), "exposure time (s)")
            hdr["BUNIT"] = ("electron", "pixel unit") if gain is None else ("adu", "pixel unit")
            if gain is not None:
                hdr["GAIN"] = (float(gain), "e/ADU")
            for key, card in series["header"].items():
                hdr[key] = (card[0] * scale, card[1].replace("(e)", "(ADU)")) \
                    if key == "SATURATE" and gain is not None else card
            hdr["LEVEL"] = (float(levels[k]), "mean spot flux (e)")
            hdr["IMAGETYP"] = ("SPOT", "spot-grid exposure") if kind == "images" else \
                ("SPOT NOBF TRUTH", "same photons without BF: benchmark truth only")
            data = np.asarray(arrays[k], float) * scale
            with atomic_output(paths[kind][k], overwrite=overwrite) as tmp:
                fits.PrimaryHDU(data.astype(np.float32), header=hdr).writeto(tmp, overwrite=True)
    with atomic_output(paths["truth"], overwrite=overwrite) as tmp:
        series["spots"].write(tmp, format="ascii.ecsv", overwrite=True)
    return paths
