"""Tests of the input warnings (lsst_bfdrift.correction.checks)."""

import numpy as np

from lsst_bfdrift.correction.checks import input_warnings


def test_warnings_need_sixteen_pixels():
    img = np.ones((8, 8))
    blocked = np.ones((8, 8), bool)
    blocked[0, :2] = False
    assert input_warnings(img, blocked) == []


def test_warnings_do_not_modify_the_input():
    rng = np.random.default_rng(5)
    img = 15000.0 + rng.normal(0.0, 5.0, (1100, 1000))
    blocked = np.zeros(img.shape, bool)
    before = img.copy()
    warnings = input_warnings(img, blocked)
    assert any("bias pedestal" in w for w in warnings)
    assert np.array_equal(img, before)
