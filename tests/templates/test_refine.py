"""Area refinement of templates: exact polygon areas, conservation, curl-free shifts."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.refine import (area_response_directions, combine_templates,
                                          curl_free_template, match_area_coefficients,
                                          template_alpha, template_difference)
from lsst_bfdrift.templates.template import TemplateSettings, build_template
from lsst_bfdrift.utils.errors import InputError


@pytest.fixture(scope="module")
def pair():
    s = TemplateSettings(size=9, edge_samples=4, tol=1e-4, aggressor_charge=1e4, workers=2)
    return (build_template(SensorParameters(), s),
            build_template(SensorParameters(channel_depth=1.2, xi_ck=8.0), s))


def test_alpha_is_the_linear_response(pair):
    """alpha from two charges equals the finite-difference derivative of
    the exact polygon areas at small charge."""
    t = pair[0]
    q = 1e-3 * t.charge
    deriv = (t.moments(charge=q).area - t.moments(charge=-q).area) / (2 * q)
    assert_allclose(template_alpha(t), deriv, rtol=1e-6, atol=1e-14)


def test_matches_another_templates_areas(pair):
    """Refining template A to template B's a_ij reproduces B's exact
    polygon areas' linear response at the matched lags; the added edge
    shifts are a gradient (zero circulation round every interior corner);
    the corners and the outer boundary do not move; the area sum is kept."""
    a_t, b_t = pair
    c = a_t.center
    target = template_alpha(b_t)[c:c + 4, c:c + 4].T  # lags 0..3, [i, j]
    before = np.abs(template_alpha(a_t)[c:c + 4, c:c + 4].T / target - 1).max()
    r = match_area_coefficients(a_t, target)
    got = template_alpha(r)[c:c + 4, c:c + 4].T
    assert before > 0.1
    assert_allclose(got, target, rtol=0, atol=1e-10)  # a00 ~ 5e-6
    assert_allclose(template_alpha(r).sum(), template_alpha(a_t).sum(), atol=1e-12)
    assert_allclose(r.corner_d, a_t.corner_d, atol=0)
    uv = (r.vedge_d - a_t.vedge_d)[..., 0]  # uniform along each edge
    uh = (r.hedge_d - a_t.hedge_d)[..., 0]
    assert_allclose(r.vedge_d - a_t.vedge_d, np.repeat(uv[..., None], 4, -1), atol=1e-15)
    assert_allclose(uv[:, [0, -1]], 0, atol=0)
    assert_allclose(uh[[0, -1], :], 0, atol=0)
    # circulation round interior corner (J, I): right-hand loop of the shift field
    circ = uv[1:, 1:-1] - uv[:-1, 1:-1] - (uh[1:-1, 1:] - uh[1:-1, :-1])
    assert np.abs(circ).max() < 1e-3 * np.abs(uv).max()
    assert r.meta["area_refined"]["max_lag"] == 3


def test_curl_free_template_keeps_the_areas_and_drops_the_curl(pair):
    """curl_free_template: the same linear area response as the model
    template at every lag it holds (exact polygon areas), no circulation
    round any interior corner (a gradient field), corners unmoved; the model
    template itself does have a divergence-free part, which is what the
    difference carries."""
    t = pair[1]
    c = t.center
    cf = curl_free_template(t)
    want = template_alpha(t)[c:2 * c, c:2 * c]
    # to 2e-5 of a00: the outer ring, which cannot move, keeps zero area change
    # and the matched lags share what the model's outer ring carried
    assert_allclose(template_alpha(cf)[c:2 * c, c:2 * c], want, rtol=0,
                    atol=2e-5 * np.abs(want).max())
    assert_allclose(cf.corner_d, 0, atol=0)

    def circulation(tpl):
        # effective shift of each edge: trapezoid over corners and samples
        f = np.concatenate([[0.0], tpl.fractions, [1.0]])
        uv = np.trapezoid(np.concatenate([tpl.corner_d[:-1, :, :1], tpl.vedge_d,
                                          tpl.corner_d[1:, :, :1]], axis=-1), f, axis=-1)
        uh = np.trapezoid(np.concatenate([tpl.corner_d[:, :-1, 1:], tpl.hedge_d,
                                          tpl.corner_d[:, 1:, 1:]], axis=-1), f, axis=-1)
        circ = uv[1:, 1:-1] - uv[:-1, 1:-1] - (uh[1:-1, 1:] - uh[1:-1, :-1])
        return np.abs(circ).max() / np.abs(uv).max()

    assert circulation(cf) < 1e-3
    assert circulation(t) > 0.05
    # given a_ij instead of the template's own
    a = 0.5 * template_alpha(t)[c:c + 3, c:c + 3].T
    half = curl_free_template(t, a)
    assert_allclose(template_alpha(half)[c:c + 3, c:c + 3].T, a, rtol=0,
                    atol=2e-5 * np.abs(a).max())
    with pytest.raises(TypeError, match="DistortionTemplate"):
        curl_free_template("template.fits")


def test_area_response_directions_move_the_a_ij_within_their_errors(pair):
    """Measured on the exact polygon areas of the template plus a direction
    (an independent reference for the solver's linearisation), for two steps:

    * without the sum rule, one direction per lag changes its a_ij by its
      error (to 2 %: one Newton step on the exact areas, as draw_templates)
      and no other measured lag;
    * with it (the default), one direction fewer than the lags; each
      changes the a_ij as it reports, keeps the measured lags' area sum and
      moves no pixel beyond them; together they have the covariance of the
      errors conditioned on the sum rule (computed here directly), and a
      step costs one unit of the a-matrix's chi2 (the directions are
      orthonormal in it);
    * unmeasured lags (NaN or zero error) get no direction.
    """
    t = pair[1]
    c = t.center
    a0 = template_alpha(t)
    sigma = 0.05 * np.abs(a0[c:c + 3, c:c + 3].T)
    sigma[2, 1] = np.nan
    sigma[1, 2] = 0.0
    measured = np.isfinite(sigma) & (sigma > 0)
    lags = [(i, j) for i in range(3) for j in range(3) if measured[i, j]]
    npix = np.array([[1, 2, 2], [2, 4, 4], [2, 4, 4]], float)
    near = np.zeros(a0.shape, bool)
    near[c - 2:c + 3, c - 2:c + 3] = True  # lags <= 2
    for rule in (False, True):
        dirs = area_response_directions(t, sigma, sum_rule=rule)
        assert len(dirs) == len(lags) - rule
        if not rule:
            assert sorted(dirs) == sorted(f"a{i}{j}" for i, j in lags)
        for name, d in dirs.items():
            want = d["a_change"]
            assert np.all(np.isnan(want[~measured]))
            if not rule:
                i, j = int(name[1]), int(name[2])
                assert want[i, j] == sigma[i, j]
                assert np.count_nonzero(want[measured]) == 1
            else:
                assert_allclose(np.sum(npix[measured] * want[measured]), 0,
                                atol=1e-9 * np.abs(want[measured]).max())
                assert_allclose(np.sum((want[measured] / sigma[measured]) ** 2), 1, rtol=1e-9)
            for step in (1.0, -2.0):
                full = template_alpha(combine_templates(t, [d["delta"]], [step])) - a0
                moved = full[c:c + 3, c:c + 3].T
                scale = np.abs(want[measured]).max()
                assert_allclose(moved[measured], step * want[measured], rtol=0.02,
                                atol=2e-3 * abs(step) * scale)
                if rule:  # nothing pushed into the far lags
                    assert np.abs(full[~near]).max() < 2e-3 * abs(step) * scale
            assert_allclose(d["delta"]["corner_d"], 0, atol=0)
        if rule:
            m = np.array([d["a_change"][measured] for d in dirs.values()])
            s2, n = sigma[measured] ** 2, npix[measured]
            cond = np.diag(s2) - np.outer(s2 * n, s2 * n) / np.sum(n * n * s2)
            assert_allclose(m.T @ m, cond, rtol=0, atol=1e-9 * s2.max())
            assert_allclose((m / sigma[measured]) @ (m / sigma[measured]).T,
                            np.eye(len(dirs)), atol=1e-9)
    with pytest.raises(ValueError, match="square"):
        area_response_directions(t, np.zeros((2, 3)))
    with pytest.raises(TypeError, match="DistortionTemplate"):
        area_response_directions("template.fits", sigma)


def test_combined_template_area_response_is_linear(pair):
    """Independent reference (exact polygon areas): a template plus c times
    its difference to another has, from its own polygons, the a_ij
    (1 - c) alpha_A + c alpha_B; c = 1 gives B's displacements back."""
    ta, tb = pair
    d = template_difference(tb, ta)
    for c in (-0.7, 0.4, 2.0):
        mixed = combine_templates(ta, [d], [c])
        assert_allclose(mixed.corner_d, ta.corner_d + c * (tb.corner_d - ta.corner_d))
        assert_allclose(template_alpha(mixed),
                        (1 - c) * template_alpha(ta) + c * template_alpha(tb),
                        atol=1e-12 * np.abs(template_alpha(ta)).max() + 1e-16)
    back = combine_templates(ta, [d], [1.0])
    assert_allclose(back.vedge_d, tb.vedge_d, rtol=0, atol=1e-15)
    assert_allclose(back.hedge_d, tb.hedge_d, rtol=0, atol=1e-15)


def test_template_difference_refuses_other_grids(pair):
    other = build_template(SensorParameters(), TemplateSettings(size=7, edge_samples=4, tol=1e-4,
                                                                aggressor_charge=1e4, workers=2))
    with pytest.raises(InputError, match="differ in size"):
        template_difference(pair[0], other)


def test_nan_lags_are_not_matched(pair):
    a_t, b_t = pair
    c = a_t.center
    target = template_alpha(b_t)[c:c + 3, c:c + 3].T.copy()
    target[2, 2] = np.nan
    r = match_area_coefficients(a_t, target)
    got = template_alpha(r)[c:c + 3, c:c + 3].T
    assert_allclose(got[:2, :2], target[:2, :2], rtol=0, atol=1e-10)


@pytest.mark.parametrize("a, kw, err, match", [
    (np.zeros((2, 3)), {}, ValueError, "square"),
    (np.full((2, 2), np.inf), {}, ValueError, "finite"),
    (np.zeros((2, 2)), {"max_lag": 9}, ValueError, "max_lag"),
])
def test_bad_input(pair, a, kw, err, match):
    with pytest.raises(err, match=match):
        match_area_coefficients(pair[0], a, **kw)
    with pytest.raises(TypeError, match="DistortionTemplate"):
        match_area_coefficients("template.fits", np.zeros((2, 2)))
