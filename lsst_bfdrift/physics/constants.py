"""Physical constants used by the electrostatic kernels, converted once.

All kernels work in plain float64 with lengths in micrometres (um), electric
fields in V/um, charges in electrons (e), line-dipole moments per unit length
in e (that is e um / um) and point-dipole moments in e um.

References
----------
* Elementary charge and vacuum permittivity: the CODATA release of the
  installed astropy (CODATA 2022 for astropy >= 7), through
  :mod:`astropy.constants`.
* Planck's constant times the speed of light, and Boltzmann's constant
  (the photon energies and thermal factors of the absorption model): likewise.
* Relative permittivity of silicon, 11.7: S. M. Sze and K. K. Ng, *Physics of
  Semiconductor Devices*, 3rd ed. (Wiley, 2007), Appendix G; the value used by
  the Poisson_CCD solver behind GalSim's sensor files.
"""

from astropy import constants as const
from astropy import units as u

__all__ = ["EPS_SI", "COULOMB_UM", "SPACE_CHARGE_UM", "HC_EV_NM", "K_B_EV"]

#: Relative permittivity of silicon (dimensionless).
EPS_SI = 11.7

_eps = const.eps0.si * EPS_SI

#: e / (4 pi eps0 eps_Si) in V um: the field of one electron's charge at 1 um
#: is ``COULOMB_UM`` V/um.
COULOMB_UM = float((const.e.si / (4 * 3.141592653589793 * _eps)).to_value(u.V * u.um))

#: e / (eps0 eps_Si) per cm^-3 of doping, in V/um^2: the field gradient of a
#: depleted layer with unit (1 cm^-3) acceptor density.
SPACE_CHARGE_UM = float((const.e.si * u.cm**-3 / _eps).to_value(u.V / u.um**2))

#: h c in eV nm: a photon of wavelength L nm carries HC_EV_NM / L eV.
HC_EV_NM = float((const.h * const.c).to_value(u.eV * u.nm))

#: Boltzmann's constant in eV/K.
K_B_EV = float(const.k_B.to_value(u.eV / u.K))
