"""Absorption of light in silicon: the absorption length at a wavelength and a temperature.

The table is GalSim's ``share/sensors/abs_length.dat`` (Green 2008, silicon
at 300 K, 255-1450 nm), the table galsim.SiliconSensor draws its conversion
depths from, so that at 300 K the package's depths are GalSim's.

An LSST sensor runs at about 173 K (-100 C). Cooling widens silicon's band
gap, and near the gap, where the absorption is indirect (phonon-assisted),
it weakens steeply: red photons convert deeper. At another temperature the
table is scaled by the ratio of absorption coefficients of the
parameterisation of Rajkanan, Singh & Shewchun (1979, Solid-State
Electronics 22, 793; the form used for CCD quantum efficiencies at
operating temperature, e.g. by the LBNL CCD group's tables at 77-300 K):

.. math::

    \\alpha(E, T) = \\sum_{i,j=1}^{2} C_i A_j \\left[
        \\frac{(E - E_{gj}(T) + E_{pi})^2}{e^{E_{pi}/kT} - 1} +
        \\frac{(E - E_{gj}(T) - E_{pi})^2}{1 - e^{-E_{pi}/kT}} \\right]
        + A_d \\sqrt{E - E_{gd}(T)}

each bracket term taken only where its base is positive, with the band gaps
``E_g(T) = E_g(0) - beta T^2 / (T + gamma)`` (Varshni) and the constants of
:data:`RAJKANAN`. So

``L(lambda, T) = L_table(lambda) * alpha(lambda, 300 K) / alpha(lambda, T)``:

the measured table keeps its shape, the model gives only the change with
temperature, which is set by the gaps' shift and the phonon populations
rather than by the model's absolute level (the model's own 300 K lengths
are 0.61-0.97 of the table's from 450 to 1050 nm;
``benchmarks/calibration/band_temperature.py`` prints them). The ratio is defined where
the model absorbs at both temperatures (photon energies above the indirect
gap less a phonon, out to about 1100 nm at 173 K); beyond that
:func:`absorption_length` refuses a temperature.
"""

import functools
import os

import numpy as np
from astropy import units as u

from lsst_bfdrift.physics.constants import HC_EV_NM, K_B_EV
from lsst_bfdrift.utils.errors import InputError

__all__ = ["absorption_length", "absorption_table_range", "check_temperature", "rajkanan_alpha",
           "RAJKANAN", "TABLE_TEMPERATURE", "TEMPERATURE_RANGE"]

#: Temperature (K) of GalSim's table.
TABLE_TEMPERATURE = 300.0
#: Temperatures (K) the scaling is offered for (the parameterisation's fitted range).
TEMPERATURE_RANGE = (20.0, 500.0)

#: Rajkanan, Singh & Shewchun (1979): phonon energies E_p1, E_p2 (eV) and their
#: weights C1, C2; indirect gaps at 0 K E_g1, E_g2 (eV) and strengths A1, A2
#: (1/(cm eV^2)); direct gap E_gd (eV) and strength A_d (1/(cm eV^0.5)); Varshni
#: beta (eV/K) and gamma (K).
RAJKANAN = {"E_p": (1.827e-2, 5.773e-2), "C": (5.5, 4.0),
            "E_g": (1.1557, 2.5), "A": (3.231e2, 7.237e3),
            "E_gd": 3.2, "A_d": 1.052e6, "beta": 7.021e-4, "gamma": 1108.0}


@functools.lru_cache(maxsize=1)
def _table():
    """GalSim's table (nm, um), read once per process (read-only)."""
    import galsim  # heavy: only for its table

    path = os.path.join(galsim.meta_data.share_dir, "sensors", "abs_length.dat")
    table = np.loadtxt(path, skiprows=1)
    table.flags.writeable = False
    return table


def absorption_table_range():
    """(shortest, longest) wavelength (nm) of the silicon absorption table."""
    wl = _table()[:, 0]
    return float(wl[0]), float(wl[-1])


def check_temperature(temperature):
    """A silicon temperature as K (float), checked against :data:`TEMPERATURE_RANGE`.

    Parameters
    ----------
    temperature : float or Quantity
        K, or an astropy Quantity of temperature (deg_C included).

    Returns
    -------
    float

    Raises
    ------
    InputError
        Not a temperature, not finite, or outside the range.
    """
    try:
        t = (float(temperature.to_value(u.K, equivalencies=u.temperature()))
             if isinstance(temperature, u.Quantity) else float(temperature))
    except (TypeError, ValueError, u.UnitsError) as exc:
        raise InputError(f"temperature must be a number of K or a Quantity of temperature, "
                         f"got {temperature!r}") from exc
    lo, hi = TEMPERATURE_RANGE
    if not (np.isfinite(t) and lo <= t <= hi):
        raise InputError(f"temperature must lie in [{lo:g}, {hi:g}] K (the absorption "
                         f"model's range), got {temperature!r}")
    return t


def rajkanan_alpha(wavelength, temperature):
    """Absorption coefficient of silicon (1/cm) of Rajkanan, Singh & Shewchun (1979).

    Parameters
    ----------
    wavelength : array_like
        Wavelength (nm), > 0.
    temperature : float
        Temperature (K), in :data:`TEMPERATURE_RANGE`.

    Returns
    -------
    ndarray
        alpha (1/cm); 0 where no term absorbs (below the indirect gap less
        the largest phonon energy).
    """
    wl = np.asarray(wavelength, float)
    if np.any(~np.isfinite(wl)) or np.any(wl <= 0):
        raise InputError("wavelength must be finite and positive (nm)")
    t = check_temperature(temperature)
    p = RAJKANAN
    energy = HC_EV_NM / wl
    shift = p["beta"] * t * t / (t + p["gamma"])
    kt = K_B_EV * t
    alpha = np.zeros_like(energy)
    for ep, c in zip(p["E_p"], p["C"]):
        absorb = 1.0 / np.expm1(ep / kt)            # phonon absorbed
        emit = 1.0 / -np.expm1(-ep / kt)            # phonon emitted
        for eg0, a in zip(p["E_g"], p["A"]):
            eg = eg0 - shift
            up = np.clip(energy - eg + ep, 0.0, None)
            down = np.clip(energy - eg - ep, 0.0, None)
            alpha += c * a * (up * up * absorb + down * down * emit)
    alpha += p["A_d"] * np.sqrt(np.clip(energy - (p["E_gd"] - shift), 0.0, None))
    return alpha


def absorption_length(wavelength, *, temperature=None):
    """Absorption length of photons in silicon (um) at ``wavelength`` (nm).

    Parameters
    ----------
    wavelength : array_like
        Wavelength (nm), within the table (:func:`absorption_table_range`).
    temperature : float, optional
        Temperature of the silicon (K). None (the default): the table's,
        300 K, which is galsim.SiliconSensor's. Another temperature scales
        the table by ``alpha(lambda, 300 K) / alpha(lambda, T)`` of
        :func:`rajkanan_alpha` (module docstring).

    Returns
    -------
    ndarray or float
        L (um).

    Raises
    ------
    InputError
        A wavelength outside the table; a temperature outside
        :data:`TEMPERATURE_RANGE`, or at a wavelength where the model does
        not absorb at one of the two temperatures (beyond about 1100 nm at
        173 K).
    """
    table = _table()
    wl = np.asarray(wavelength, dtype=float)
    if np.any(~np.isfinite(wl)) or np.any(wl < table[0, 0]) or np.any(wl > table[-1, 0]):
        raise InputError(f"wavelength must lie in [{table[0, 0]}, {table[-1, 0]}] nm")
    length = np.interp(wl, table[:, 0], table[:, 1])
    if temperature is None:
        return length
    t = check_temperature(temperature)
    if t == TABLE_TEMPERATURE:
        return length
    a_ref, a_t = rajkanan_alpha(wl, TABLE_TEMPERATURE), rajkanan_alpha(wl, t)
    bad = (a_ref <= 0) | (a_t <= 0)
    if np.any(bad):
        raise InputError(f"no absorption model at {t:g} K beyond "
                         f"{float(np.min(wl[bad])):g} nm (silicon is transparent there in the "
                         "Rajkanan model): use wavelengths below about 1100 nm with a "
                         "temperature")
    return length * a_ref / a_t
