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


def test_a_negative_image_is_named():
    """Issue 44 item 5: the sample star times -1 (median far below zero) is named."""
    rng = np.random.default_rng(7)
    img = -(1000.0 + rng.normal(0.0, 30.0, (64, 64)))
    img[30:34, 30:34] = -1e5
    warnings = input_warnings(img, np.zeros(img.shape, bool))
    assert any("mostly negative" in w for w in warnings)
    assert not any("mostly negative" in w for w in input_warnings(-img, np.zeros(img.shape,
                                                                                  bool)))
