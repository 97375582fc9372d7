"""Tests of the windowed inverse series, the swept-area operator cache and
the strip form of the astier23 pass."""

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import ndimage
from scipy.signal import convolve2d

from lsst_bfdrift.correction import solvers as C
from lsst_bfdrift.correction import series as S
from lsst_bfdrift.templates.swept import OperatorCache, SweptAreas, swept_area_kernels
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.correction.settings import REFERENCE


@pytest.fixture(scope="module")
def sky_field():
    """Sky with stars from 1e4 to 1.5e6 e (some at the border), a masked
    column segment and a NaN pixel."""
    rng = np.random.default_rng(11)
    n = 512
    img = rng.poisson(1200.0, (n, n)).astype(float)
    yy, xx = np.mgrid[-12:13, -12:13]
    pos = [(40, 40), (3, 120), (506, 200), (128, 128), (140, 135), (60, 400)]
    pos += [tuple(p) for p in rng.integers(0, n, (20, 2))]
    for k, (x, y) in enumerate(pos):
        f = 1.5e6 if k < 6 else 10 ** rng.uniform(4, 6)
        star = f * np.exp(-0.5 * (xx**2 + yy**2) / 1.4**2) / (2 * np.pi * 1.4**2)
        y0, x0 = y - 12, x - 12
        ys, xs = slice(max(y0, 0), min(y0 + 25, n)), slice(max(x0, 0), min(x0 + 25, n))
        img[ys, xs] += star[ys.start - y0:ys.stop - y0, xs.start - x0:xs.stop - x0]
    img[90, 10] = np.nan
    blocked = np.zeros(img.shape, bool)
    blocked[150:160, 60] = True
    return img, blocked


def test_apply_stack_is_the_direct_convolution(rng):
    """Batched swept areas equal the direct linear convolution with the
    template's swept-area kernels, window by window."""
    t = load_default_template()
    kv, kh = swept_area_kernels(t)
    q = rng.uniform(0, 1e4, (3, 30, 41))
    op = SweptAreas(t, (30, 41))
    sv, sh = op.apply_stack(q)
    c = t.center
    for m in range(3):
        ref_v = convolve2d(q[m], kv / t.charge)[c:c + 30, c:c + 42]
        ref_h = convolve2d(q[m], kh / t.charge)[c:c + 31, c:c + 41]
        assert_allclose(sv[m], ref_v, rtol=0, atol=1e-12 * np.abs(ref_v).max())
        assert_allclose(sh[m], ref_h, rtol=0, atol=1e-12 * np.abs(ref_h).max())
    with pytest.raises(ValueError, match="stack"):
        op.apply_stack(q[0])
    # single images: the kept padded buffer must not carry one call's charge
    # into the next (a smaller image is refused, not padded)
    first = op(q[0])
    again = op(q[1])
    ref_v = convolve2d(q[1], kv / t.charge)[c:c + 30, c:c + 42]
    assert_allclose(again[0], ref_v, rtol=0, atol=1e-12 * np.abs(ref_v).max())
    assert not np.allclose(first[0], again[0])
    with pytest.raises(ValueError, match="shape"):
        op(q[0][:29])


def test_operator_cache_reuses_and_checks():
    t = load_default_template()
    ops = OperatorCache(t, workers=1, dtype=np.float32, max_shapes=2)
    a = ops((40, 50))
    assert ops((40, 50)) is a
    ops((41, 50)), ops((42, 50))
    assert ops((40, 50)) is not a  # the oldest was dropped
    kv, kh = swept_area_kernels(t)
    assert ops.kernel_abs_sum == pytest.approx(max(np.abs(kv).sum(), np.abs(kh).sum()) / t.charge)
    with pytest.raises(ValueError, match="OperatorCache"):
        C.correct_image(np.ones((20, 20)), t, **REFERENCE.solver_kwargs(cache=ops,
                                                                        dtype=np.float64))


def test_active_cells_match_numpy_reference(rng):
    img = rng.uniform(0, 5e4, (70, 53))
    k, cell = 2e-6, 16
    b = rng.normal(0, 0.05, img.shape)
    b[20:24, 30:33] = 400.0  # one strong source
    got = S.active_cells(img, b, k, noise_tol=0.05, cell=cell, safety=20.0)
    my, mx = 5, 4
    ref = np.zeros((my, mx), bool)
    imax = np.zeros((my, mx))
    imin = np.zeros((my, mx))
    bmax = np.zeros((my, mx))
    for j in range(my):
        for i in range(mx):
            s = (slice(j * cell, (j + 1) * cell), slice(i * cell, (i + 1) * cell))
            imax[j, i], imin[j, i], bmax[j, i] = (np.abs(img[s]).max(), img[s].min(),
                                                  np.abs(b[s]).max())
    for j in range(my):
        for i in range(mx):
            nb = (slice(max(j - 2, 0), j + 3), slice(max(i - 2, 0), i + 3))
            lmin = 0.05 * np.sqrt(np.maximum(imin[nb].min(), 1.0))
            ref[j, i] = 20.0 * k * imax[nb].max() * bmax[j, i] > lmin
    assert got.shape == (my, mx)
    assert np.array_equal(got, ref)
    assert 0 < ref.sum() < ref.size  # the test exercises both outcomes


@pytest.mark.parametrize("strip", [None, 40, 37])
def test_first_order_pass_gathers_the_cell_statistics(rng, strip):
    """The statistics gathered block by block during the first-order pass
    (blocks not aligned with the cells for strip=37) equal plain numpy ones
    over the finished image, and the pass itself equals the dense
    half-shift I - B(I, I)/2."""
    t = load_default_template()
    img = rng.uniform(0, 5e4, (101, 70))
    img[30:34, 40:44] += 4e5
    blk = np.zeros(img.shape, bool)
    blk[50, 10:14] = True
    ops = OperatorCache(t, dtype=np.float64)
    first, sv, sh, (imax, imin, bmax) = S.first_order_terms(img, blk, ops, strip=strip,
                                                            cubic="fv4", cell=16)
    sv_ref, sh_ref = SweptAreas(t, img.shape)(img)
    b_ref = C.fused_transfer(sv_ref, sh_ref, img, blk, cubic="fv4")
    assert_allclose(first, img - 0.5 * b_ref, rtol=0, atol=1e-9 * np.abs(b_ref).max())
    assert_allclose(sv, sv_ref, rtol=0, atol=1e-12 * np.abs(sv_ref).max())
    assert_allclose(sh, sh_ref, rtol=0, atol=1e-12 * np.abs(sh_ref).max())
    assert imax.shape == (7, 5)
    for j in range(7):
        for i in range(5):
            s = (slice(16 * j, 16 * j + 16), slice(16 * i, 16 * i + 16))
            assert imax[j, i] == np.abs(img[s]).max()
            assert imin[j, i] == img[s].min()
            assert_allclose(bmax[j, i], np.abs(b_ref[s]).max(), rtol=1e-9)
    assert S.first_order_terms(img, blk, ops, strip=strip, cubic="fv4")[3] is None


def test_window_boxes_cover_and_do_not_overlap(rng):
    for trial in range(20):
        act = rng.random((12, 15)) < 0.06
        boxes = S.window_boxes(act, (12 * 16 - 5, 15 * 16), cell=16, dilate=1)
        grown = ndimage.binary_dilation(act, structure=np.ones((3, 3), bool))
        cover = np.zeros((12 * 16 - 5, 15 * 16), int)
        for y0, y1, x0, x1 in boxes:
            cover[y0:y1, x0:x1] += 1
        assert cover.max() <= 1  # no overlap
        full = np.kron(grown, np.ones((16, 16), int))[:12 * 16 - 5]
        assert np.all(cover[full.astype(bool)] == 1)  # every dilated active cell covered
    assert S.window_boxes(np.zeros((3, 3), bool), (48, 48)) == []


@pytest.mark.parametrize("density", ["mean2", "cubic4", "fv4"])
def test_sparse_equals_dense_series_within_the_bound(sky_field, density):
    """The windowed series differs from the dense third-order series by far
    less than its bound (0.1 x tolerance), conserves flux exactly, leaves
    blocked and NaN pixels alone and never touches the input."""
    img, blocked = sky_field
    t = load_default_template()
    keep = img.copy()
    kw = dict(density=density, noise_tol=0.05, start="series", blocked=blocked, strip=64)
    dense, it_d, _ = C.correct_image(img, t, **REFERENCE.solver_kwargs(**kw))
    info = {}
    sparse, it, conv = C.correct_image(img, t, **REFERENCE.solver_kwargs(sparse=True, info=info,
                                                                         **kw))
    assert info["solver"] == "sparse" and it == 0 and conv
    assert 0.0 < info["window_fraction"] < 0.5
    ok = np.isfinite(img) & ~blocked
    lim = 0.05 * np.sqrt(np.maximum(img[ok], 1.0))
    assert np.max(np.abs(sparse - dense)[ok] / lim) < 0.1
    assert np.max(np.abs(sparse - img)[ok] / lim) > 100  # a strong correction
    assert abs(sparse[ok].sum() - img[ok].sum()) < 1e-9 * img[ok].sum()
    assert np.isnan(sparse[90, 10])
    assert_allclose(sparse[blocked], img[blocked])
    assert np.array_equal(img, keep, equal_nan=True)


def test_sparse_against_iterated_reference(sky_field):
    """At the calibrated strength the windowed series is within 0.02 of the
    Poisson noise of the solution iterated to 1e-12 (the dense series'
    accuracy, tests/test_task.py)."""
    img, blocked = sky_field
    t = load_default_template()
    ok = np.isfinite(img) & ~blocked
    ref, _, conv = C.correct_image(img, t, **REFERENCE.solver_kwargs(density="mean2",
                                                                     start="image", rtol=1e-12,
                                                                     max_iter=60, blocked=blocked))
    assert conv
    info = {}
    fast, _, _ = C.correct_image(img, t, **REFERENCE.solver_kwargs(density="mean2", noise_tol=0.05,
                                                                   start="series", sparse=True,
                                                                   blocked=blocked,
                                                                   dtype=np.float32, info=info))
    assert info["solver"] == "sparse", info
    assert np.max(np.abs(fast - ref)[ok] / np.sqrt(img[ok])) < 0.02


def test_sparse_falls_back_to_dense_on_flats():
    """A bright flat needs the higher-order terms everywhere: the sparse
    solver declines and the dense result is returned unchanged."""
    rng = np.random.default_rng(3)
    flat = rng.poisson(1e5, (96, 96)).astype(float)
    t = load_default_template()
    info = {}
    a, _, _ = C.correct_image(flat, t, **REFERENCE.solver_kwargs(density="mean2", noise_tol=0.05,
                                                                 start="series", sparse=True,
                                                                 info=info))
    b, _, _ = C.correct_image(flat, t, **REFERENCE.solver_kwargs(density="mean2", noise_tol=0.05,
                                                                 start="series"))
    assert info["solver"] == "dense" and "windows cover" in info["reason"]
    # in strips, the attempt stops after a quarter of the rows
    info = {}
    c, _, _ = C.correct_image(flat, t, **REFERENCE.solver_kwargs(density="mean2", noise_tol=0.05,
                                                                 start="series", sparse=True,
                                                                 info=info, strip=16))
    assert info["solver"] == "dense" and "cells need" in info["reason"]
    assert_allclose(c, b, rtol=0, atol=1e-9 * flat.max())
    assert_allclose(a, b, rtol=0, atol=0)


def test_sparse_rtol_and_bad_cell(sky_field):
    img, blocked = sky_field
    t = load_default_template()
    eff = np.where(np.isfinite(img), img, 0.0)
    blk = blocked | ~np.isfinite(img)
    ops = OperatorCache(t)
    info = {}
    out = S.sparse_series(eff, blk, ops, rtol=1e-5, noise_tol=None, density="mean2", info=info)
    dense, _, _ = C.correct_image(img, t, **REFERENCE.solver_kwargs(density="mean2", rtol=1e-5,
                                                                    start="series",
                                                                    blocked=blocked))
    assert out is not None, info
    ok = ~blk
    assert np.max(np.abs(out - dense)[ok]) < 0.1 * 1e-5 * np.abs(eff).max()
    with pytest.raises(ValueError, match="cell"):
        S.sparse_series(eff, blk, ops, noise_tol=0.05, cell=4)


def test_half_shift_strips_are_exact(sky_field):
    img, blocked = sky_field
    t = load_default_template()
    whole, _, _ = C.correct_half_shift(img, t, blocked=blocked)
    strips, _, _ = C.correct_half_shift(img, t, blocked=blocked, strip=37)
    ok = np.isfinite(img)
    assert_allclose(strips[ok], whole[ok], rtol=0, atol=1e-9 * np.nanmax(img))
    with pytest.raises(ValueError, match="strip"):
        C.correct_half_shift(img, t, strip=0)


def test_fused_transfer_serial_and_parallel_agree(rng):
    """The parallel kernel (which fused_transfer runs on large images when numba
    has more than one thread) gives the serial kernel's numbers bit for bit."""
    from lsst_bfdrift.correction import _edge_kernels as E
    f = rng.uniform(0, 1e4, (40, 33))
    blk = np.zeros(f.shape, bool)
    blk[7, 8] = True
    sv, sh = rng.normal(size=(40, 34)), rng.normal(size=(41, 33))
    serial = E.fused_transfer(sv[:, :], sh, f, blk, cubic=True)
    parallel = np.empty(f.shape)
    E.fused_parallel(sv, sh, f, blk, blk.any(axis=1), E.density_weight(True), parallel)
    assert_allclose(serial, parallel, rtol=0, atol=0)
    ref = C.edge_transfer(sv, sh, *C.edge_flux_density(f, mode="cubic4", blocked=blk))
    assert_allclose(serial, ref, rtol=1e-12, atol=1e-9)


def test_task_uses_windows_and_keeps_its_operators(sky_field):
    from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    img, blocked = sky_field
    task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False,
                                                                    workers=1))
    res = task.run(np.where(blocked, np.nan, img))
    assert res.header["BFSOLVER"] == "sparse" and "BFGSAMP" not in res.header
    ops = task._cache
    n_ops = len(ops._ops)
    again = task.run(np.where(blocked, np.nan, img))
    assert task._cache is ops and len(ops._ops) == n_ops  # kernel transforms reused
    assert np.array_equal(res.exposure, again.exposure, equal_nan=True)
    dense = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(
        compute_geometry=False, workers=1, sparse=False)).run(np.where(blocked, np.nan, img))
    assert dense.header["BFSOLVER"] == "dense"
    ok = np.isfinite(img) & ~blocked
    lim = 0.05 * np.sqrt(img[ok])
    assert np.max(np.abs(res.exposure - dense.exposure)[ok] / lim) < 0.1
    assert abs(res.flux_moved.sum()) < 1e-9 * np.nansum(img)


def test_one_task_in_several_threads(sky_field):
    """A Task shared by threads (as in a dask worker) gives each image the
    result it gets alone: the work arrays are per thread."""
    from concurrent.futures import ThreadPoolExecutor

    from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    img, _ = sky_field
    imgs = [np.nan_to_num(img), np.nan_to_num(img[::-1].copy()), np.nan_to_num(img.T.copy())]
    task = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False,
                                                                    workers=1))
    alone = [task.run(a).exposure for a in imgs]
    with ThreadPoolExecutor(3) as pool:
        together = list(pool.map(lambda a: task.run(a).exposure, imgs * 2))
    for k, out in enumerate(together):
        assert np.array_equal(out, alone[k % 3])


def test_sparse_series_takes_a_template_smaller_than_7_px(small_template):
    """A 5 x 5 template reaches 3 px: the cell margins start there, not at 4 px
    (once 'margins must be increasing ... (4, 3, 6)'). Independent reference:
    the dense float64 solver on the same image, and charge conservation."""
    from lsst_bfdrift.correction.settings import RECOMMENDED
    rng = np.random.default_rng(7)
    yy, xx = np.mgrid[:96, :96]
    img = 1000.0 + 6e4 * np.exp(-((xx - 47.3) ** 2 + (yy - 50.6) ** 2) / (2 * 1.8 ** 2))
    img = img + rng.normal(0.0, 30.0, img.shape)
    before = img.copy()
    sparse, _, converged = C.correct_image(img, small_template,
                                           **RECOMMENDED.solver_kwargs(dtype=np.float64))
    dense, _, _ = C.correct_image(img, small_template, **REFERENCE.solver_kwargs())
    assert converged
    assert_allclose(img, before)
    assert_allclose(sparse.sum(), img.sum(), rtol=1e-9)
    assert_allclose(sparse, dense, atol=0.05 * np.abs(dense - img).max())
