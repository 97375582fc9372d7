"""Tests of the second tier of the windowed series: the per-cell bound on
the higher orders and the windows with a halo (lsst_bfdrift.correction.tiles)."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import ndimage

from lsst_bfdrift.correction import series as S
from lsst_bfdrift.correction import solvers as C
from lsst_bfdrift.correction import tiles as T
from lsst_bfdrift.correction._edge_kernels import fused_transfer
from lsst_bfdrift.templates.swept import OperatorCache, SweptAreas
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.correction.settings import REFERENCE

CELL = 16
MARGINS = (4, 11, 22)  # the default template's reach: 11 px
NOISE_TOL = 0.05


@pytest.fixture(scope="module")
def template():
    return load_default_template()


def crowded(n, *, seed=2, density=4000 / 4096**2):
    """Sky of 1200 e with stars of 1e4 to 1.5e6 e (sigma 1.5 px) at the
    density of the crowded field of benchmarks/performance/bench_task.py (4000 stars on
    4096 x 4096)."""
    rng = np.random.default_rng(seed)
    img = rng.poisson(1200.0, (n, n)).astype(float)
    yy, xx = np.mgrid[-8:9, -8:9]
    for _ in range(round(density * n * n)):
        x, y = rng.integers(20, n - 20, 2)
        f = 10 ** rng.uniform(4, np.log10(1.5e6))
        img[y - 8:y + 9, x - 8:x + 9] += f * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2) / (
            2 * np.pi * 1.5**2)
    return img


def flat(n, *, seed=3):
    return np.random.default_rng(seed).poisson(1e5, (n, n)).astype(float)


def _cells(a):
    n0, n1 = a.shape
    return a.reshape(n0 // CELL, CELL, n1 // CELL, CELL)


def test_constants_are_those_of_the_operator(template):
    """A is the sum of abs of the charge a constant unit density gains per
    electron (the transfer B(1, delta)); K is the operator's own."""
    n = 64
    delta = np.zeros((n, n))
    delta[32, 31] = 1.0
    sv, sh = SweptAreas(template, (n, n))(delta)
    area = fused_transfer(sv, sh, np.ones((n, n)), np.zeros((n, n), bool), cubic="fv4")
    consts = T.bound_constants(template, "fv4")
    assert_allclose(consts["A"], np.abs(area).sum(), rtol=1e-9)
    assert_allclose(consts["K"], OperatorCache(template).kernel_abs_sum, rtol=1e-12)
    assert consts["W"] == pytest.approx(4.0 / 3.0)
    assert consts["S0"] < 1e-9 * consts["K"]  # a uniform level sweeps nothing
    assert T.bound_constants(template, "mean2")["W"] == 1.0


def _bound_and_terms(img, blocked, template, density="fv4", order=3):
    ops = OperatorCache(template)  # float64: the reference terms
    eff, blk = np.where(np.isfinite(img), img, 0.0), blocked | ~np.isfinite(img)
    _, (x2, x3) = C._series_block(eff, blk, ops(img.shape), order, density, terms=3)
    first, sv, sh, stats = S.first_order_terms(eff, blk, ops, strip=None, cubic=density,
                                               cell=CELL)
    local = T.local_stats(eff, first, sv, sh, cell=CELL, margins=MARGINS)
    bound, _ = T.higher_order_bound(stats, local, blk, T.bound_constants(template, density),
                                    cell=CELL, order=order)
    true = _cells(np.abs(x2 + x3)).max(axis=(1, 3))
    return bound, true, stats


@pytest.mark.parametrize("field, density, order", [
    ("flat", "fv4", 3), ("crowded", "fv4", 3), ("masked", "fv4", 3), ("flat", "mean2", 4),
    ("crowded", "cubic4", 2)])
def test_bound_holds_in_every_cell(field, density, order, template):
    """The bound is above the largest higher-order term of the dense series
    in every cell, blocked pixels and the image border included, for every
    density and order; on a flat it is within a few times that term."""
    img = flat(512) if field == "flat" else crowded(512)
    blocked = np.zeros(img.shape, bool)
    if field == "masked":
        blocked[200:260, 300] = True
        img[100, 100] = np.nan
    bound, true, stats = _bound_and_terms(img, blocked, template, density, order)
    assert np.all(true <= bound)
    if field == "flat":
        inner = (slice(3, -3),) * 2
        ratio = bound[inner] / true[inner]
        assert ratio.max() < 5.0 and ratio.min() > 1.5
        # the interior of a flat needs no higher orders, its border does
        lmin = ndimage.minimum_filter(S.tolerance(stats[1], NOISE_TOL), size=3)
        assert np.all(bound[inner] < 0.5 * lmin[inner])
        assert np.any(true[:, 0] > 0.5 * lmin[:, 0])


@pytest.mark.parametrize("field", ["flat", "crowded"])
def test_refined_bound_lies_between_the_terms_and_the_coarse_bound(field, template):
    """The coarse statistics are at least the local ones, so the bound from
    them is at least the local bound; cell_bound refines the flagged cells
    only, and stays above the true terms."""
    img = flat(512) if field == "flat" else crowded(512)
    blk = np.zeros(img.shape, bool)
    ops = OperatorCache(template)
    _, (x2, x3) = C._series_block(img, blk, ops(img.shape), 3, "fv4", terms=3)
    first, sv, sh, stats = S.first_order_terms(img, blk, ops, strip=None, cubic="fv4",
                                               cell=CELL)
    consts = T.bound_constants(template, "fv4")
    local = T.local_stats(img, first, sv, sh, cell=CELL, margins=MARGINS)
    coarse = T.coarse_stats(stats, consts)
    # (b from the first pass and b = 2 (I - first) differ by rounding)
    for name in T.LOCAL_STATS:
        if name == "imin":
            assert np.all(coarse[name] <= local[name])
        else:
            assert np.all(coarse[name] >= local[name] - 1e-12 * np.abs(local[name]).max())
    b_local = T.higher_order_bound(stats, local, blk, consts, cell=CELL)[0]
    b_coarse = T.higher_order_bound(stats, coarse, blk, consts, cell=CELL)[0]
    assert np.all(b_local <= b_coarse * (1 + 1e-12))
    lim = 0.5 * ndimage.minimum_filter(S.tolerance(stats[1], NOISE_TOL), size=3)
    bound, _ = T.cell_bound(img, first, sv, sh, stats, blk, consts, cell=CELL,
                            margins=MARGINS, threshold=lim)
    flagged = b_coarse > lim
    assert 0 < flagged.sum() < flagged.size
    assert np.array_equal(T.cell_bound(img, first, sv, sh, stats, blk, consts, cell=CELL,
                                       margins=MARGINS, threshold=lim, refine=False)[0],
                          b_coarse)
    # refined where flagged (their neighbours' swept areas keep the coarse maxima)
    assert np.all(bound[flagged] >= b_local[flagged] * (1 - 1e-12))
    assert np.all(bound[flagged] <= b_coarse[flagged])
    assert np.mean(bound[flagged] < 0.9 * b_coarse[flagged]) > 0.5
    assert np.array_equal(bound[~flagged], b_coarse[~flagged])
    assert np.all(_cells(np.abs(x2 + x3)).max(axis=(1, 3)) <= bound)
    # a few cells: read pixel by pixel; all of them: by blocks of 4 x 4 px
    # with the margins rounded up to multiples of 4 (equal for such margins)
    few = np.zeros(flagged.shape, bool)
    few.flat[::23] = True
    for margins in (MARGINS, (4, 12, 24)):
        part = T.local_stats(img, first, sv, sh, cell=CELL, margins=margins, cells=few)
        full = T.local_stats(img, first, sv, sh, cell=CELL, margins=margins)
        for name in T.LOCAL_STATS:
            assert np.all(np.isnan(part[name][~few]))
            if margins == MARGINS and name != "imin":
                assert np.all(full[name][few] >= part[name][few])
            elif margins == MARGINS:
                assert np.all(full[name][few] <= part[name][few])
            else:
                assert np.array_equal(full[name][few], part[name][few])
    with pytest.raises(InputError, match="margins must be increasing"):
        T.local_stats(img, first, sv, sh, cell=CELL, margins=(4, 22, 11))


def test_halo_windows_keep_every_active_cell_once(rng):
    for trial in range(20):
        shape = (rng.integers(5, 20) * CELL - rng.integers(0, CELL), 15 * CELL)
        my, mx = -(-shape[0] // CELL), 15
        act = rng.random((my, mx)) < 0.15
        halo = 1 + trial % 2
        kept = np.zeros(shape, int)
        for (y0, y1, x0, x1), keep in T.halo_windows(act, shape, cell=CELL, group=4,
                                                      halo=halo):
            assert 0 <= y0 < y1 <= shape[0] and 0 <= x0 < x1 <= shape[1]
            assert keep.shape == (y1 - y0, x1 - x0)
            kept[y0:y1, x0:x1] += keep
            # kept pixels lie at least the halo inside the window, image border excepted
            inner = np.zeros(keep.shape, bool)
            h = halo * CELL
            inner[0 if y0 == 0 else h:(y1 - y0) if y1 == shape[0] else -h,
                  0 if x0 == 0 else h:(x1 - x0) if x1 == shape[1] else -h] = True
            assert not np.any(keep & ~inner)
        want = np.kron(act, np.ones((CELL, CELL), int))[:shape[0], :shape[1]]
        assert np.array_equal(kept, want)
    assert T.halo_windows(np.zeros((3, 3), bool), (48, 48), cell=CELL) == []


def test_window_terms_within_the_truncation_bound(template):
    """Terms kept one cell inside a window differ from the dense series' by
    at most the truncation bound of window_sides (y misses the sources just
    outside); two cells inside they are exact; a side whose bound exceeds
    the limit gets two cells."""
    img = crowded(256, seed=5)
    blk = np.zeros(img.shape, bool)
    ops = OperatorCache(template)
    _, (x2, x3) = C._series_block(img, blk, ops(img.shape), 3, "fv4", terms=3)
    first, sv, sh, stats = S.first_order_terms(img, blk, ops, strip=None, cubic="fv4",
                                               cell=CELL)
    local = T.local_stats(img, first, sv, sh, cell=CELL, margins=MARGINS)
    _, p_wide = T.higher_order_bound(stats, local, blk, T.bound_constants(template, "fv4"),
                                     cell=CELL)
    act = np.zeros(stats[0].shape, bool)
    act[5:8, 6:9] = True  # away from the border
    cells_box = (5, 8, 6, 9)
    halos, bound = T.window_sides(cells_box, stats[2], p_wide, np.inf)
    assert halos == (1, 1, 1, 1) and bound > 0.0
    for halo in (1, 2):
        (box, keep), = T.halo_windows(act, img.shape, cell=CELL, group=16, halo=halo)
        assert box == tuple(CELL * v for v in (5 - halo, 8 + halo, 6 - halo, 9 + halo))
        extra, _, _ = S._window_terms(ops, [box], img, blk, first, sv, sh, 1 / 6, 0.0, "fv4")
        y0, y1, x0, x1 = box
        diff = np.abs(extra[0] - (x2 + x3)[y0:y1, x0:x1])[keep]
        if halo == 1:
            assert 0.0 < diff.max() <= bound
        else:
            assert diff.max() <= 1e-9 * np.abs(x2 + x3).max()
    # a limit below the bound: the sides that set it get two cells
    halos, tight = T.window_sides(cells_box, stats[2], p_wide, 0.5 * bound)
    assert 2 in halos and tight <= 0.5 * bound
    (box, _), = T.halo_windows(act, img.shape, cell=CELL, group=16,
                               halo=lambda cb: T.window_sides(cb, stats[2], p_wide,
                                                              0.5 * bound)[0])
    assert box == tuple(CELL * v for v in (5 - halos[0], 8 + halos[1], 6 - halos[2],
                                           9 + halos[3]))


def _forced_second_tier(img, blocked, template, monkeypatch, **kw):
    """sparse_series with the first tier's windows made to cover the image twice."""
    monkeypatch.setattr(S, "window_boxes",
                        lambda act, shape, **k: [(0, shape[0], 0, shape[1])] * 2)
    ops = OperatorCache(template, dtype=np.float32)
    eff, blk = np.where(np.isfinite(img), img, 0.0), blocked | ~np.isfinite(img)
    info = {}
    kw = {"noise_tol": NOISE_TOL, **kw}
    out = S.sparse_series(eff, blk, ops, density="fv4", strip=None, max_fraction=1.5,
                          second_max_fraction=1.5, info=info, **kw)
    return out, info


@pytest.mark.parametrize("field", ["flat", "crowded"])
def test_second_tier_within_half_the_tolerance(field, template, monkeypatch):
    """Against the dense third-order series, on a 512 x 512 flat and crowded
    field: every pixel within half the tolerance, the total flux within the
    sum of those bounds over the pixels left out; blocked pixels kept."""
    img = flat(512) if field == "flat" else crowded(512)
    blocked = np.zeros(img.shape, bool)
    blocked[200:260, 300] = True
    dense, _, _ = C.correct_image(img, template, **REFERENCE.solver_kwargs(density="fv4",
                                                                           noise_tol=NOISE_TOL,
                                                                           start="series",
                                                                           dtype=np.float32,
                                                                           blocked=blocked))
    out, info = _forced_second_tier(img, blocked, template, monkeypatch)
    assert info["tier"] == 2 and info["reason"] is None, info
    assert 0.0 < info["active_fraction"] < 1.0
    out[blocked] = img[blocked]
    lim = S.tolerance(img, NOISE_TOL)
    dev = np.abs(out - dense) / lim
    assert dev.max() <= 0.5
    assert dev.max() > 1e-3  # terms were left out
    assert abs(out.sum() - dense.sum()) <= 0.5 * lim[dev > 1e-6].sum()


def test_second_tier_with_one_tolerance(template, monkeypatch):
    """With ``rtol`` (one tolerance for every pixel) instead of the noise:
    within half of it of the dense series."""
    img = crowded(512)
    blk = np.zeros(img.shape, bool)
    rtol = 1e-5
    dense, _, _ = C.correct_image(img, template, **REFERENCE.solver_kwargs(density="fv4",
                                                                           rtol=rtol,
                                                                           start="series",
                                                                           dtype=np.float32))
    out, info = _forced_second_tier(img, blk, template, monkeypatch, rtol=rtol,
                                    noise_tol=None)
    assert info["tier"] == 2 and info["reason"] is None, info
    assert 0.0 < np.abs(out - dense).max() <= 0.5 * rtol * img.max()


def test_second_tier_declines_what_it_cannot_bound(template, monkeypatch):
    """A flat too small for its interior to outweigh its border: the second
    tier's windows would cover the image, and the dense solver is asked for."""
    out, info = _forced_second_tier(flat(64), np.zeros((64, 64), bool), template, monkeypatch)
    assert out is not None and info["window_fraction"] > 0.75  # up to 1.5 allowed here
    ops = OperatorCache(template, dtype=np.float32)
    info = {}
    assert S.sparse_series(flat(96), np.zeros((96, 96), bool), ops, noise_tol=NOISE_TOL,
                           density="mean2", info=info) is None
    assert info["tier"] == 2 and "second-tier windows" in info["reason"]


def test_flat_uses_the_second_tier(template):
    """A 2048 x 2048 flat of 1e5 e, in strips: the first tier flags every
    cell, the second only the border (also on the first quarter of the rows,
    where the attempt would stop); the result is within half the tolerance
    of the dense series."""
    img = flat(2048)
    kw = dict(density="fv4", noise_tol=NOISE_TOL, start="series", dtype=np.float32,
              strip=512)
    dense, _, _ = C.correct_image(img, template, **REFERENCE.solver_kwargs(**kw))
    info = {}
    out, it, conv = C.correct_image(img, template, **REFERENCE.solver_kwargs(sparse=True,
                                                                             info=info, **kw))
    assert info["solver"] == "sparse" and info["tier"] == 2, info
    assert info["window_fraction"] < 0.5 and it == 0 and conv
    assert np.max(np.abs(out - dense) / S.tolerance(img, NOISE_TOL)) <= 0.5


def test_first_tier_fields_are_unchanged(template):
    """Where the first tier's windows pass, the second tier changes nothing,
    bit for bit (the 400-star density of benchmarks/performance/bench_task.py)."""
    img = crowded(512, seed=7, density=400 / 4096**2)
    img[100:117, 100:117] += 3e4  # and one bright source
    blk = np.zeros(img.shape, bool)
    ops = OperatorCache(template, dtype=np.float32)
    info = {}
    new = S.sparse_series(img, blk, ops, noise_tol=NOISE_TOL, density="fv4", info=info)
    old = S.sparse_series(img, blk, ops, noise_tol=NOISE_TOL, density="fv4",
                          second_tier=False)
    assert info["tier"] == 1 and info["windows"] > 0
    assert np.array_equal(new, old)


@pytest.mark.parametrize("kw, match", [({"fraction": 0.0}, "fraction must be in"),
                                       ({"fraction": 1.5}, "fraction must be in"),
                                       ({"group": 0}, "group must be at least 1")])
def test_bad_options(template, kw, match):
    ops = OperatorCache(template)
    with pytest.raises(InputError, match=match):
        S.sparse_series(np.ones((64, 64)), np.zeros((64, 64), bool), ops, noise_tol=0.05,
                        **kw)


def test_first_tier_area_floor(rng):
    """The dilated active cells' area, which lets the first tier skip forming
    windows bound to exceed max_fraction, never exceeds its windows' area."""
    for _ in range(30):
        shape = (int(rng.integers(40, 300)), int(rng.integers(40, 300)))
        act = rng.random((-(-shape[0] // CELL), -(-shape[1] // CELL))) < 0.1
        boxes = S.window_boxes(act, shape, cell=CELL, dilate=1)
        grown = ndimage.binary_dilation(act, structure=np.ones((3, 3), bool))
        pixels = np.kron(grown, np.ones((CELL, CELL), bool))[:shape[0], :shape[1]].sum()
        floor = S._dilated_area(act, shape, CELL, 1)
        assert floor == pixels
        assert floor <= sum((y1 - y0) * (x1 - x0) for y0, y1, x0, x1 in boxes)


def test_task_on_a_flat_uses_the_second_tier(template):
    """The Task (default drift settings) on a 1024 x 1024 flat of 1e5 e:
    windowed solver, within half the tolerance of the Task without windows,
    the same geometry maps (from the completed first-order pass) as without."""
    from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    img = flat(1024)
    res = BrighterFatterDriftTask(BrighterFatterDriftConfig(workers=1),
                                  template=template).run(img)
    dense = BrighterFatterDriftTask(BrighterFatterDriftConfig(workers=1, sparse=False),
                                    template=template).run(img)
    assert res.header["BFSOLVER"] == "sparse" and dense.header["BFSOLVER"] == "dense"
    dev = np.abs(res.exposure - dense.exposure) / S.tolerance(img, NOISE_TOL)
    assert 0.0 < dev.max() <= 0.5
    for name in ("area", "e1", "e2"):
        assert_allclose(getattr(res, name), getattr(dense, name), rtol=0,
                        atol=1e-6 * np.abs(getattr(dense, name) - (name == "area")).max())
