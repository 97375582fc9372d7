"""Chromatic galsim.SiliconSensor draws: photons with wavelengths, paired stars, band flats.

galsim.SiliconSensor converts each photon that carries a wavelength at a
depth drawn from the absorption length of silicon at that wavelength
(``share/sensors/abs_length.dat``), and scales the boundary distortions that
the photon sees by its conversion height (GalSim ``src/Silicon.cpp``,
``Silicon::insidePixel`` and ``Silicon::calculateConversionDepth``, read for
these facts; no code taken):

* depth d = -L(lambda) ln(1 - u), u uniform, L linearly interpolated in the
  table;
* conversion height z = t - d above the collecting wells, t the sensor
  thickness (``SensorThickness`` of the ``.cfg``, 100 um for the LSST
  files); a photon with z < 0 (it crossed the silicon) is dropped;
* the displacement of every pixel vertex is multiplied by tanh(z / 12 um)
  (:data:`~lsst_bfdrift.physics.depth.GALSIM_ZFIT`) when that photon is
  tested against the pixel's polygon; the stored distortions assume
  conversion at the top of the silicon. That test runs only for photons
  between the pixel's inscribed and bounding boxes of the unscaled polygon
  (inside the first: inside; outside the second: outside), so where an
  edge is shifted straight the scale does not act and the images carry a
  small part of the rule (``benchmarks/simulation/galsim_depth_rule.py``);
* the diffusion step is proportional to sqrt(z t).

The bands, spectra and depth distributions are those of
:mod:`lsst_bfdrift.physics.depth` (one home): this module turns them into
GalSim objects (:func:`galsim_bandpass`, :func:`galsim_sed`), samples photon
wavelengths the way a chromatic draw does (``galsim.WavelengthSampler``),
and draws the data the package did not make: paired stars with and without
brighter-fatter (:func:`draw_chromatic_star_pairs`) and the pixel-area response a flat of a band
sees (:func:`flat_area_response`).
"""

import os

import numpy as np

from lsst_bfdrift.physics.depth import normalize_band, sed_photons
from lsst_bfdrift.physics.absorption import absorption_length
from lsst_bfdrift.simulation.galsim_twins import accumulate_twins, shoot_stamp_photons, sky_box
from lsst_bfdrift.simulation.stars import make_psf
from lsst_bfdrift.utils.errors import InputError

__all__ = ["galsim_bandpass", "galsim_sed", "sample_wavelengths", "galsim_thickness",
           "detected_fraction", "star_list", "draw_chromatic_star_pairs",
           "flat_area_response"]

#: Wavelength grid (nm) on which :func:`galsim_sed` tabulates a spectrum.
_SED_GRID = np.arange(250.0, 1200.01, 0.5)


def _galsim():
    import galsim  # galsim: heavy, imported only where GalSim runs
    return galsim


def galsim_bandpass(band):
    """GalSim's LSST throughput of one band (``share/bandpasses/LSST_<band>.dat``).

    Parameters
    ----------
    band : str
        An LSST band (:data:`~lsst_bfdrift.physics.depth.BANDS`; the
        spellings of :func:`~lsst_bfdrift.physics.depth.normalize_band`).

    Returns
    -------
    galsim.Bandpass
        Wavelengths in nm.
    """
    galsim = _galsim()
    b = normalize_band(band)
    path = os.path.join(galsim.meta_data.share_dir, "bandpasses", f"LSST_{b}.dat")
    return galsim.Bandpass(path, "nm")


def galsim_sed(sed=None):
    """A spectrum of :func:`~lsst_bfdrift.physics.depth.sed_photons` as a ``galsim.SED``.

    Parameters
    ----------
    sed : optional
        None/'flat', a temperature (K) or 'blackbody:T', or one of GalSim's
        SED names ('vega', 'CWW_E_ext', ...).

    Returns
    -------
    galsim.SED
        Photons per nm (shape only), tabulated every 0.5 nm over 250-1200 nm
        (linear interpolation), the spectrum the band templates use.
    """
    galsim = _galsim()
    dens = np.asarray(sed_photons(sed, _SED_GRID), float)
    if not np.all(np.isfinite(dens)) or np.any(dens < 0) or dens.max() <= 0:
        raise InputError(f"sed {sed!r} has no positive, finite photon density over "
                         "250-1200 nm")
    table = galsim.LookupTable(_SED_GRID, dens / dens.max(), interpolant="linear")
    return galsim.SED(table, "nm", "fphotons")


def sample_wavelengths(n, band, sed=None, *, seed):
    """Photon wavelengths drawn by ``galsim.WavelengthSampler`` (band throughput x SED).

    Parameters
    ----------
    n : int
        Number of photons (>= 0).
    band : str
        LSST band.
    sed : optional
        Source spectrum (:func:`galsim_sed`).
    seed : int
        Seed of the sampling (``galsim.BaseDeviate``).

    Returns
    -------
    ndarray, shape (n,)
        Wavelengths (nm).
    """
    if isinstance(n, bool) or int(n) != n or n < 0:
        raise InputError(f"n must be an integer >= 0, got {n!r}")
    galsim = _galsim()
    pa = galsim.PhotonArray(max(int(n), 1))
    galsim.WavelengthSampler(galsim_sed(sed), galsim_bandpass(band)).applyTo(
        pa, rng=galsim.BaseDeviate(int(seed)))
    return np.asarray(pa.wavelength, float)[:int(n)].copy()


def galsim_thickness(sensor):
    """``SensorThickness`` (um) of a GalSim sensor's ``.cfg``."""
    galsim = _galsim()
    path = os.path.join(galsim.meta_data.share_dir, "sensors", f"{sensor}.cfg")
    if not os.path.isfile(path):
        raise InputError(f"no GalSim sensor {sensor!r} (looked for {path})")
    with open(path) as fh:
        for line in fh:
            key, _, rest = line.partition("=")
            if key.strip() == "SensorThickness":
                return float(rest.split("#")[0])
    raise InputError(f"{path} has no SensorThickness")


def detected_fraction(wavelength, thickness):
    """Probability that a photon of ``wavelength`` (nm) converts in ``thickness`` um of silicon.

    ``1 - exp(-t / L(lambda))``, L from GalSim's table
    (:func:`~lsst_bfdrift.physics.absorption.absorption_length`).
    """
    return -np.expm1(-float(thickness) / absorption_length(wavelength))


def star_list(n_stars, *, psf="moffat", fwhm=(0.6, 0.9), emax=0.05, flux=(1e4, 1.5e6),
              seed):
    """Star parameters shared by every band (so that bands are compared star by star).

    Parameters
    ----------
    n_stars : int
        Number of stars.
    psf : {'moffat', 'kolmogorov', 'gaussian'}, optional
        PSF family.
    fwhm : tuple of float, optional
        Range of the FWHM (arcsec), uniform.
    emax : float, optional
        Largest PSF ellipticity (random orientation).
    flux : tuple of float, optional
        Range of the detected fluxes (e), log-uniform.
    seed : int
        Seed.

    Returns
    -------
    list of dict
        ``psf, fwhm, e, beta, flux`` (detected e), ``offset`` (px) and
        ``seed`` (the star's own seed for photons and sensor).
    """
    if isinstance(n_stars, bool) or int(n_stars) != n_stars or n_stars < 1:
        raise InputError(f"n_stars must be a positive integer, got {n_stars!r}")
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(int(n_stars)):
        out.append({"psf": psf,
                    "flux": float(np.exp(rng.uniform(np.log(flux[0]), np.log(flux[1])))),
                    "fwhm": float(rng.uniform(*fwhm)), "e": float(rng.uniform(0, emax)),
                    "beta": float(rng.uniform(0, 180)),
                    "offset": tuple(float(v) for v in rng.uniform(-0.5, 0.5, 2)),
                    "seed": int(rng.integers(1, 2**30))})
    return out


def draw_chromatic_star_pairs(stars, band, *, sed=None, sensor="lsst_itl_50_8", sky=1000.0,
                              stamp=41, pixel_scale=0.2, sky_radius=8, updates=300,
                              min_nrecalc=100):
    """Stars drawn by galsim.SiliconSensor with photon wavelengths, with and without BF.

    Each star is photon-shot with ``flux / f`` photons, f the mean detected
    fraction of its band and SED (so that about ``flux`` electrons are
    collected in every band), each photon given a wavelength by
    ``galsim.WavelengthSampler``; sky photons (the band's flat-spectrum
    wavelengths) are collected through the sensor around the star, and the
    same photons are accumulated with ``strength`` 1 and 1e-9 and the same
    sensor seed (identical conversion depths and diffusion;
    :func:`~lsst_bfdrift.simulation.galsim_twins.accumulate_twins`).

    Parameters
    ----------
    stars : list of dict
        From :func:`star_list`.
    band : str
        LSST band.
    sed : optional
        Spectrum of the stars (:func:`galsim_sed`).
    sensor : str, optional
        GalSim sensor name.
    sky : float, optional
        Sky level (e per pixel of nominal area); 0: none.
    stamp, pixel_scale, sky_radius, updates, min_nrecalc : optional
        As :func:`~lsst_bfdrift.validation.stars.draw_star_pairs` (fewer
        boundary updates by default: 300 weakens the simulated effect by
        about 0.3 %, the same in every band).

    Returns
    -------
    list of dict
        ``bf``, ``truth`` (arrays, e), ``flux`` (expected detected e, from the
        photons' wavelengths), ``flux_incident``, ``fwhm``.
    """
    b = normalize_band(band)
    t = galsim_thickness(sensor)
    out = []
    for s in stars:
        seed = int(s["seed"])
        rng = np.random.default_rng(seed)
        ref = sample_wavelengths(20000, b, sed, seed=seed + 1)
        frac = float(np.mean(detected_fraction(ref, t)))
        f_inc = s["flux"] / frac
        prof = make_psf(s["psf"], s["fwhm"], e=s["e"], beta=s["beta"]).withFlux(f_inc)
        x, y, fl = shoot_stamp_photons(prof, stamp, pixel_scale=pixel_scale, seed=seed + 2,
                                       offset=s["offset"])
        wl = sample_wavelengths(x.size, b, sed, seed=seed + 3)
        sky_wl = sample_wavelengths(20000, b, None, seed=seed + 4)
        lo, hi, inner = sky_box(stamp, sky_radius)
        # sky photons are incident ones: the detected sky level is `sky`
        sky_inc = sky / float(np.mean(detected_fraction(sky_wl, t)))
        images, _ = accumulate_twins(x, y, fl, (1.0, 1e-9), sensor=sensor, seed=seed + 5,
                                     stamp=stamp, pixel_scale=pixel_scale, sky=sky_inc,
                                     box=(lo, hi), rng=rng, updates=updates,
                                     min_nrecalc=min_nrecalc, wavelength=wl,
                                     sky_wavelength=sky_wl)
        noise = rng.poisson(sky, (stamp, stamp)).astype(float)
        outside = np.ones((stamp, stamp), bool)
        outside[inner, inner] = False
        noise = np.where(outside, noise, 0.0)
        detected = float(np.sum(fl * detected_fraction(wl, t)))
        out.append({"bf": images[0] + noise, "truth": images[1] + noise, "flux": detected,
                    "flux_incident": float(fl.sum()), "fwhm": s["fwhm"]})
    return out


def flat_area_response(sensor, band, *, sed=None, wavelength=None, charge=5e4, photons=8e5,
                       seed):
    """a00, a10, a01 seen by a band's photons: a flat over a pixel that holds charge.

    A 9 x 9 px image whose central pixel holds ``charge`` (and ``charge / 2``)
    electrons is illuminated uniformly (over its central 5 x 5 pixels, so
    that diffusion is balanced) with photons of ``band`` x ``sed`` carrying
    negligible charge, through galsim.SiliconSensor (boundaries computed
    from the image's charge, not updated during the exposure); the same
    photons with ``strength`` 1e-9 and the same sensor seed give the
    undistorted counts (identical conversion depths and diffusion). The
    counts' change is the pixel-area change: A(Q) - 1 = N_Q / N_0 - 1 in the
    central pixel (a00) and its neighbours (a10: x lag, a01: y lag, means of
    the two signs), and the linear response, GalSim's vertices moving
    linearly with charge, is ``(4 (A(Q/2) - 1) - (A(Q) - 1)) / Q`` (as in
    :func:`~lsst_bfdrift.simulation.galsim_twins.galsim_acoeffs`).

    Parameters
    ----------
    sensor : str
        GalSim sensor name.
    band : str or None
        LSST band; None: no wavelengths (conversion at the entrance window,
        GalSim's achromatic draw, which ``galsim_acoeffs`` describes).
    sed : optional
        Spectrum of the illumination (:func:`galsim_sed`); None: flat.
    wavelength : float, optional
        Instead of a band (``band`` None): every photon at this wavelength (nm).
    charge : float, optional
        Charge Q (e) of the central pixel.
    photons : float, optional
        Detected test photons per pixel (about; the error of a00 scales as
        1 / sqrt(photons charge)).
    seed : int
        Seed.

    Returns
    -------
    dict
        ``a00, a10, a01`` (1/e) and their errors ``*_err`` (binomial counts
        of the photons that changed pixel), ``photons`` (test photons
        accumulated, incident).
    """
    galsim = _galsim()
    if not charge > 0 or not photons > 0:
        raise InputError(f"charge and photons must be positive, got {charge!r}, {photons!r}")
    if band is not None and wavelength is not None:
        raise InputError("give a band or a wavelength, not both")
    rng = np.random.default_rng(seed)
    t = galsim_thickness(sensor)
    frac = 1.0
    if band is not None:
        frac = float(np.mean(detected_fraction(
            sample_wavelengths(20000, band, sed, seed=seed + 1), t)))
    elif wavelength is not None:
        frac = float(detected_fraction(float(wavelength), t))
    lo, hi = 2.5, 7.5  # the central 5 x 5 pixels of 9 (pixel centres 1 .. 9)
    n = int(rng.poisson(float(photons) / frac * (hi - lo) ** 2))
    x = rng.uniform(lo, hi, n)
    y = rng.uniform(lo, hi, n)
    wl = None
    if band is not None:
        wl = sample_wavelengths(n, band, sed, seed=seed + 2)
    elif wavelength is not None:
        wl = np.full(n, float(wavelength))
    tiny = 1e-6  # charge of a test photon (e)
    counts = {}
    for name, strength, q in (("0", 1e-9, charge), ("Q", 1.0, charge),
                              ("Q/2", 1.0, 0.5 * charge)):
        sens = galsim.SiliconSensor(sensor, strength=strength,
                                    rng=galsim.BaseDeviate(int(seed) + 3), nrecalc=1e30)
        im = galsim.ImageD(9, 9)
        im.array[4, 4] = q
        before = im.array.copy()
        sens.accumulate(galsim.PhotonArray(n, x=x, y=y, flux=np.full(n, tiny),
                                           wavelength=wl), im)
        counts[name] = np.rint((im.array - before) / tiny)
    out = {"photons": n}
    for key, (iy, ix) in (("a00", ((4,), (4,))), ("a10", ((4, 4), (3, 5))),
                          ("a01", ((3, 5), (4, 4)))):
        n0 = counts["0"][iy, ix].sum()
        dq = counts["Q"][iy, ix].sum() - n0
        dh = counts["Q/2"][iy, ix].sum() - n0
        out[key] = float((4 * dh - dq) / n0 / charge)
        # the changed photons are a subset of the swept area's; Poisson errors of the changes
        out[key + "_err"] = float(np.sqrt(16 * abs(dh) + abs(dq)) / n0 / charge)
    return out
