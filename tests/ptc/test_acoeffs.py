"""Tests of lsst_bfdrift.ptc.acoeffs.near_field_response (S1, the 3 x 3 block's net response).

Kinds: correctness against a direct sum over the signed lags of the block,
against Monte Carlo draws of the a_ij (its error), and against GalSim's own
a-matrix, whose pixel areas conserve the total (S1 is minus the response of
every pixel beyond the block); bad input refused.
"""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.ptc.acoeffs import near_field_response
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs
from lsst_bfdrift.templates.refine import lag_multiplicity


def _block_sum(a):
    """Sum of a[|i|, |j|] over the signed lags -1..1 x -1..1, written out."""
    return sum(a[abs(i), abs(j)] for i in (-1, 0, 1) for j in (-1, 0, 1))


def test_near_field_is_the_block_sum_and_its_error_the_draws_scatter():
    rng = np.random.default_rng(7)
    a = rng.normal(0.0, 1e-7, (4, 4))
    a[0, 0] = -2.4e-6
    sigma = rng.uniform(1e-9, 5e-8, (4, 4))
    s1, err = near_field_response(a, sigma)
    assert_allclose(s1, _block_sum(a), rtol=1e-14)
    draws = np.array([near_field_response(a + sigma * rng.standard_normal(a.shape))[0]
                      for _ in range(4000)])
    assert_allclose(draws.std(), err, rtol=0.05)
    assert near_field_response(a)[1] is None
    s = sigma.copy()
    s[1, 1] = np.nan  # an unmeasured lag of the block: no error
    assert np.isnan(near_field_response(a, s)[1])


@pytest.mark.parametrize("sensor", ["lsst_itl_50_8", "lsst_e2v_50_32"])
def test_galsim_areas_conserve_so_s1_is_minus_the_rest(sensor):
    """GalSim's a-matrix (lags 0-6: its files move nothing beyond about 4 px):
    S1 equals minus the response of every pixel beyond the block within 1.5 %
    (GalSim's areas keep the total to 0.3 % of a00)."""
    a = galsim_acoeffs(sensor, 6)
    w = lag_multiplicity(6)
    w[:2, :2] = 0.0
    s1, _ = near_field_response(a)
    assert s1 < 0 and abs(s1) < 0.5 * abs(a[0, 0])  # the neighbours take back most of a00
    assert_allclose(s1, -np.sum(w * a), rtol=0.015)


def test_a00_from_the_sum_rule_gives_s1_from_the_lags_beyond():
    """A table whose a00 was set by the sum rule: S1 is minus the lags beyond the
    block (with their errors), which equals the direct formula there exactly."""
    rng = np.random.default_rng(11)
    a = rng.normal(0.0, 3e-8, (5, 5))
    w = lag_multiplicity(4)
    a[0, 0] = -np.sum(w[1:, :] * a[1:, :]) - np.sum(w[0, 1:] * a[0, 1:])  # the rule
    sigma = np.full(a.shape, 1e-9)
    sigma[0, 0] = 1e-12  # a00's stated error: not S1's
    s1, err = near_field_response(a, sigma, from_sum_rule=True)
    assert_allclose(s1, _block_sum(a), rtol=1e-10)
    beyond = np.ones(a.shape, bool)
    beyond[:2, :2] = False  # the block's lags: weights 1, 2, 2, 4
    assert_allclose(err, 1e-9 * np.sqrt(np.sum(w[beyond] ** 2)), rtol=1e-12)


def test_bad_input():
    with pytest.raises(ValueError,
                       match=r"needs lags 0-1 on both axes, got a_ij of shape \(1, 1\)"):
        near_field_response([[-2e-6]])
    with pytest.raises(ValueError, match="shape \\(3,\\)"):
        near_field_response([1.0, 2.0, 3.0])
