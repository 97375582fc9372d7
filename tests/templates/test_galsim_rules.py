"""Binning of a batch of located conversions, shared by both layouts' accumulation."""

import numpy as np

from lsst_bfdrift.templates.galsim_rules import collect_batch


def test_collect_batch_equals_direct_binning(rng):
    ny, nx = 7, 9
    n = 500
    oi = rng.integers(-2, nx + 2, n)
    oj = rng.integers(-2, ny + 2, n)
    px = rng.uniform(-1.5, nx + 0.5, n)
    py = rng.uniform(-1.5, ny + 0.5, n)
    image = np.full((ny, nx), 3.0)
    nominal = np.zeros((ny, nx))
    dq = np.zeros((ny, nx))
    changed = np.empty(ny * nx, dtype=np.int64)
    nch, lost, jlo, jhi, ilo, ihi = collect_batch(oi, oj, px, py, image, nominal, dq, changed)

    on = (oi >= 0) & (oi < nx) & (oj >= 0) & (oj < ny)
    ref = np.zeros((ny, nx))
    np.add.at(ref, (oj[on], oi[on]), 1.0)
    assert lost == np.sum(~on)
    np.testing.assert_array_equal(image, 3.0 + ref)
    np.testing.assert_array_equal(dq, ref)
    i0, j0 = np.floor(px + 0.5).astype(int), np.floor(py + 0.5).astype(int)
    ok = (i0 >= 0) & (i0 < nx) & (j0 >= 0) & (j0 < ny)
    nom = np.zeros((ny, nx))
    np.add.at(nom, (j0[ok], i0[ok]), 1.0)
    np.testing.assert_array_equal(nominal, nom)
    # changed pixels: each once, in order of their first conversion
    flat = oj[on] * nx + oi[on]
    _, first = np.unique(flat, return_index=True)
    np.testing.assert_array_equal(changed[:nch], flat[np.sort(first)])
    assert (jlo, jhi, ilo, ihi) == (oj[on].min(), oj[on].max(), oi[on].min(), oi[on].max())


def test_collect_batch_of_lost_conversions_only():
    image = np.zeros((3, 3))
    dq = np.zeros((3, 3))
    out = collect_batch(np.array([-1, 5]), np.array([0, 0]), np.array([9.0, 9.0]),
                        np.array([9.0, 9.0]), image, np.zeros((3, 3)), dq,
                        np.empty(9, dtype=np.int64))
    assert out == (0, 2, 3, -1, 3, -1)
    assert not image.any() and not dq.any()
