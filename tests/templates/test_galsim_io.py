"""Tests of the transfer-matched import of GalSim's sensor files (lsst_bfdrift.templates.galsim_io)."""

from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.templates import galsim_io
from lsst_bfdrift.correction.solvers import swept_area_kernels

NAME = "lsst_itl_50_8"
CELLS = 800  # sampling cells per pixel side (the import's default is 2000)


@pytest.fixture(scope="module")
def raw():
    return galsim_io.read_galsim_sensor(NAME)


@pytest.fixture(scope="module")
def moves(raw):
    return galsim_io.galsim_effective_moves(NAME, template=raw, cells=CELLS)


@pytest.fixture(scope="module")
def matched(raw):
    return galsim_io.match_galsim_transfers(raw, NAME, cells=CELLS)


def kernel_areas(template):
    kv, kh = swept_area_kernels(template)
    return 1.0 + kv[:, 1:] - kv[:, :-1] + kh[1:, :] - kh[:-1, :]


def received(mv):
    """Area each pixel receives, summed directly from the moves (no edges involved)."""
    m = mv.shape[0]
    out = np.zeros((m + 2, m + 2))
    for j in range(m):
        for i in range(m):
            out[j:j + 3, i:i + 3] += mv[j, i]
    return out


def test_moves_cover_every_pixel_once(moves):
    # every point of a nominal pixel goes somewhere: rows sum to the pixel's area
    assert_allclose(moves.sum(axis=(2, 3)), 1.0, atol=1e-9)
    assert moves.min() >= 0.0
    # GalSim's qdist=3 moves nothing at the margin: no area leaves the sampled region
    assert_allclose(received(moves)[[0, -1], :], 0.0, atol=0)
    assert_allclose(received(moves)[:, [0, -1]], 0.0, atol=0)


def test_transfers_keep_every_pixel_gain_and_conserve(moves):
    """Sum rule: the net edge transfers (diagonal moves split over two paths)
    give each pixel exactly the area it receives from the moves, and the
    total area is conserved."""
    tv, th = galsim_io.transfers_from_moves(moves)
    area = 1.0 + tv[:, 1:] - tv[:, :-1] + th[1:, :] - th[:-1, :]
    assert_allclose(area, received(moves)[1:-1, 1:-1], atol=1e-12)
    assert_allclose(area.sum(), area.size, atol=1e-9)
    # outer boundary of the sampled region: nothing crosses it
    assert_allclose(tv[:, [0, -1]], 0.0, atol=0)
    assert_allclose(th[[0, -1], :], 0.0, atol=0)


def test_diagonal_move_is_split_over_both_paths():
    mv = np.zeros((3, 3, 3, 3))
    mv[..., 1, 1] = 1.0
    mv[1, 1, 1, 1] = 0.9
    mv[1, 1, 2, 2] = 0.1  # centre -> upper right
    tv, th = galsim_io.transfers_from_moves(mv)
    assert_allclose(tv[1, 2], -0.05) and assert_allclose(tv[2, 2], -0.05)
    assert_allclose(th[2, 1], -0.05) and assert_allclose(th[2, 2], -0.05)
    assert np.count_nonzero(tv) == 2 and np.count_nonzero(th) == 2


def test_rules_engine_reproduces_galsim(raw, moves):
    """The re-implementation of GalSim's layout and rule (_galsim_rules) sends the
    same points to the same pixels as galsim.SiliconSensor itself, up to GalSim's
    random choice for points found in no pixel and a 1e-5 px^2 detail at one
    pixel far from the aggressor."""
    rules = galsim_io.galsim_effective_moves(NAME, template=raw, cells=CELLS, engine="rules")
    assert_allclose(rules, moves, atol=2e-5)
    # the effect is far larger than the tolerance
    assert np.abs(moves[..., 1, 1] - 1.0).max() > 0.1


def test_matched_template_kernels_are_galsim_transfers(raw, matched, moves):
    tv, th = galsim_io.transfers_from_moves(moves)
    kv, kh = swept_area_kernels(matched)
    n, mg = matched.size, 2
    assert_allclose(kv, tv[mg:mg + n, mg:mg + n + 1], atol=1e-12)
    assert_allclose(kh, th[mg:mg + n + 1, mg:mg + n], atol=1e-12)
    # conservation of the kernels: areas sum to N^2, border edges carry nothing
    assert_allclose(kernel_areas(matched).sum(), n * n, atol=1e-9)
    # only the edge samples moved, by less than 0.01 px; corners untouched
    assert_allclose(matched.corner_d, raw.corner_d, atol=0)
    assert 0 < matched.meta["transfer_matched"]["max_sample_change_px"] < 0.01
    assert matched.meta["transfer_matched"]["max_outside_transfer_px2"] == 0.0


@pytest.mark.slow
def test_flat_through_galsim_measures_the_matched_areas(matched):
    """Independent test: a flat (uniform photons, diffusion on) through
    galsim.SiliconSensor onto a stamp whose central pixel already holds the
    template's charge (the boundaries are set from the image's charge when the
    accumulation starts and frozen: nrecalc above the photon count). Counts
    minus the same photons without the aggressor, over the density, are the
    effective area changes; the matched template's must agree within the
    Poisson error of the moved photons."""
    import galsim

    half, pad = 6, 3
    side = 2 * half + 1
    n = 8_000_000
    rng = np.random.default_rng(20151)
    lo, hi = -half - 0.5 - pad, half + 0.5 + pad
    x, y = rng.uniform(lo, hi, n), rng.uniform(lo, hi, n)
    dens = n / (hi - lo) ** 2
    counts = []
    for q in (matched.charge, 0.0):
        img = galsim.ImageD(side, side)
        img.setCenter(0, 0)
        img[0, 0] = q
        sensor = galsim.SiliconSensor(NAME, rng=galsim.BaseDeviate(7), nrecalc=1e18)
        sensor.accumulate(galsim.PhotonArray(n, x=x, y=y, flux=np.ones(n)), img)
        a = img.array.copy()
        a[half, half] -= q
        counts.append(a)
    measured = (counts[0] - counts[1]) / dens
    c, nt = matched.center, matched.size
    kv, kh = swept_area_kernels(matched)
    model = np.zeros((side, side))
    model[half - c:half + c + 1, half - c:half + c + 1] = kernel_areas(matched) - 1.0
    moved = np.zeros((side, side))
    moved[half - c:half + c + 1, half - c:half + c + 1] = (
        np.abs(kv[:, 1:]) + np.abs(kv[:, :-1]) + np.abs(kh[1:, :]) + np.abs(kh[:-1, :]))
    sigma = np.sqrt((moved + 1.0 / dens) / dens)
    z = (measured - model) / sigma
    inner = slice(2, side - 2)  # the stamp's outermost pixels lose photons by diffusion
    assert np.abs(z[inner, inner]).max() < 5
    assert np.mean(z[inner, inner] ** 2) < 2.0
    # and the test has power: the central pixel's change is many sigma
    assert abs(measured[half, half]) > 20 * sigma[half, half]
    assert nt == 9


def test_area_match_path_unchanged(raw):
    """match='areas' is the default import; its pixel polygons have GalSim's
    own areas."""
    import galsim

    old = import_galsim_sensor(NAME, match="areas")
    default = import_galsim_sensor(NAME)
    for t in (default,):
        assert_allclose(t.corner_d, old.corner_d, atol=0)
        assert_allclose(t.vedge_d, old.vedge_d, atol=0)
        assert_allclose(t.hedge_d, old.hedge_d, atol=0)
    assert_allclose(old.vedge_d, raw.vedge_d, atol=0)  # only corners move
    sensor = galsim.SiliconSensor(NAME)
    img = galsim.ImageD(21, 21)
    img.setCenter(0, 0)
    img[0, 0] = old.charge
    ref = sensor.calculate_pixel_areas(img).array[10 - 4:10 + 5, 10 - 4:10 + 5]
    assert_allclose(old.moments().area, ref, atol=1e-9)
    none = import_galsim_sensor(NAME, match="none")
    assert_allclose(none.corner_d, raw.corner_d, atol=0)
    assert none.meta["galsim_match"] == "none" and old.meta["galsim_match"] == "areas"


def test_bad_options():
    with pytest.raises(ValueError, match="match must be"):
        import_galsim_sensor(NAME, match="polygons")
    with pytest.raises(ValueError, match="engine"):
        galsim_io.galsim_effective_moves(NAME, engine="magic")
    with pytest.raises(ValueError, match="cells"):
        galsim_io.galsim_effective_moves(NAME, cells=3)
    with pytest.raises(ValueError, match="charge"):
        galsim_io.galsim_effective_moves(NAME, charge=-1.0)


@pytest.mark.slow
def test_import_galsim_sensor_transfers_default_is_small_charge_limit(raw):
    """match='transfers' measures at 1e4 e and scales to the file's charge; the
    central pixel's effective area change per 1e5 e is then larger in size than
    at the file's own 1e5 e (GalSim's rule is slightly non-linear)."""
    tpl = import_galsim_sensor(NAME, match="transfers", transfer_cells=1000)
    meta = tpl.meta["transfer_matched"]
    assert tpl.meta["galsim_match"] == "transfers" and meta["charge"] == 1e4
    assert tpl.charge == raw.charge
    mv = galsim_io.galsim_effective_moves(NAME, template=raw, cells=1000, charge=1e4)
    tv, th = galsim_io.transfers_from_moves(mv)
    kv, kh = swept_area_kernels(tpl)
    n, s = tpl.size, raw.charge / 1e4
    assert_allclose(kv, s * tv[2:2 + n, 2:2 + n + 1], atol=1e-12)
    assert_allclose(kh, s * th[2:2 + n + 1, 2:2 + n], atol=1e-12)
    c = tpl.center
    small = kernel_areas(tpl)[c, c] - 1.0
    at_file = kernel_areas(galsim_io.match_galsim_transfers(raw, NAME, cells=CELLS))[c, c] - 1.0
    assert -0.110 < small < -0.105 and -0.106 < at_file < -0.102 and small < at_file


def test_ring_offset_of_galsim_files(raw):
    """GalSim's own files (independent data): the ITL file's outermost ring is at
    rest, the older e2v file's horizontal boundaries all sit 0.0158 px low
    (at 8e4 e), which the import records and warns about."""
    dx, dy = raw.meta["galsim_ring_offset"]
    assert abs(dx) < 1e-4 and abs(dy) < 1e-4
    with pytest.warns(UserWarning, match=r"dy = -0\.0158 px.*charge-independent offset"):
        old = galsim_io.read_galsim_sensor("lsst_e2v_8")
    dx, dy = old.meta["galsim_ring_offset"]
    assert abs(dx) < 1e-4
    assert_allclose(dy, -0.0158, atol=5e-4)


def test_ring_offset_injected(tmp_path):
    """A copy of the ITL file with every horizontal boundary moved up by 0.02 px:
    the injected offset is found exactly (the ITL file's own ring is at rest)."""
    cfg, dat = galsim_io.galsim_sensor_files(NAME)
    table, config = galsim_io.galsim_vertex_table(NAME)
    header = Path(dat).read_text().splitlines()[0]
    data = np.loadtxt(dat, skiprows=1)
    horiz = np.isin(np.asarray(table["kind"]), ["top", "bottom"])
    data[horiz, 4] += 0.02 * float(config["PixelSizeX"])
    (tmp_path / "moved.cfg").write_text(Path(cfg).read_text())
    np.savetxt(tmp_path / "moved.dat", data, header=header.strip(), comments="")
    before = galsim_io.galsim_ring_offset(table)
    with pytest.warns(UserWarning, match="charge-independent offset"):
        moved = galsim_io.read_galsim_sensor(str(tmp_path / "moved"))
    assert_allclose(moved.meta["galsim_ring_offset"][1], before[1] + 0.02, atol=1e-6)
    assert_allclose(moved.meta["galsim_ring_offset"][0], before[0], atol=1e-12)
