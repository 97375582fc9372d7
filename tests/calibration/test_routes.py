"""Tests of the three calibration routes (lsst_bfdrift.calibration.routes).

Kinds: the kernel route is checked against numpy's discrete Laplacian and
the measured a-matrix (an independent reference); the Astier & Regnault
route against an a-matrix made by its own model (consistency) and on the
measured ITL a-matrix of the shared data (it runs and states its fit);
bad input by the messages.
"""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.calibration import routes as R
from lsst_bfdrift.calibration.astier23_model import Astier23Parameters, astier23_acoeffs
from lsst_bfdrift.correction.solvers import area_coefficients
from lsst_bfdrift.ptc.acoeffs import AcoeffTable, read_acoeff_table
from lsst_bfdrift.utils.errors import FitError, InputError

ITL = "/work/shared/data/measured/itl_covariances_21oct19.txt"


def test_symmetric_amatrix():
    a = np.arange(9.0).reshape(3, 3)  # [i, j]
    full = R.symmetric_amatrix(a)
    assert full.shape == (5, 5)
    assert full[2, 2] == a[0, 0] and full[2, 3] == a[1, 0] and full[3, 2] == a[0, 1]
    assert_allclose(full, full[::-1]) and assert_allclose(full, full[:, ::-1])


def test_coulton18_route_kernel_is_the_measured_amatrix():
    tab = read_acoeff_table(ITL)
    res = R.calibrate_route(tab, "coulton18")
    k = res.product.kernel
    assert k.shape == (17, 17) and res.template.meta["method"] == "coulton18"
    p = np.pad(k, 1, mode="edge")
    lap = p[1:-1, 2:] + p[1:-1, :-2] + p[2:, 1:-1] + p[:-2, 1:-1] - 4 * k
    full = R.symmetric_amatrix(tab.a)
    full[8, 8] = 0.0
    full[8, 8] = -full.sum()  # the sum rule the route applies
    inner = np.s_[2:-2, 2:-2]  # the cut kernel's border lacks its outer neighbours
    assert_allclose(lap[inner], full[inner], rtol=0, atol=1e-3 * abs(full[8, 8]))
    a_t = area_coefficients(res.template)
    assert_allclose(a_t[inner], full[inner], rtol=0, atol=1e-2 * abs(full[8, 8]))


def test_astier23_route_on_its_own_model():
    """Consistency: an a-matrix made by the model (3 % errors, no noise) gives back
    its shifts and a template of that a-matrix."""
    truth = Astier23Parameters(alpha=-2.0e-7, z_q=0.3, z_sh=0.5, z_sv=0.2, a=0.5, b=0.3)
    a = astier23_acoeffs(truth, 4)
    tab = AcoeffTable(a, 0.03 * np.abs(a) + 1e-11, source="model")
    res = R.calibrate_route(tab, "astier23")
    assert res.chi2 < 1e-6 and res.dof == 25 - 6
    assert res.template.meta["method"] == "astier23"
    a_t = area_coefficients(res.template)
    c = res.template.center
    got = a_t[c:c + 4, c:c + 4].T
    # to the second-order terms of ln(area) at the template charge (1e4 e); a00 is the
    # template's sum rule, short of the model's by the area beyond the template
    assert_allclose(got[0, 0], a[0, 0], rtol=3e-3)
    got[0, 0] = a[0, 0]
    assert_allclose(got, a[:4, :4], rtol=0, atol=5e-4 * abs(a[0, 0]))


def test_astier23_route_on_the_measured_itl_amatrix():
    res = R.calibrate_route(read_acoeff_table(ITL), "astier23")
    assert res.dof == 81 - 1 - 6  # a00 is set by the sum rule in this file: left out
    assert np.isfinite(res.chi2) and res.chi2 / res.dof < 3.0
    assert set(res.product.fit_params) >= {"alpha", "z_q", "z_sh", "z_sv", "a", "b"}


def test_bad_input():
    with pytest.raises(InputError, match="model must be one of electrostatic, astier23, "
                                         "coulton18"):
        R.calibrate_route(None, "kernel")
    a00 = AcoeffTable(np.array([[-2.6e-6]]), np.array([[1e-7]]), source="ptc.txt")
    with pytest.raises(FitError, match="ptc.txt: the astier23 route fits 6 parameters .* this "
                                       "input has 1"):
        R.calibrate_route(a00, "astier23")
    with pytest.raises(InputError, match="kernel size must be odd and >= 17"):
        R.coulton18_route(read_acoeff_table(ITL), size=15)
