"""Tests of the Astier & Regnault 2023 model (lsst_bfdrift.calibration.astier23_model).

Kinds: the field integral is checked against a direct numerical integral of
Coulomb's law over the charge rectangle, its images and the drift height
(an independent reference, scipy's quadrature); the symmetries and the
image series' convergence against the model's own statements; the fit's
recovery of known parameters is a consistency check (the model against
itself), labelled as such.
"""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import integrate

from lsst_bfdrift.calibration import astier23_model as M
from lsst_bfdrift.utils.errors import FitError, InputError


def _direct_field_integral(x, y, stop, p, images=3):
    """int_stop^t E_x dz of a unit charge uniform over the a x b rectangle at z_q,
    with the images of a slab, by nested quadrature (no closed form used)."""
    t = p.thickness
    heights = [(2 * n * t + p.z_q, 1.0) for n in range(-images, images + 1)] + \
        [(2 * n * t - p.z_q, -1.0) for n in range(-images, images + 1)]

    def ex(z, yy, xx):
        out = 0.0
        for zc, q in heights:
            dx, dy, dz = x - xx, y - yy, z - zc
            out += q * dx / (dx * dx + dy * dy + dz * dz) ** 1.5
        return out / (p.a * p.b)

    val, _ = integrate.tplquad(ex, -p.a / 2, p.a / 2, -p.b / 2, p.b / 2, stop, t,
                               epsabs=1e-12, epsrel=1e-9)
    return val


@pytest.mark.parametrize("x, y, stop", [(0.5, 0.1, 0.3), (1.5, -0.4, 0.0), (0.5, 2.3, 1.2)])
def test_field_integral_against_direct_quadrature(x, y, stop):
    """The closed-form z integral and the 4 x 4 Gauss rule over the rectangle
    agree with scipy's triple quadrature of Coulomb's law to 3e-5 relative
    (the rule's error at the aggressor's own edge, 1e-5, is far below any
    measured a_ij's error)."""
    p = M.Astier23Parameters(alpha=1.0, z_q=0.4, a=0.5, b=0.3, images=3)
    got = M._field_integral(np.array([x]), np.array([y]), stop, p)[0]
    ref = _direct_field_integral(x, y, stop, p, images=3)
    assert_allclose(got, ref, rtol=3e-5)


def test_image_series_has_converged():
    """20 image pairs against 80: the a_ij differ by < 1e-6 of a00."""
    a20 = M.astier23_acoeffs(M.Astier23Parameters(alpha=-1.0, images=20), 6)
    a80 = M.astier23_acoeffs(M.Astier23Parameters(alpha=-1.0, images=80), 6)
    assert np.max(np.abs(a20 - a80)) < 1e-6 * abs(a80[0, 0])


def test_square_charge_and_equal_stops_are_isotropic():
    p = M.Astier23Parameters(alpha=-1e-7, a=0.4, b=0.4, z_sh=0.5, z_sv=0.5)
    a = M.astier23_acoeffs(p, 5)
    assert_allclose(a, a.T, rtol=1e-10, atol=1e-22)
    a_n, a_s, a_e, a_w = M.astier23_shifts(p, 5)
    assert_allclose(a_n, a_e.T, rtol=1e-10, atol=1e-22)


def test_shape_of_the_effect():
    """The aggressor shrinks (a00 < 0), its neighbours grow; a deeper stop of the
    row boundaries (z_sh > z_sv) makes the parallel neighbour grow less; the
    edge shifts of pixel (0, 0) are equal on opposite edges (symmetry)."""
    p = M.Astier23Parameters(alpha=-1e-7)
    a = M.astier23_acoeffs(p, 4)
    assert a[0, 0] < 0 and a[0, 1] > 0 and a[1, 0] > 0 and a[1, 1] > 0
    a_n, a_s, a_e, a_w = M.astier23_shifts(p, 4)
    assert_allclose(a_n[0, 0], a_s[0, 0], rtol=1e-12)
    assert_allclose(a_e[0, 0], a_w[0, 0], rtol=1e-12)
    assert a_n[0, 0] < 0  # the edges of the aggressor move inwards
    deeper = M.astier23_acoeffs(p.replace(z_sh=1.5), 4)
    assert deeper[0, 1] < a[0, 1]
    assert a[0, 0] == pytest.approx(4 * a_n[0, 0] * 0 + a_n[0, 0] + a_s[0, 0] + a_e[0, 0]
                                    + a_w[0, 0])


def test_fit_recovers_its_own_parameters():
    """Consistency (the model against itself): a-matrix made by the model with
    3 % errors, no noise, is fitted back to its parameters."""
    truth = M.Astier23Parameters(alpha=-2.1e-7, z_q=0.35, z_sh=0.45, z_sv=0.2, a=0.45, b=0.25)
    a = M.astier23_acoeffs(truth, 5)
    sigma = 0.03 * np.abs(a) + 1e-10
    fit = M.fit_astier23(a, sigma, start=M.Astier23Parameters())
    assert fit.chi2 < 1e-6 and fit.dof == 36 - 6
    for name in fit.names:
        assert getattr(fit.params, name) == pytest.approx(getattr(truth, name), rel=1e-3)
    assert_allclose(fit.model, a, rtol=1e-6, atol=1e-12)


def test_bad_input():
    a = np.zeros((3, 3))
    with pytest.raises(InputError, match="square arrays of one shape"):
        M.fit_astier23(a, np.ones((2, 2)))
    with pytest.raises(InputError, match="errors must be positive"):
        M.fit_astier23(a, -np.ones((3, 3)))
    with pytest.raises(InputError, match="unknown Astier & Regnault parameters"):
        M.fit_astier23(a, np.ones((3, 3)), free=("alpha", "xi0"))
    with pytest.raises(FitError, match="4 lags cannot constrain 6 parameters"):
        M.fit_astier23(np.ones((2, 2)), np.ones((2, 2)))
    with pytest.raises(InputError, match="max_lag"):
        M.astier23_shifts(M.Astier23Parameters(), 0)
