"""Tests of lsst_bfdrift.geometry.linear: first-order maps, their bound, the exact fallback.

These are consistency tests of the package against itself: the reference is
the exact polygon moments of :func:`lsst_bfdrift.geometry.superpose.moment_maps`
with the same template, not an outside truth.
"""

import numpy as np
import pytest

from tests.geometry.conftest import star_field
from numpy.testing import assert_allclose

from lsst_bfdrift.geometry._exact import exact_boxes
from lsst_bfdrift.geometry.bounds import (displacement_bound, pixel_displacement_bound,
                                          second_order_bounds)
from lsst_bfdrift.geometry.first_order import (LINEAR_MAPS, FirstOrderPass,
                                               convolved_first_order_maps, linear_kernels)
from lsst_bfdrift.geometry.linear import (MEASURED_CONSTANTS, _binned_eps, _index_map,
                                          error_bounds, linear_moment_maps)
from lsst_bfdrift.geometry.superpose import moment_maps, resample_template, superpose_boundaries

NOMINAL = dict(area=1.0, dx=0.0, dy=0.0, e1=0.0, e2=0.0)


def _star_field(n, peak_flux, rng, sky=1200.0):
    """Poisson sky, one star of ``peak_flux`` e (sigma 1.5 px) and fainter ones."""
    return star_field(n, peak_flux, rng, sky=sky, faint=((0.2, 0.8, 30, 1.2), (0.8, 0.2, 8, 2.0)))


def _signal(maps):
    return {k: np.abs(getattr(maps, k) - NOMINAL[k]).max() for k in LINEAR_MAPS}


def _true_eps(template, q):
    """Largest abs displacement component of every pixel's boundary points (px)."""
    g = superpose_boundaries(template, q)
    nom = g.nominal()
    c = np.abs(g.corners - nom.corners).max(-1)
    v = np.abs(g.vedge - nom.vedge).max(-1)
    h = np.abs(g.hedge - nom.hedge).max(-1)
    return np.maximum.reduce([c[:-1, :-1], c[1:, :-1], c[:-1, 1:], c[1:, 1:],
                              v[:, :-1], v[:, 1:], h[:-1], h[1:]])


@pytest.mark.parametrize("which", ["small", "default"])
def test_kernels_are_the_first_order_response(which, small_template, default_template):
    """Central difference of the exact maps for one aggressor (+-q: the
    second-order terms cancel) equals the kernels."""
    t = small_template if which == "small" else default_template
    r = t.center + 1
    n = 2 * r + 5
    q = np.zeros((n, n))
    q[n // 2, n // 2] = 1e-3 * t.charge
    plus, minus = moment_maps(t, q), moment_maps(t, -q)
    k = linear_kernels(t).kernels
    assert k.shape == (5, 2 * r + 1, 2 * r + 1)
    sl = slice(n // 2 - r, n // 2 + r + 1)
    for m, name in enumerate(LINEAR_MAPS):
        diff = (getattr(plus, name) - getattr(minus, name)) / (2 * q.max())
        assert_allclose(diff[sl, sl], k[m], rtol=0, atol=1e-6 * np.abs(k[m]).max())
        # nothing beyond the kernel's reach
        assert np.abs(diff).sum() == pytest.approx(np.abs(diff[sl, sl]).sum(), rel=1e-9)


def test_kernels_do_not_depend_on_resampling(default_template):
    t = default_template
    full, eight = linear_kernels(t), linear_kernels(t, samples=8)
    assert linear_kernels(t) is full  # cached per template
    assert_allclose(eight.kernels, full.kernels, rtol=0, atol=1e-12 * np.abs(full.kernels).max())
    # the bound of the resampled template's own displacements is its own
    assert eight.disp.max() > 0 and eight.chi == 4.0


def test_linear_maps_are_the_convolutions(small_template, rng):
    """Tiled FFTs (tiles smaller than the image) against a direct sum."""
    t = small_template
    q = rng.uniform(0, 5e4, (37, 29))
    k = linear_kernels(t).kernels
    r = t.center + 1
    qp = np.pad(q, r)
    ref = np.zeros((5,) + q.shape)
    for dj in range(-r, r + 1):
        for di in range(-r, r + 1):
            ref += k[:, dj + r, di + r, None, None] * qp[r - dj:r - dj + 37, r - di:r - di + 29]
    lk = linear_kernels(t)
    for dtype, tol in ((np.float64, 1e-12), (np.float32, 1e-5)):
        maps, smax = convolved_first_order_maps(lk, q, LINEAR_MAPS, tile=(10, 13),
                                                dtype=dtype, workers=1)
        for i, name in enumerate(LINEAR_MAPS):
            s = np.abs(ref[i]).max()
            assert_allclose(maps[i] - NOMINAL[name], ref[i], rtol=0, atol=tol * s)
            assert smax[i] == pytest.approx(s, rel=10 * tol)
    # the maps returned add the uniform level's second-order terms within
    # the reach of the border only
    info = {}
    m = linear_moment_maps(t, q, fallback=False, strip=10, dtype=np.float64, info=info)
    assert m.ixx is None and info["method"] == "linear"
    d = np.abs(m.area - 1.0 - ref[0])
    assert d[r:-r, r:-r].max() < 1e-15 and d.max() > 1e-6


@pytest.fixture(scope="module")
def fields(default_template):
    """Star field with a 1.5e6 e star and a 1e5 e flat: charge, exact maps,
    first-order maps alone (raw), with the border terms (``fallback=False``),
    true largest displacements."""
    rng = np.random.default_rng(17)
    out = {}
    t8 = resample_template(default_template, 8)
    lk = linear_kernels(default_template, samples=8)
    for name, q in (("stars", _star_field(80, 1.5e6, rng)),
                    ("flat", rng.poisson(1e5, (72, 72)).astype(float))):
        exact = moment_maps(default_template, q, samples=8)
        raw = dict(zip(LINEAR_MAPS, convolved_first_order_maps(
            lk, q, LINEAR_MAPS, tile=(64, 64), dtype=np.float64, workers=1)[0]))
        lin = linear_moment_maps(default_template, q, samples=8, fallback=False,
                                 dtype=np.float64)
        out[name] = (q, exact, raw, lin, _true_eps(t8, q))
    return out


def _pixels(binned, b, shape):
    return np.repeat(np.repeat(binned, b, 0), b, 1)[:shape[0], :shape[1]]


@pytest.mark.parametrize("name", ["stars", "flat"])
def test_bound_holds(name, fields, default_template):
    """displacement_bound >= the true displacements; the first-order error
    is within MEASURED_CONSTANTS * eps**2 (true eps) and the analytic
    second_order_bounds; the error of the maps with the border terms is
    within error_bounds (measured and analytic constants)."""
    q, exact, raw, lin, eps = fields[name]
    lk = linear_kernels(default_template, samples=8)
    d = _pixels(displacement_bound(lk, q, bin=2), 2, q.shape)
    assert np.all(d >= eps)
    # pixel by pixel: still a bound, and at most the binned one
    rows, cols = np.indices(q.shape).reshape(2, -1)
    qbar = float(np.median(q))
    d1 = pixel_displacement_bound(lk, q, rows, cols, qbar=qbar, outside=abs(qbar))
    d1 = d1.reshape(q.shape)
    assert np.all(d1 >= eps) and np.all(d1 <= _pixels(displacement_bound(lk, q, bin=2, qbar=qbar),
                                                       2, q.shape))
    assert np.median(d1 / d) < 0.9
    analytic = second_order_bounds(d, lk.chi)
    for k in LINEAR_MAPS:
        err = np.abs(raw[k] - getattr(exact, k))
        assert np.all(err <= MEASURED_CONSTANTS[k] * eps**2), (k, (err / eps**2).max())
        assert np.all(err <= analytic[k]), k
    for how in ("measured", "analytic"):
        bd = error_bounds(default_template, q, samples=8, bound=how)
        for k in LINEAR_MAPS:
            err = np.abs(getattr(lin, k) - getattr(exact, k))
            assert np.all(err <= _pixels(bd[k], 2, q.shape)), (how, k)


@pytest.mark.parametrize("name", ["stars", "flat"])
def test_maps_within_tolerance_of_exact(name, fields, default_template):
    """Default maps: worst pixel within 1e-3 of each map's signal (its largest
    abs(map - nominal) over the image, exact maps). The linear maps alone are
    not: on both fields the exact fallback is needed (this test fails with
    it disabled)."""
    q, exact, _, lin, _ = fields[name]
    s = _signal(exact)
    info = {}
    m = linear_moment_maps(default_template, q, samples=8, info=info)
    errs = {k: np.abs(getattr(m, k) - getattr(exact, k)).max() / s[k] for k in LINEAR_MAPS}
    assert max(errs.values()) <= 1e-3, errs
    lin_err = {k: np.abs(getattr(lin, k) - getattr(exact, k)).max() / s[k] for k in LINEAR_MAPS}
    assert max(lin_err.values()) > 1e-3, lin_err
    assert info["method"] in ("linear+exact", "exact") and info["exact_fraction"] > 0


def test_bright_star_windows_only(default_template, rng):
    """On a larger sky the fallback is confined to windows around the bright
    star and the image border; the rest is linear."""
    q = _star_field(384, 1.5e6, rng)
    info = {}
    m = linear_moment_maps(default_template, q, samples=8, info=info)
    assert info["method"] == "linear+exact"
    assert 0 < info["exact_fraction"] < 0.1
    # the one-threshold flag is error_bounds' flag; refined pixel by pixel,
    # fewer bins
    bd = error_bounds(default_template, q, samples=8)
    flag = np.zeros(bd["area"].shape, bool)
    for k in LINEAR_MAPS:
        flag |= bd[k] > info["tolerance"][k]
    coarse = {}
    linear_moment_maps(default_template, q, samples=8, info=coarse, refine=False)
    assert coarse["exact_fraction"] == pytest.approx(flag.sum() * 4 / q.size, rel=1e-12)
    assert 0 < info["exact_fraction"] < 0.8 * coarse["exact_fraction"]
    exact = moment_maps(default_template, q, samples=8)
    s = _signal(exact)
    for k in LINEAR_MAPS:
        assert np.abs(getattr(m, k) - getattr(exact, k)).max() <= 1e-3 * s[k], k


@pytest.mark.parametrize("n, shape, b", [(23, (301, 299), 2), (23, (100, 37), 3),
                                         (11, (11, 50), 4), (7, (7, 7), 1)])
def test_binned_eps_is_the_bin_maximum(n, shape, b):
    """_binned_eps against the direct maximum over each bin of the uniform
    response spread over the image (partial bins at the far edges)."""
    eps = np.random.default_rng(n + b).random((n, n))
    rm, cm = _index_map(shape[0], n), _index_map(shape[1], n)
    nby, nbx = -(-shape[0] // b), -(-shape[1] // b)
    full = np.full((nby * b, nbx * b), -np.inf)
    full[:shape[0], :shape[1]] = eps[np.ix_(rm, cm)]
    direct = full.reshape(nby, b, nbx, b).max(axis=(1, 3))
    got = _binned_eps(eps, rm, cm, b, nby, nbx)
    np.testing.assert_array_equal(got, direct)
    assert got.flags.c_contiguous  # the callers' in-place arithmetic is 15x slower otherwise


def test_pixel_bound_is_the_direct_sum(default_template):
    """pixel_displacement_bound against ``sum_a disp(p - a) g(a)`` summed
    with numpy over a zero-padded image (``outside`` beyond it), for pixels
    inside, next to the borders and in the corners."""
    lk = linear_kernels(default_template, samples=8)
    r = lk.disp.shape[0] // 2
    q = np.random.default_rng(7).poisson(900.0, (60, 47)).astype(float)
    q[30, 20] += 4e5
    qbar, outside = 880.0, 123.0
    g = np.full((q.shape[0] + 2 * r, q.shape[1] + 2 * r), outside)
    g[r:-r, r:-r] = np.abs(q - qbar)
    rows = np.array([30, 0, 59, 5, r, q.shape[0] - r - 1, 31, 0])
    cols = np.array([20, 3, 46, 0, r, q.shape[1] - r - 1, 45, 46])
    # disp[dj + r, di + r] weighs the aggressor at (j - dj, i - di)
    direct = [(lk.disp[::-1, ::-1] * g[j:j + 2 * r + 1, i:i + 2 * r + 1]).sum()
              for j, i in zip(rows, cols)]
    got = pixel_displacement_bound(lk, q, rows, cols, qbar=qbar, outside=outside)
    assert_allclose(got, np.array(direct) * (1 + 1e-12) + abs(qbar) * lk.net, rtol=1e-13)


def test_border_strips_follow_the_flagged_runs():
    """exact_boxes: flagged bins near the border make one strip per run along the
    side (runs farther apart than 2 band + 1 bins stay apart), each as deep as
    its own deepest flagged bin; every flagged bin lies in a box."""
    flag = np.zeros((40, 50), bool)
    flag[0, 3:6] = True          # a run near the left end of the bottom side
    flag[0:2, 30:33] = True      # another, deeper, far along the same side
    flag[20:22, 20:23] = True    # an interior group
    boxes = exact_boxes(flag, 2, (80, 100), band=3)
    bottom = sorted(bx for bx in boxes if bx[0] == 0)
    assert bottom == [(0, 2, 6, 12), (0, 4, 60, 66)]
    assert (40, 44, 40, 46) in boxes and len(boxes) == 3
    for by, bx in zip(*np.nonzero(flag)):
        assert any(y0 <= 2 * by < y1 and x0 <= 2 * bx < x1 for y0, y1, x0, x1 in boxes)


def test_star_at_the_border_within_tolerance_of_exact(default_template, rng):
    """A bright star 3 px from the right edge: its windows reach the image
    border (no charge beyond it) and the maps stay within 1e-3 of each map's
    signal of the exact polygon moments."""
    q = rng.poisson(1200.0, (160, 160)).astype(float)
    yy, xx = np.mgrid[:160, :160]
    q += 1.5e6 / (2 * np.pi * 1.5**2) * np.exp(-((xx - 156.3)**2 + (yy - 40.2)**2) / (2 * 1.5**2))
    info = {}
    m = linear_moment_maps(default_template, q, samples=8, info=info)
    exact = moment_maps(default_template, q, samples=8)
    s = _signal(exact)
    for k in LINEAR_MAPS:
        assert np.abs(getattr(m, k) - getattr(exact, k)).max() <= 1e-3 * s[k], k
    assert info["method"] == "linear+exact"


def test_float32_rounding_is_small(fields, default_template):
    q, exact, _, lin, _ = fields["stars"]
    m32 = linear_moment_maps(default_template, q, samples=8, fallback=False)
    s = _signal(lin)
    for k in LINEAR_MAPS:
        assert np.abs(getattr(m32, k) - getattr(lin, k)).max() < 1e-5 * s[k], k


@pytest.mark.parametrize("name", ["stars", "flat"])
def test_single_precision_maps(name, fields, default_template):
    """map_dtype=float32: the centroid and ellipticity maps are the float64
    ones rounded to single precision (exact windows included), the area stays
    float64 and identical, and the maps remain within 1e-3 of each map's
    signal against the exact ones (independent reference: exact polygon moments)."""
    q, exact, _, _, _ = fields[name]
    m64 = linear_moment_maps(default_template, q, samples=8)
    m32 = linear_moment_maps(default_template, q, samples=8, map_dtype=np.float32)
    assert m32.area.dtype == np.float64 and np.array_equal(m32.area, m64.area)
    s = _signal(exact)
    for k in ("dx", "dy", "e1", "e2"):
        assert getattr(m32, k).dtype == np.float32, k
        assert np.array_equal(getattr(m32, k), getattr(m64, k).astype(np.float32)), k
    for k in LINEAR_MAPS:
        assert np.abs(getattr(m32, k) - getattr(exact, k)).max() <= 1e-3 * s[k], k
    with pytest.raises(ValueError, match="dtype must be float64 or float32"):
        linear_moment_maps(default_template, q, map_dtype=np.float16)


def test_zero_charge_and_mask(small_template):
    m = linear_moment_maps(small_template, np.zeros((9, 8)))
    assert_allclose(m.area, 1.0, rtol=0, atol=0)
    assert_allclose(m.e2, 0.0, rtol=0, atol=0)
    q = np.zeros((12, 12))
    q[5, 5] = 3e4
    q[2, 9] = np.nan
    mask = np.isnan(q)
    a = linear_moment_maps(small_template, q, mask=mask)
    b = linear_moment_maps(small_template, np.where(mask, 0.0, q))
    assert np.array_equal(a.area, b.area)


@pytest.mark.parametrize("kw, match", [
    ({"maps": ("area", "ixx")}, "unknown linear maps"),
    ({"bound": "tight"}, "bound must be"),
    ({"rtol": 0.0}, "rtol must be between"),
    ({"dtype": np.float16}, "dtype must be float64 or float32"),
    ({"strip": 0}, "strip and bin must be positive"),
])
def test_bad_options(small_template, kw, match):
    with pytest.raises(ValueError, match=match):
        linear_moment_maps(small_template, np.zeros((6, 6)), **kw)


def test_task_geometry_methods(default_template, rng):
    """The correction is bit-identical whatever the geometry method; the
    linear maps are within the tolerance of the exact ones."""
    from lsst_bfdrift.utils.config import FieldValidationError
    from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
    q = _star_field(96, 1.5e6, rng)
    res = {}
    for method in ("linear", "exact"):
        cfg = BrighterFatterDriftConfig(geometry_method=method)
        res[method] = BrighterFatterDriftTask(cfg, template=default_template).run(q)
    none = BrighterFatterDriftTask(BrighterFatterDriftConfig(compute_geometry=False),
                                   template=default_template).run(q)
    assert BrighterFatterDriftConfig().geometry_method == "linear"
    for r in res.values():
        assert np.array_equal(r.exposure, none.exposure)
        assert np.array_equal(r.flux_moved, none.flux_moved)
    assert res["linear"].header["BFGMETH"] == "linear"
    # single-precision FFTs (the default): centroid and ellipticity maps in float32
    assert res["linear"].area.dtype == np.float64 and res["linear"].e1.dtype == np.float32
    assert res["exact"].header["BFGMETH"] == "exact"
    ex = res["exact"]
    for name in ("area", "centroid_x", "centroid_y", "e1", "e2"):
        nominal = 1.0 if name == "area" else 0.0
        s = np.abs(getattr(ex, name) - nominal).max()
        assert np.abs(getattr(res["linear"], name) - getattr(ex, name)).max() <= 1e-3 * s, name
    with pytest.raises(FieldValidationError, match="geometry_tolerance"):
        BrighterFatterDriftConfig(geometry_tolerance=0.0).validate()


@pytest.mark.parametrize("which", ["small", "default"])
def test_first_order_pass_from_the_swept_areas(which, small_template, default_template, rng):
    """The maps combined from the swept areas and three edge fields (default
    template) or convolved directly (small template: its outer corners move,
    which the swept-area kernels leave out) are the five-kernel maps; sharing
    the transforms leaves the correction's first-order pass bit for bit."""
    from lsst_bfdrift.correction.series import first_order_terms
    from lsst_bfdrift.templates.swept import OperatorCache
    t = small_template if which == "small" else default_template
    lk = linear_kernels(t)
    assert lk.decomposed == (which == "default")
    q = _star_field(70, 4e5, rng)
    ref, smax = convolved_first_order_maps(lk, q, LINEAR_MAPS, tile=(64, 64),
                                           dtype=np.float64, workers=1)
    ops = OperatorCache(t, dtype=np.float64)
    blocked = np.zeros(q.shape, bool)
    fo = FirstOrderPass(t, q.shape, maps=("e2", "area"))
    plain = first_order_terms(q, blocked, ops, strip=24, cubic="fv4")
    plain = [None if x is None else np.array(x) for x in plain[:3]]
    shared = first_order_terms(q, blocked, ops, strip=24, cubic="fv4", maps=fo)
    for a, b in zip(plain, shared[:3]):
        assert np.array_equal(a, b)
    assert fo.complete
    for k, name in enumerate(LINEAR_MAPS):
        if name in fo.names:
            assert_allclose(fo.outs[fo.names.index(name)], ref[k], rtol=0, atol=1e-12 * smax[k])
    assert_allclose(fo.smax, smax, rtol=1e-12)
    with pytest.raises(ValueError, match="in order"):
        fo.add(None, None, None, 0, 5, 10)


def test_progress_is_reported_and_changes_nothing(default_template, rng):
    """linear_moment_maps and the Task report progress (fractions never
    decreasing, 1 at the end; the Task by stage, in the order they run: the
    exact maps then the correction, the correction then the linear maps from
    its first pass); the maps and the correction are bit-identical without it."""
    from lsst_bfdrift.correction.task import (BrighterFatterDriftConfig, BrighterFatterDriftTask,
                                              stage_order)
    from lsst_bfdrift.templates.swept import OperatorCache
    q = _star_field(96, 1.5e6, rng)
    for kw, method in ((dict(max_fraction=10.0), "linear+exact"), (dict(fallback=False), "linear"),
                       (dict(max_fraction=0.0), "exact")):
        seen, info = [], {}
        m = linear_moment_maps(default_template, q, samples=8, progress=seen.append,
                               info=info, **kw)
        ref = linear_moment_maps(default_template, q, samples=8, **kw)
        for name in LINEAR_MAPS:
            assert np.array_equal(getattr(m, name), getattr(ref, name)), name
        assert info["method"] == method
        assert seen == sorted(seen) and seen[-1] == 1.0 and len(seen) >= 2, (kw, seen)
    # the first-order maps already done (the Task's case): the rest reported
    ops = OperatorCache(default_template, dtype=np.float32)
    first = FirstOrderPass(default_template, q.shape, samples=8).run(q, ops)
    seen = []
    m = linear_moment_maps(default_template, q, samples=8, first_order=first, ops=ops,
                           progress=seen.append)
    ref = linear_moment_maps(default_template, q, samples=8)
    for name in LINEAR_MAPS:
        assert np.array_equal(getattr(m, name), getattr(ref, name)), name
    assert seen == sorted(seen) and seen[0] == 0.0 and seen[-1] == 1.0, seen
    for cfg, expect in ((BrighterFatterDriftConfig(), ["correct", "maps"]),
                        (BrighterFatterDriftConfig(method="astier23"), ["correct", "maps"]),
                        (BrighterFatterDriftConfig(geometry_method="exact"), ["maps", "correct"]),
                        (BrighterFatterDriftConfig(compute_geometry=False), ["correct"])):
        assert list(stage_order(cfg)) == expect
        task = BrighterFatterDriftTask(cfg, template=default_template)
        calls = []
        res = task.run(q, progress=lambda stage, f: calls.append((stage, f)))
        ref = task.run(q)
        assert np.array_equal(res.exposure, ref.exposure)
        if cfg.compute_geometry:
            assert np.array_equal(res.area, ref.area) and np.array_equal(res.e2, ref.e2)
        stages = [s for s, _ in calls]
        assert sorted(set(stages), key=stages.index) == expect
        assert stages == sorted(stages, key=expect.index)  # one stage after the other
        for stage in expect:
            fr = [f for s, f in calls if s == stage]
            assert fr[0] == 0.0 and fr[-1] == 1.0 and fr == sorted(fr), (stage, fr)
