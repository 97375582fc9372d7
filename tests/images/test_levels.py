"""Tests of an image's levels (lsst_bfdrift.images.levels): against numpy's
median and MAD of every pixel (an independent reference) and hand-made
plateaus."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.images.levels import ROBUST_SAMPLE, plateau_level, robust_level


def _full(image, blocked):
    good = image[~blocked]
    med = np.median(good)
    return med, 1.4826 * np.median(np.abs(good - med))


@pytest.mark.parametrize("shape, seed", [((1100, 1024), 1), ((1536, 2048), 2), ((700, 1601), 3)])
def test_robust_level_of_a_sample_matches_the_whole_image(shape, seed):
    """Independent reference: numpy's median and MAD of every unblocked pixel.
    Above ROBUST_SAMPLE pixels the strided sample agrees within its sampling
    error (a few 1e-3 of the scatter, here at most the 1 e step of Poisson counts),
    also with a column pattern at a power-of-two period and blocked rows."""
    rng = np.random.default_rng(seed)
    img = rng.poisson(1200.0, shape).astype(float)
    img[:, ::16] += 40.0  # a column pattern the stride must not alias onto
    blocked = np.zeros(shape, bool)
    blocked[100:140] = True
    img[blocked] = 1e6
    assert img.size > ROBUST_SAMPLE
    med, mad = robust_level(img, blocked)
    fmed, fmad = _full(img, blocked)
    assert abs(med - fmed) < 0.05 * fmad  # Poisson counts: medians move by whole e
    assert_allclose(mad, fmad, rtol=0.01)
    # small images: exactly numpy's
    small = img[:64, :64]
    assert robust_level(small, blocked[:64, :64]) == pytest.approx(_full(small, blocked[:64, :64]))


def test_robust_level_needs_sixteen_pixels():
    img = np.ones((8, 8))
    blocked = np.ones((8, 8), bool)
    blocked[0, :10 % 8] = False
    assert robust_level(img, blocked) == (None, None)


def test_plateau_level():
    """The largest value shared exactly by >= 3 unblocked pixels; not by two,
    not by blocked pixels, not a constant image."""
    img = np.random.default_rng(4).normal(1000.0, 30.0, (40, 40))
    assert plateau_level(img) is None
    img[3, 4:7] = 5000.0
    assert plateau_level(img) == 5000.0
    blocked = np.zeros(img.shape, bool)
    blocked[3, 4] = True
    assert plateau_level(img, blocked) is None  # two unblocked pixels left
    img[3, 4] = 4000.0
    assert plateau_level(img) is None
    assert plateau_level(np.full((8, 8), 7.0)) is None
    assert plateau_level(np.empty((0, 0))) is None
    # an integer sky: its largest count, shared by chance, is no plateau
    low = np.random.default_rng(6).poisson(2.0, (200, 200)).astype(float)
    assert np.count_nonzero(low == low.max()) >= 3 and plateau_level(low) is None


def test_plateau_under_a_masked_hot_pixel():
    """A blocked pixel above the plateau (a masked hot pixel) hides nothing:
    the plateau is the largest value of the unblocked pixels."""
    img = np.random.default_rng(8).normal(1000.0, 30.0, (40, 40))
    img[10, 10:14] = 6.0e4  # a clipped star core
    img[30, 30] = 9.9e5  # a hot pixel, masked
    blocked = np.zeros(img.shape, bool)
    blocked[30, 30] = True
    assert plateau_level(img, blocked) == 6.0e4
    assert plateau_level(img) is None  # unmasked, the hot pixel is the maximum
    assert plateau_level(img, np.ones(img.shape, bool)) is None
