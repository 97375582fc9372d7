"""Where photons convert: depth distributions of a band or a wavelength.

A photon of wavelength lambda entering the backside (z = t, the entrance
window) converts at depth d = t - z with the exponential law
``exp(-d / L) / L``, L the absorption length of silicon
(:func:`~lsst_bfdrift.physics.absorption.absorption_length`: GalSim's
``share/sensors/abs_length.dat``, Green 2008 at 300 K, the table
galsim.SiliconSensor draws its depths from; at another ``temperature``
scaled by the Rajkanan, Singh & Shewchun model's change with temperature).
A band mixes wavelengths with weights ``T(lambda) N(lambda)``: the band's throughput (the LSST total
throughputs ``LSST_u.dat`` .. ``LSST_y.dat`` that ship with GalSim, airmass
1.2) times the photon spectrum of the source (:func:`sed_photons`).

Photons that cross the whole thickness without converting are not detected:
the distribution is normalised over the silicon, ``0 <= z <= t``, i.e. over
the detected photons (the fraction detected is
:attr:`DepthDistribution.converted_fraction`; 0.64 in y for a flat spectrum
and a 100 um sensor).

A template's displacements are linear in the weights of the conversion
heights, so a band's template is the weighted mean of templates built on one
shared grid of heights (:func:`conversion_nodes`), with the weights of
:meth:`DepthDistribution.node_weights`: the integrals of the distribution
against the hat functions of the grid (piecewise-linear interpolation of the
displacements in z between nodes, computed in closed form for every
wavelength, so that a u-band distribution 0.01 um deep is weighted as
exactly as a y-band one 100 um deep).
"""

import os

import numpy as np

from lsst_bfdrift.physics.absorption import (absorption_length, absorption_table_range,
                                             check_temperature)
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["BANDS", "DepthDistribution", "depth_distribution", "bandpass", "sed_photons",
           "conversion_nodes", "normalize_band", "GALSIM_ZFIT", "galsim_depth_factor"]

#: The LSST bands, blue to red.
BANDS = ("u", "g", "r", "i", "z", "y")

#: GalSim's depth scale (um) of the boundary distortions: galsim.SiliconSensor
#: scales every boundary displacement by ``tanh(zconv / 12 um)`` for a photon
#: converting at ``zconv`` above the front side (``Silicon::insidePixel``,
#: "an empirical fit to the Poisson solver simulations").
GALSIM_ZFIT = 12.0

#: Step (nm) of the wavelength grid a band is integrated on.
_WAVELENGTH_STEP = 0.5


def normalize_band(band):
    """The LSST band name of ``band`` ('u' .. 'y'), or InputError naming it.

    Accepts the band letter in either case, optionally with a filter suffix
    or prefix as LSST's physical filters and GalSim's file names spell them
    (``'r_57'``, ``'LSST_r'``, ``'lsst r'``).
    """
    if not isinstance(band, str):
        raise InputTypeError(f"band must be a string, one of {', '.join(BANDS)}; got "
                             f"{band!r}")
    s = band.strip()
    low = s.lower()
    for prefix in ("lsst_", "lsst ", "lsst-"):
        if low.startswith(prefix):
            low = low[len(prefix):]
    if "_" in low:
        low = low.split("_", 1)[0]
    if low in BANDS:
        return low
    raise InputError(f"unknown band {band!r}; accepted: {', '.join(BANDS)} (optionally with a "
                     "filter suffix such as 'r_57')")


def bandpass(band):
    """The LSST total throughput of ``band``: (wavelength in nm, throughput 0..1).

    Read from GalSim's ``share/bandpasses/LSST_<band>.dat`` (from
    lsst/throughputs baseline, airmass 1.2).
    """
    import galsim  # heavy: only for its files

    b = normalize_band(band)
    path = os.path.join(galsim.meta_data.share_dir, "bandpasses", f"LSST_{b}.dat")
    wl, thr = np.loadtxt(path).T
    return wl, thr


def _planck_photons(wavelength, temperature):
    """Photons per nm of a black body (arbitrary scale) at ``wavelength`` nm."""
    hc_over_k = 1.438776877e7  # nm K
    x = hc_over_k / (np.asarray(wavelength, float) * float(temperature))
    return np.asarray(wavelength, float) ** -4 / np.expm1(x)


def sed_photons(sed, wavelength):
    """Photons per nm of the spectrum ``sed`` at ``wavelength`` (nm), arbitrary scale.

    Parameters
    ----------
    sed : None, str, float or galsim.SED
        None or ``'flat'``: flat in photons per nm. A number or
        ``'blackbody:T'`` / ``'T K'``: a black body of temperature T (K). A
        galsim.SED: its photon density. Another string: the name of one of
        GalSim's SED files (``share/SEDs``: ``'vega'``, ``'CWW_E_ext'``,
        ``'CWW_Sbc_ext'``, ``'CWW_Scd_ext'``, ``'CWW_Im_ext'``, with or
        without the extension).
    wavelength : array_like
        Wavelengths (nm).

    Returns
    -------
    ndarray
        Photon density (arbitrary units, >= 0).
    """
    wl = np.asarray(wavelength, float)
    if sed is None or (isinstance(sed, str) and sed.strip().lower() == "flat"):
        return np.ones_like(wl)
    if isinstance(sed, (int, float, np.number)) and not isinstance(sed, bool):
        return _planck_photons(wl, _temperature(sed, sed))
    if isinstance(sed, str):
        s = sed.strip()
        low = s.lower()
        if low.startswith("blackbody:") or low.endswith("k"):
            num = low.split(":", 1)[1] if low.startswith("blackbody:") else low[:-1]
            try:
                t = float(num)
            except ValueError:
                t = None
            if t is not None or low.startswith("blackbody:"):
                return _planck_photons(wl, _temperature(t, sed))
        return _galsim_sed(s)(wl)
    try:
        out = np.asarray(sed(wl), float)
    except Exception as exc:  # a galsim.SED outside its range, or not a spectrum at all
        raise InputTypeError(f"sed {sed!r} cannot be evaluated at {wl.min():g}-{wl.max():g} nm "
                             f"({exc}); accepted: None/'flat', a temperature (K), "
                             "'blackbody:T', a GalSim SED file name or a galsim.SED") from exc
    return out


def _temperature(t, given):
    if t is None or not np.isfinite(t) or t <= 0:
        raise InputError(f"black-body temperature must be a positive number of K, got "
                         f"{given!r}")
    return float(t)


def _galsim_sed(name):
    """galsim.SED of one of GalSim's SED files (by name, extension optional)."""
    import galsim

    folder = os.path.join(galsim.meta_data.share_dir, "SEDs")
    known = sorted(f for f in os.listdir(folder) if not f.startswith("README"))
    match = [f for f in known if f == name or os.path.splitext(f)[0] == name]
    if not match:
        raise InputError(f"unknown sed {name!r}; accepted: 'flat', a temperature such as "
                         f"'5800K' or 'blackbody:5800', or one of GalSim's SEDs "
                         f"{[os.path.splitext(f)[0] for f in known]}")
    fname = match[0]
    # vega.txt is in nm and erg/s/cm^2/nm; the CWW files are in Angstrom and flambda
    wave_type = "nm" if fname.startswith("vega") else "Angstrom"
    return galsim.SED(os.path.join(folder, fname), wave_type=wave_type, flux_type="flambda")


class DepthDistribution:
    """Conversion heights of the detected photons of a band or a wavelength.

    Heights z are in um above the front side (the gates, z = 0); the
    entrance window is at ``thickness``. The density is a mixture of
    truncated exponentials, one per wavelength of the grid:
    ``p(z) = sum_k c_k exp(-(t - z) / L_k) / L_k`` on ``0 <= z <= t``,
    ``sum_k c_k (1 - exp(-t / L_k)) = 1``.

    Parameters
    ----------
    wavelength : ndarray
        Wavelength grid (nm).
    photons : ndarray
        Incident photons per grid point (throughput x spectrum x step), >= 0.
    thickness : float
        Silicon thickness t (um).
    label : str, optional
        What the distribution is of (the band, or ``'700nm'``).
    temperature : float, optional
        Temperature of the silicon (K; None: the table's 300 K,
        galsim.SiliconSensor's), :func:`~lsst_bfdrift.physics.absorption.absorption_length`.

    Attributes
    ----------
    wavelength, absorption : ndarray
        The grid (nm) and the absorption lengths there (um).
    coefficients : ndarray
        c_k above (per um of density, normalised over the detected photons).
    converted_fraction : float
        Fraction of the incident photons that convert in the silicon.
    """

    def __init__(self, wavelength, photons, thickness, *, label="", temperature=None):
        self.wavelength = np.atleast_1d(np.asarray(wavelength, float))
        photons = np.atleast_1d(np.asarray(photons, float))
        self.thickness = float(thickness)
        self.label = str(label)
        if not (np.isfinite(self.thickness) and self.thickness > 0):
            raise InputError(f"thickness must be a positive number of um, got {thickness!r}")
        if photons.shape != self.wavelength.shape or np.any(photons < 0) or \
                not np.all(np.isfinite(photons)) or photons.sum() <= 0:
            raise InputError("photon weights must be finite, >= 0, not all 0, one per "
                             "wavelength")
        self.temperature = None if temperature is None else check_temperature(temperature)
        self.absorption = absorption_length(self.wavelength, temperature=self.temperature)
        detected = photons * -np.expm1(-self.thickness / self.absorption)
        self.converted_fraction = float(detected.sum() / photons.sum())
        self.coefficients = photons / detected.sum()

    def _parts(self, z):
        """Per wavelength: exp(-(t - z) / L), shape (nw, nz)."""
        d = self.thickness - np.asarray(z, float)
        return np.exp(-d[None, :] / self.absorption[:, None])

    def pdf(self, z):
        """Density (1/um) of conversion heights ``z`` (um); 0 outside [0, t]."""
        z = np.atleast_1d(np.asarray(z, float))
        inside = (z >= 0) & (z <= self.thickness)
        out = (self.coefficients[:, None] / self.absorption[:, None] *
               self._parts(np.clip(z, 0, self.thickness))).sum(axis=0)
        return np.where(inside, out, 0.0)

    def cdf(self, z):
        """Fraction of the detected photons converting below height ``z`` (um)."""
        z = np.clip(np.atleast_1d(np.asarray(z, float)), 0, self.thickness)
        e0 = np.exp(-self.thickness / self.absorption)
        return (self.coefficients[:, None] * (self._parts(z) - e0[:, None])).sum(axis=0)

    @property
    def mean_height(self):
        """Mean conversion height (um) of the detected photons."""
        t, L = self.thickness, self.absorption
        e0 = np.exp(-t / L)
        # int_0^t z e^{(z-t)/L} / L dz = t - L (1 - e0)
        return float(np.sum(self.coefficients * (t - L * (1.0 - e0))))

    def expectation(self, func, *, points=4000):
        """Mean of ``func(z)`` (vectorised, z in um) over the detected photons.

        Integrated on a grid in depth that is geometric from 1e-6 um, so that
        distributions a few nm deep (u band) are resolved, and divided by the
        integral of the density on the same grid (so that the mean of a
        bounded function stays within its bounds).
        """
        t = self.thickness
        d = np.concatenate([[0.0], np.geomspace(1e-6, t, int(points))])
        z = t - d
        p = self.pdf(z)
        return float(np.trapezoid(p * np.asarray(func(z), float), d) / np.trapezoid(p, d))

    def node_weights(self, nodes):
        """Weights of the heights ``nodes`` (um, increasing, last = thickness).

        ``w_k = int_0^t p(z) phi_k(z) dz`` with phi_k the hat functions of
        the nodes (piecewise-linear interpolation in z; below the first node
        phi_0 = 1: conversions below the lowest node count as at that node).
        The weights sum to 1.
        """
        nodes = np.asarray(nodes, float)
        t = self.thickness
        if nodes.ndim != 1 or nodes.size < 2 or np.any(np.diff(nodes) <= 0) or \
                nodes[0] < 0 or not np.isclose(nodes[-1], t, rtol=0, atol=1e-9 * t):
            raise InputError(f"conversion nodes must increase strictly from >= 0 to the "
                             f"thickness {t} um, got {nodes.tolist()}")
        L = self.absorption[:, None]
        c = self.coefficients[:, None]

        def E(z):  # e^{(z - t)/L}: the antiderivative of the density's kernel
            return np.exp((np.asarray(z, float) - t) / L)

        def moment(a, b):  # int_a^b e^{(z-t)/L}/L dz and int_a^b z e^{(z-t)/L}/L dz
            ea, eb = E(a), E(b)
            return eb - ea, (b * eb - L * eb) - (a * ea - L * ea)

        w = np.zeros(nodes.size)
        m0, _ = moment(0.0, nodes[0])
        w[0] += float(np.sum(c * m0))
        for k in range(nodes.size - 1):
            a, b = nodes[k], nodes[k + 1]
            i0, i1 = moment(a, b)
            h = b - a
            up = (i1 - a * i0) / h  # int p (z - a)/h
            w[k + 1] += float(np.sum(c * up))
            w[k] += float(np.sum(c * (i0 - up)))
        return w

    def __repr__(self):
        return (f"DepthDistribution({self.label or 'custom'}: mean height "
                f"{self.mean_height:.2f} um of {self.thickness:g}, converted "
                f"{self.converted_fraction:.3f})")


def depth_distribution(source, thickness=100.0, *, sed=None, temperature=None):
    """Depth distribution of the photons of a band or of one wavelength.

    Parameters
    ----------
    source : str or float
        An LSST band ('u', 'g', 'r', 'i', 'z', 'y'; :func:`normalize_band`
        spellings) or a wavelength (nm; a float or an astropy Quantity of
        length) inside the absorption table (255-1450 nm).
    thickness : float or Quantity, optional
        Silicon thickness (um), default 100.
    sed : optional
        Spectrum of the source (:func:`sed_photons`); None: flat in photons
        per nm. Ignored for one wavelength.
    temperature : float, optional
        Temperature of the silicon (K); None: 300 K, the table's
        (:func:`~lsst_bfdrift.physics.absorption.absorption_length`). An LSST
        sensor runs at about 173 K, where z and y photons convert deeper.

    Returns
    -------
    DepthDistribution

    Examples
    --------
    Blue photons convert at the entrance window, red ones all through the
    sensor, and a third of the y-band photons cross it:

    >>> from lsst_bfdrift.physics.depth import depth_distribution
    >>> for band in ("u", "y"):
    ...     d = depth_distribution(band, 100.0)
    ...     print(band, round(d.mean_height, 1), round(d.converted_fraction, 2))
    u 100.0 1.0
    y 60.8 0.64
    """
    t = _um(thickness, "thickness")
    if isinstance(source, str):
        band = normalize_band(source)
        wl0, thr = bandpass(band)
        wl = np.arange(wl0[0], wl0[-1] + 0.5 * _WAVELENGTH_STEP, _WAVELENGTH_STEP)
        wl = wl[wl <= wl0[-1]]
        lo, hi = absorption_table_range()
        wl = np.clip(wl, lo, hi)
        photons = np.interp(wl, wl0, thr) * sed_photons(sed, wl) * _WAVELENGTH_STEP
        return DepthDistribution(wl, photons, t, label=band, temperature=temperature)
    wl = _nm(source)
    lo, hi = absorption_table_range()
    if not lo <= wl <= hi:
        raise InputError(f"wavelength {wl:g} nm is outside the silicon absorption table "
                         f"({lo:g}-{hi:g} nm, GalSim's abs_length.dat)")
    return DepthDistribution([wl], [1.0], t, label=f"{wl:g}nm", temperature=temperature)


def _um(value, name):
    if hasattr(value, "unit"):
        import astropy.units as u

        value = value.to_value(u.um)
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"{name} must be a number of um, got {value!r}") from exc
    if not (np.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a positive number of um, got {value!r}")
    return v


def _nm(value):
    if hasattr(value, "unit"):
        import astropy.units as u

        value = value.to_value(u.nm, equivalencies=u.spectral())
    if isinstance(value, bool):
        raise InputTypeError(f"wavelength must be a number of nm, got {value!r}")
    try:
        v = float(value)
    except (TypeError, ValueError) as exc:
        raise InputTypeError(f"a band or a wavelength is needed: unknown band or wavelength "
                             f"{value!r}; accepted: {', '.join(BANDS)} or a number of nm"
                             ) from exc
    if not np.isfinite(v):
        raise InputError(f"wavelength must be finite, got {value!r}")
    return v


def conversion_nodes(thickness, z_stop, n=8, *, power=2.0):
    """Shared grid of conversion heights (um) for per-band templates.

    ``z_k = z_stop + (t - z_stop) (k / (n - 1))^power``, k = 0 .. n - 1:
    denser towards the collecting wells, where the boundary displacements
    change with the conversion height (they reach 90 % of the entrance
    window's within about 12 um of the gates and are flat above 30 um, see
    ``docs/templates.rst``). The first node is the collection height, where
    a drift line ends as it starts (no displacement: no build needed).

    Parameters
    ----------
    thickness, z_stop : float
        Silicon thickness and collection height (um).
    n : int, optional
        Number of nodes (>= 2); n - 1 templates are built.
    power : float, optional
        Grading of the grid (1: uniform).
    """
    if isinstance(n, bool) or int(n) != n or n < 2:
        raise InputError(f"number of conversion nodes must be an integer >= 2, got {n!r}")
    if not 0 <= z_stop < thickness:
        raise InputError(f"collection height {z_stop} um must lie in [0, {thickness}) um")
    if not (np.isfinite(power) and power > 0):
        raise InputError(f"node grading power must be positive, got {power!r}")
    s = np.linspace(0.0, 1.0, int(n)) ** float(power)
    z = z_stop + (thickness - z_stop) * s
    z[-1] = thickness
    return z


def galsim_depth_factor(distribution, *, zfit=GALSIM_ZFIT):
    """GalSim's mean scale of the boundary displacements over ``distribution``.

    galsim.SiliconSensor moves each boundary by ``tanh(zconv / zfit)`` times
    its sensor file's displacement for a photon converting at height zconv
    (:data:`GALSIM_ZFIT`); averaged over the detected photons of a band this
    is ``E[tanh(z / zfit)]`` (0.955 in y, 1.000 in u for a flat spectrum and
    100 um).
    """
    return distribution.expectation(lambda z: np.tanh(np.asarray(z) / float(zfit)))
