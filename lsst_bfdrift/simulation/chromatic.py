"""Photon wavelengths for galsim.SiliconSensor draws: LSST bands, stellar SEDs, GalSim's depths.

galsim.SiliconSensor converts each photon that carries a wavelength at a
depth drawn from the absorption length of silicon at that wavelength
(``share/sensors/abs_length.dat``, read by ``galsim.SiliconSensor``), and
scales the boundary distortions that the photon sees by its conversion
height (GalSim ``src/Silicon.cpp``, ``Silicon::insidePixel`` and
``Silicon::calculateConversionDepth``, read for these facts; no code taken):

* depth d = -L(lambda) ln(1 - u), u uniform, L linearly interpolated in the
  table (and clamped at its ends);
* conversion height z = t - d above the collecting wells, t the sensor
  thickness (``SensorThickness`` of the ``.cfg``, 100 um for the LSST
  files); a photon with z < 0 (it passed through the silicon) is dropped;
* the displacement of every pixel vertex from its undistorted position is
  multiplied by tanh(z / 12 um) ("an empirical fit to the Poisson solver
  simulations", ``zfit = 12``) when that photon is tested; the stored
  distortions assume conversion at the top of the silicon;
* the diffusion step is proportional to sqrt(z t).

This module samples the photon wavelengths the way a chromatic draw does
(``galsim.WavelengthSampler`` over an LSST bandpass shipped with GalSim
times an SED) and computes, from GalSim's own table and rule, the quantities
that an achromatic draw does not have: the fraction of photons collected and
the photon-weighted mean of tanh(z / 12 um) (GalSim's chromatic scale of
the brighter-fatter effect).
"""

import os

import numpy as np

from lsst_bfdrift.utils.errors import InputError

__all__ = ["LSST_BANDS", "GALSIM_ZFIT_UM", "lsst_bandpass", "blackbody_sed", "flat_sed",
           "sample_wavelengths", "galsim_abs_length", "galsim_thickness", "galsim_depth_factors"]

#: The six LSST bands whose throughputs ship with GalSim (``share/bandpasses/LSST_<b>.dat``).
LSST_BANDS = ("u", "g", "r", "i", "z", "y")

#: GalSim's conversion-height scale of the boundary distortions (um): tanh(z / zfit).
GALSIM_ZFIT_UM = 12.0

_H_C_OVER_K_NM_K = 1.438777e7  # h c / k_B in nm K


def _galsim():
    import galsim  # galsim: heavy, imported only where GalSim runs
    return galsim


def lsst_bandpass(band):
    """GalSim's LSST throughput of one band (``share/bandpasses/LSST_<band>.dat``).

    Parameters
    ----------
    band : str
        One of :data:`LSST_BANDS`.

    Returns
    -------
    galsim.Bandpass
        Wavelengths in nm, AB zero point set.
    """
    if band not in LSST_BANDS:
        raise InputError(f"unknown band {band!r}; known: {', '.join(LSST_BANDS)}")
    galsim = _galsim()
    path = os.path.join(galsim.meta_data.share_dir, "bandpasses", f"LSST_{band}.dat")
    return galsim.Bandpass(path, "nm").withZeropoint("AB")


def blackbody_sed(temperature):
    """A blackbody SED in photons per nm (shape only), as a ``galsim.SED``.

    Parameters
    ----------
    temperature : float
        Temperature (K), e.g. 10000 (a blue star) or 3500 (a red one).

    Returns
    -------
    galsim.SED
        Photon density n(lambda) proportional to lambda^-4 / (exp(hc / lambda k T) - 1).
    """
    t = float(temperature)
    if not np.isfinite(t) or t <= 0:
        raise InputError(f"temperature must be positive (K), got {temperature!r}")
    galsim = _galsim()
    wave = np.linspace(250.0, 1200.0, 1901)
    dens = wave ** -4.0 / np.expm1(_H_C_OVER_K_NM_K / (wave * t))
    table = galsim.LookupTable(wave, dens / dens.max(), interpolant="linear")
    return galsim.SED(table, "nm", "fphotons")


def flat_sed():
    """A flat photon spectrum (a white flat-field lamp within a band), as a ``galsim.SED``."""
    return _galsim().SED("1", "nm", "fphotons")


def sample_wavelengths(n, band, sed, *, seed):
    """Photon wavelengths drawn by ``galsim.WavelengthSampler`` (band throughput x SED).

    Parameters
    ----------
    n : int
        Number of photons.
    band : str
        LSST band (:data:`LSST_BANDS`).
    sed : galsim.SED
        Source spectrum (:func:`blackbody_sed`, :func:`flat_sed`).
    seed : int
        Seed of the sampling (``galsim.BaseDeviate``).

    Returns
    -------
    ndarray, shape (n,)
        Wavelengths (nm).
    """
    n = int(n)
    if n < 0:
        raise InputError(f"n must be >= 0, got {n}")
    galsim = _galsim()
    pa = galsim.PhotonArray(max(n, 1))
    galsim.WavelengthSampler(sed, lsst_bandpass(band)).applyTo(pa, rng=galsim.BaseDeviate(int(seed)))
    return np.asarray(pa.wavelength, float)[:n].copy()


def galsim_abs_length():
    """GalSim's absorption length of silicon (``share/sensors/abs_length.dat``).

    Returns
    -------
    wavelength, length : ndarray
        nm and um.
    """
    galsim = _galsim()
    path = os.path.join(galsim.meta_data.share_dir, "sensors", "abs_length.dat")
    data = np.loadtxt(path, skiprows=1)
    return data[:, 0].copy(), data[:, 1].copy()


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


def galsim_depth_factors(wavelength, *, thickness=100.0, zfit=GALSIM_ZFIT_UM):
    """GalSim's collection probability and mean distortion scale per wavelength.

    For depth d ~ Exp(L(lambda)): p = P(d < t) = 1 - exp(-t / L), and
    E[tanh((t - d) / zfit) | d < t] by quadrature of the truncated
    exponential (GalSim's rule, module docstring).

    Parameters
    ----------
    wavelength : array_like
        Wavelengths (nm), within GalSim's table.
    thickness : float, optional
        Sensor thickness t (um).
    zfit : float, optional
        GalSim's height scale (um).

    Returns
    -------
    collected, scale : ndarray
        Per wavelength: the probability that the photon converts in the
        silicon, and the mean tanh(z / zfit) over those that do.
    """
    lam = np.atleast_1d(np.asarray(wavelength, float))
    wt, lt = galsim_abs_length()
    if np.any(lam < wt[0]) or np.any(lam > wt[-1]) or not np.all(np.isfinite(lam)):
        raise InputError(f"wavelengths must lie within GalSim's table {wt[0]:g}-{wt[-1]:g} nm")
    length = np.interp(lam, wt, lt)
    t = float(thickness)
    # quadrature over the collected depths: d = -L ln(1 - u p), u uniform on (0, 1)
    u = (np.arange(2000) + 0.5) / 2000
    p = -np.expm1(-t / length)
    d = -length[:, None] * np.log1p(-u[None, :] * p[:, None])
    scale = np.tanh((t - d) / float(zfit)).mean(axis=1)
    return p, scale
