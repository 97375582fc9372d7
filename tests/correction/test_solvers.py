"""Tests of lsst_bfdrift.correction.solvers: the public solvers refuse images
outside the model's range (issue 20, F12) and conserve flux inside it
(conservation law: the sum of the image is unchanged)."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.correction.solvers import (MAX_SWEEP, correct_half_shift, correct_image,
                                             correct_series)
from lsst_bfdrift.templates.swept import OperatorCache
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.correction.settings import REFERENCE

SOLVERS = (correct_image, correct_series, correct_half_shift)


@pytest.fixture(scope="module")
def limit():
    tpl = load_default_template()
    return tpl, MAX_SWEEP / OperatorCache(tpl).kernel_abs_sum


@pytest.mark.parametrize("solver", SOLVERS)
def test_out_of_range_images_are_refused(limit, solver):
    tpl, top = limit
    rng = np.random.default_rng(5)
    img = rng.normal(1000.0, 30.0, (48, 48))
    img[20, 21] = 3.0 * top
    with pytest.raises(ValueError, match="the template would sweep"):
        solver(img, tpl)
    img[20, 21] = np.nan           # non-finite pixels are blocked, not out of range
    flux = solver(img, tpl)[0]
    assert np.isnan(flux[20, 21])
    img[20, 21] = 0.5 * top        # inside: flux conserved
    flux = solver(img, tpl)[0]
    assert_allclose(flux.sum(), img.sum(), rtol=1e-12)
    assert not np.allclose(flux, img)


@pytest.mark.parametrize("kw", [dict(start="image", strip=None),
                                dict(start="image", strip=16),
                                dict(start="series", strip=16, sparse=True)])
def test_progress_is_reported_and_changes_nothing(limit, kw):
    """correct_image reports the fraction done (never decreasing, 1 at the
    end: blocks and iterations) and returns the same flux without it."""
    tpl, _ = limit
    rng = np.random.default_rng(11)
    img = rng.poisson(1000.0, (48, 40)).astype(float)
    img[20:23, 18:21] += 2e5
    seen = []
    with_p = correct_image(img, tpl, **REFERENCE.solver_kwargs(noise_tol=0.05,
                                                               progress=seen.append, **kw))
    plain = correct_image(img, tpl, **REFERENCE.solver_kwargs(noise_tol=0.05, **kw))
    assert np.array_equal(with_p[0], plain[0]) and with_p[1:] == plain[1:]
    assert seen[-1] == 1.0 and all(0 <= f <= 1 for f in seen)
    assert seen == sorted(seen)
    if kw["start"] == "image":  # the iteration ran and was reported
        assert plain[1] >= 1 and len(seen) >= 2 + (kw["strip"] is not None)
