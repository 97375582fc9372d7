"""Tests of lsst_bfdrift.ptc.inputs: every input kind of ``bfdrift calibrate``."""

import hashlib
import json
import re
import warnings

import astropy.units as u
import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from numpy.testing import assert_allclose, assert_array_equal

from lsst_bfdrift.ptc.cp_pipe import CP_PIPE_COLUMNS
from lsst_bfdrift.ptc.data import CalibrationData
from lsst_bfdrift.ptc.inputs import detect_input_kind, read_calibration_input
from lsst_bfdrift.ptc.covariances import pair_covariances

EOTEST = "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt"
ITL = "/work/shared/data/measured/itl_covariances_21oct19.txt"
SHAPE = (40, 40)
GAIN = 2.0
#: exposure times (s) and mean signals (ADU) of the synthetic flats
LEVELS = {1.0: 500.0, 2.0: 1000.0, 4.0: 2000.0, 8.0: 4000.0}


def _flat(rng, mean, shape=SHAPE, full_well=None):
    img = rng.poisson(mean * GAIN, shape) / GAIN
    return img if full_well is None else np.minimum(img, full_well)


def _write_flat(path, data, *, exptime=1.0, gain=GAIN, bunit="adu", mask=None,
                in_primary=False):
    """A flat FITS: primary header (+ image in an extension unless in_primary)."""
    img = fits.ImageHDU(data.astype(np.float32), name="IMAGE")
    prim = fits.PrimaryHDU(data.astype(np.float32) if in_primary else None)
    target = prim.header if in_primary else img.header
    for key, val in (("EXPTIME", exptime), ("GAIN", gain), ("BUNIT", bunit)):
        if val is not None:
            target[key] = val
    hdus = [prim] if in_primary else [prim, img]
    if mask is not None:
        hdus.append(fits.ImageHDU(mask.astype(np.int16), name="MASK"))
    fits.HDUList(hdus).writeto(path)
    return str(path)


def _flat_set(tmp_path, rng, levels=LEVELS, **kw):
    paths = []
    for t, mean in levels.items():
        for k in range(2):
            paths.append(_write_flat(tmp_path / f"flat_{t:05.1f}_{k}.fits", _flat(rng, mean),
                                     exptime=t, **kw))
    return paths


def _digest(paths):
    out = {}
    for p in paths:
        with open(p, "rb") as fh:
            out[p] = hashlib.sha256(fh.read()).hexdigest()
    return out


# --------------------------------------------------------------------------- flats

def test_flats_grouped_by_exptime_paired_in_name_order(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    # a third flat at 2 s, its EXPTIME 2.5e-4 off (within the 1e-3 tolerance): odd file out
    paths.append(_write_flat(tmp_path / "flat_002.0_2.fits", _flat(rng, 1000.0), exptime=2.0005))
    before = _digest(paths)
    shuffled = [paths[k] for k in rng.permutation(len(paths))]
    d = read_calibration_input(shuffled, max_lag=2, min_pixels=500)
    assert _digest(paths) == before  # inputs untouched
    assert isinstance(d, CalibrationData) and d.kind == "flats"
    assert d.n_levels == 4 and d.mu.size == 4 and d.cov.shape == (4, 3, 3)
    assert d.npix.shape == (4, 3, 3) and np.all(d.npix > 0)
    assert [p["files"] for p in d.pairs_used] == [paths[2 * k:2 * k + 2] for k in range(4)]
    assert len(d.pairs_dropped) == 1
    assert d.pairs_dropped[0]["files"] == [paths[-1]]
    assert "odd file out" in d.pairs_dropped[0]["reason"]
    assert_allclose(d.exptime, [1.0, 2.0, 4.0, 8.0])
    assert_allclose(d.mu, list(LEVELS.values()), rtol=0.01)
    # Poisson flats: variance mu / gain, neighbours uncorrelated
    assert_allclose(d.var, d.mu / GAIN, rtol=0.1)
    assert np.all(np.abs(d.cov[:, 1, 0]) < 0.05 * d.var)
    assert d.gain == GAIN and d.units == "adu" and "GAIN" in d.gain_source
    assert d.turnoff == np.inf and d.max_lag == 2
    s = d.summary()
    json.dumps(s, allow_nan=False)
    assert s["n_levels"] == 4 and s["turnoff"] is None and s["kind"] == "flats"


def test_saturated_level_past_turnoff_excluded_and_reported(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    for k in range(2):  # 16 s: mean 8000 ADU clipped at a 7000 ADU full well
        paths.append(_write_flat(tmp_path / f"flat_sat_{k}.fits",
                                 _flat(rng, 8000.0, full_well=7000.0), exptime=16.0))
    d = read_calibration_input(paths, max_lag=1, min_pixels=500)
    assert d.n_levels == 4
    assert_allclose(d.exptime, [1.0, 2.0, 4.0, 8.0])
    assert d.turnoff == pytest.approx(d.mu[-1])
    (gone,) = d.pairs_dropped
    assert gone["files"] == paths[-2:] and gone["exptime"] == 16.0
    assert "turn-off" in gone["reason"] and "saturation" in gone["reason"]
    assert gone["var"] < 0.95 * d.var.max()


def test_too_few_levels_below_turnoff_is_an_error(tmp_path, rng):
    levels = {1.0: 500.0, 2.0: 1000.0}
    paths = _flat_set(tmp_path, rng, levels)
    for k in range(2):
        paths.append(_write_flat(tmp_path / f"flat_sat_{k}.fits",
                                 _flat(rng, 8000.0, full_well=2000.0), exptime=16.0))
    with pytest.raises(ValueError, match=r"2 distinct signal level\(s\) remain below the PTC "
                                         r"turn-off, fewer than min_levels=3.*saturation"):
        read_calibration_input(paths, max_lag=1, min_pixels=500)


def test_fewer_than_three_levels_is_an_error(tmp_path, rng):
    paths = _flat_set(tmp_path, rng, {1.0: 500.0, 2.0: 1000.0})
    with pytest.raises(ValueError, match=r"2 distinct signal level\(s\) with a pair of flats, "
                                         r"fewer than min_levels=3"):
        read_calibration_input(paths, max_lag=1)


def test_nan_pixels_masked_and_counted_mask_hdu_honoured(tmp_path, rng):
    paths = _flat_set(tmp_path, rng, {1.0: 500.0, 2.0: 1000.0, 8.0: 4000.0})
    f1 = _flat(rng, 2000.0)
    f2 = _flat(rng, 2000.0)
    f1[3, 5:9] = np.nan  # 4 NaN pixels
    mask = np.zeros(SHAPE, bool)
    mask[20:22, 10:13] = True  # 6 pixels flagged bad, slightly warm (too little to be clipped)
    f2[mask] += 30.0
    paths += [_write_flat(tmp_path / "flat_004.0_0.fits", f1, exptime=4.0),
              _write_flat(tmp_path / "flat_004.0_1.fits", f2, exptime=4.0, mask=mask)]
    d = read_calibration_input(paths, max_lag=2, min_pixels=500)
    (pair,) = [p for p in d.pairs_used if p["exptime"] == 4.0]
    assert pair["nan_pixels"] == 4 and pair["mask_pixels"] == 6 and pair["nmasked"] >= 10
    assert any("4 NaN/inf pixel(s) masked" in n for n in d.notes)
    f1r = fits.getdata(paths[-2], 1).astype(float)
    f2r = fits.getdata(paths[-1], 1).astype(float)
    ref = pair_covariances(f1r, f2r, max_lag=2, mask=mask | np.isnan(f1r), min_pixels=500)
    k = int(np.flatnonzero(d.exptime == 4.0)[0])
    assert_allclose(d.cov[k], ref.cov, rtol=1e-12)
    assert_array_equal(d.npix[k], ref.npix)


def test_electron_flats_and_exptime_in_primary_header(tmp_path, rng):
    paths = _flat_set(tmp_path, rng, gain=None, bunit="electron", in_primary=True)
    d = read_calibration_input(paths, max_lag=1, min_pixels=500)
    assert d.units == "electron" and d.gain == 1.0 and "electron" in d.gain_source


def test_zero_exptime_file_dropped_as_not_a_flat(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    bias = _write_flat(tmp_path / "bias.fits", rng.normal(0.0, 5.0, SHAPE), exptime=0.0)
    d = read_calibration_input(paths + [bias], max_lag=1, min_pixels=500)
    assert d.n_levels == 4
    (gone,) = d.pairs_dropped
    assert gone["files"] == [bias] and "not positive (a bias or dark" in gone["reason"]


def test_flats_without_gain_stay_in_adu(tmp_path, rng):
    paths = _flat_set(tmp_path, rng, gain=None, bunit=None)
    d = read_calibration_input(paths, max_lag=1, min_pixels=500)
    assert d.units == "adu" and d.gain is None and "no GAIN" in d.gain_source
    assert any("no BUNIT" in n for n in d.notes)


def test_flats_of_different_shapes(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    odd = _write_flat(tmp_path / "flat_small.fits", _flat(rng, 500.0, (40, 30)), exptime=1.0)
    with pytest.raises(ValueError, match=re.escape(odd) + r": image shape \(40, 30\) differs "
                                         r"from .*flat_001\.0_0\.fits \(40, 40\)"):
        read_calibration_input(paths + [odd])


def test_flat_missing_exptime(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    bad = _write_flat(tmp_path / "flat_noexp.fits", _flat(rng, 500.0), exptime=None)
    with pytest.raises(ValueError, match=re.escape(bad) + ": no EXPTIME keyword.*primary"):
        read_calibration_input(paths + [bad])


def test_only_one_flat(tmp_path, rng):
    one = _write_flat(tmp_path / "flat.fits", _flat(rng, 500.0))
    with pytest.raises(ValueError, match=re.escape(one) + ": only one flat given"):
        read_calibration_input(one)


def test_level_with_a_single_flat(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    lone = _write_flat(tmp_path / "flat_lone.fits", _flat(rng, 1500.0), exptime=3.0)
    with pytest.raises(ValueError, match=re.escape(lone) + r": the only flat at EXPTIME = 3 s "
                                         r"\(nearest other level: EXPTIME = [24] s.*drop_single"):
        read_calibration_input(paths + [lone], max_lag=1, min_pixels=500)
    d = read_calibration_input(paths + [lone], max_lag=1, min_pixels=500, drop_single=True)
    assert d.n_levels == 4
    assert d.pairs_dropped == [{"files": [lone], "exptime": 3.0,
                                "reason": "the only flat at its EXPTIME (no partner)"}]


def test_pair_with_mismatched_exptime_is_two_lone_flats(tmp_path, rng):
    paths = _flat_set(tmp_path, rng)
    a = _write_flat(tmp_path / "flat_a.fits", _flat(rng, 1500.0), exptime=3.0)
    b = _write_flat(tmp_path / "flat_b.fits", _flat(rng, 1500.0), exptime=3.03)
    with pytest.raises(ValueError, match=r"relative difference 0\.01 > exptime_rtol=0\.001"):
        read_calibration_input(paths + [a, b], max_lag=1, min_pixels=500)


# --------------------------------------------------------------------------- PTC and a-matrix text

def test_eotest_ptc_file():
    d = read_calibration_input(EOTEST)
    raw = np.loadtxt(EOTEST)
    assert d.kind == "ptc" and d.units == "adu" and d.gain is None and d.cov is None
    assert d.mu.size + len(d.pairs_dropped) == raw.shape[0] == 43
    assert np.all(np.diff(d.mu) > 0)
    assert d.turnoff == 158970.0 and d.mu[-1] == 158970.0
    assert len(d.pairs_dropped) == 9
    assert all("turn-off" in p["reason"] and p["mu"] > d.turnoff for p in d.pairs_dropped)
    assert d.mu[0] == 99.6577 and d.var[0] == 191.377
    json.dumps(d.summary(), allow_nan=False)


def test_itl_amatrix_text():
    d = read_calibration_input(ITL)
    assert d.kind == "amatrix" and d.a.shape == (9, 9) and d.max_lag == 8
    # i serial, j parallel: the file's a[0, 1] is the (larger) parallel neighbour
    assert_allclose(d.a[0, 1], 1.761e-7)
    assert_allclose(d.a[1, 0], 7.245e-8)
    assert_allclose(d.a_sigma[0, 0], 1.454e-8)
    assert d.a00_measured is False  # set by the area sum rule
    t = d.acoeff_table()
    assert t.exclude_a00 and "serial, parallel" in t.axis_note
    assert_allclose(read_calibration_input(ITL, max_lag=3).a, d.a[:4, :4])


def _amatrix(L=3, a00=-1.0e-6):
    i, j = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    a = 1.0e-7 / (1.0 + i**2 + 2.0 * j**2) * (1.0 + j)
    a[0, 0] = a00
    return a, np.full(a.shape, 1.0e-8)


def _write_ecsv(path, a, s, *, unit=1 / u.electron, rows=None):
    L = a.shape[0] - 1
    i, j = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    t = Table({"i": i.ravel(), "j": j.ravel(), "a": a.ravel(), "a_err": s.ravel()})
    if rows is not None:
        t = t[rows]
    if unit is not None:
        t["a"].unit = t["a_err"].unit = unit
    t.write(path, format="ascii.ecsv")
    return str(path)


def _write_text(path, a, s, rows=None):
    lines = ["i \t j \t Cov mean \t Cov std"]
    L = a.shape[0] - 1
    for n, (i, j) in enumerate((i, j) for i in range(L + 1) for j in range(L + 1)):
        if rows is None or n in rows:
            lines.append(f"{i} \t {j} \t {a[i, j]:.6e} \t {s[i, j]:.6e}")
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")
    return str(path)


def test_ecsv_amatrix_roundtrip(tmp_path):
    a, s = _amatrix()
    path = _write_ecsv(tmp_path / "a.ecsv", a, s)
    assert detect_input_kind(path) == "amatrix"
    d = read_calibration_input(path)
    assert_allclose(d.a, a, rtol=1e-15)
    assert_allclose(d.a_sigma, s, rtol=1e-15)
    assert d.a00_measured is True and d.meta["format"] == "ecsv"
    # a unit of 1 / (1000 electron) scales the values
    d2 = read_calibration_input(_write_ecsv(tmp_path / "k.ecsv", a * 1e3, s * 1e3,
                                            unit=1 / (1000 * u.electron)))
    assert_allclose(d2.a, a, rtol=1e-12)
    # no unit: per electron
    assert_allclose(read_calibration_input(_write_ecsv(tmp_path / "n.ecsv", a, s, unit=None)).a, a)
    # the serial neighbour larger than the parallel one is noted, not swapped
    d3 = read_calibration_input(_write_ecsv(tmp_path / "t.ecsv", a.T.copy(), s))
    assert_allclose(d3.a, a.T)
    assert any("check the i/j columns" in n for n in d3.notes)


def test_ecsv_amatrix_wrong_unit_and_columns(tmp_path):
    a, s = _amatrix()
    bad = _write_ecsv(tmp_path / "m.ecsv", a, s, unit=u.m)
    with pytest.raises(ValueError, match=re.escape(bad) + ": column a has unit m; accepted: per "
                                         "electron"):
        read_calibration_input(bad)
    t = Table({"i": [0], "j": [0], "value": [1e-6], "a_err": [1e-8]})
    t.write(tmp_path / "c.ecsv", format="ascii.ecsv")
    with pytest.raises(ValueError, match=r"c\.ecsv: ECSV table lacks column\(s\) \['a'\]"):
        read_calibration_input(tmp_path / "c.ecsv")


BAD_TABLES = {
    "zero error": (lambda a, s: (a, np.where(np.arange(s.size).reshape(s.shape) == 5, 0.0, s)),
                   None, r"1 a_ij error\(s\) not positive and finite \(lag: error \(1, 1\): 0\)"),
    "negative error": (lambda a, s: (a, -s), None,
                       r"16 a_ij error\(s\) not positive and finite"),
    "missing a00": (lambda a, s: (a, s), list(range(1, 16)), r"no a00 \(lag 0, 0\) row"),
}


@pytest.mark.parametrize("fmt", ["text", "ecsv"])
@pytest.mark.parametrize("case", sorted(BAD_TABLES))
def test_bad_amatrix_tables(tmp_path, fmt, case):
    change, rows, msg = BAD_TABLES[case]
    a, s = change(*_amatrix())
    path = (_write_text(tmp_path / "a.txt", a, s, rows) if fmt == "text"
            else _write_ecsv(tmp_path / "a.ecsv", a, s, rows=rows))
    with pytest.raises(ValueError, match=re.escape(path) + ": " + msg):
        read_calibration_input(path)


@pytest.mark.parametrize("lag, found", [("0.5", r"\(0\.5, 1\.0\)"), ("-1", r"\(-1\.0, 1\.0\)")])
def test_bad_lags(tmp_path, lag, found):
    text = tmp_path / "a.txt"
    text.write_text(f"i j a s\n0 0 -1e-6 1e-8\n{lag} 1 1e-7 1e-8\n")
    with pytest.raises(ValueError, match=re.escape(str(text)) + ": lags must be non-negative "
                                         r"integers \(i serial, j parallel\); found \[" + found):
        read_calibration_input(text)
    t = Table({"i": [0.0, float(lag)], "j": [0.0, 1.0], "a": [-1e-6, 1e-7], "a_err": [1e-8, 1e-8]})
    t.write(tmp_path / "a.ecsv", format="ascii.ecsv")
    with pytest.raises(ValueError, match=r"a\.ecsv: lags must be non-negative integers"):
        read_calibration_input(tmp_path / "a.ecsv")


# --------------------------------------------------------------------------- cp_pipe

def _cp_row(name, n, side, side_fit, fit_type, gain, a, a00_err=np.nan, turnoff=np.nan):
    mu = np.linspace(1000.0, 1000.0 * n, n)[::-1]  # stored unsorted
    k_i_j = np.indices((n, side, side))
    cov = mu[:, None, None] * (10.0 * k_i_j[1] + k_i_j[2] + 1.0) * 1e-3  # cov[k, i, j]
    cov[:, 0, 0] = mu / gain
    mask = np.ones(n, bool)
    mask[1] = False
    pars = np.array([a[0, 0], gain, 25.0]) if fit_type == "EXPAPPROXIMATION" else np.array([np.nan])
    perr = np.array([a00_err, 0.01, 1.0]) if fit_type == "EXPAPPROXIMATION" else np.array([np.nan])
    amat = a if fit_type == "FULLCOVARIANCE" else np.full((side_fit, side_fit), np.nan)
    return {"AMPLIFIER_NAME": name, "PTC_FIT_TYPE": fit_type, "COV_MATRIX_SIDE": side,
            "COV_MATRIX_SIDE_FULL_COV_FIT": side_fit, "INPUT_EXP_ID_PAIRS": np.arange(2 * n),
            "EXP_ID_MASK": mask, "RAW_EXP_TIMES": mu / 500.0, "RAW_MEANS": mu,
            "RAW_VARS": mu / gain, "GAIN": gain, "GAIN_ERR": 0.01, "NOISE": 5.0,
            "NOISE_ERR": 0.1, "PTC_FIT_PARS": pars, "PTC_FIT_PARS_ERROR": perr,
            "PTC_FIT_CHI_SQ": 1.0, "PTC_TURNOFF": turnoff, "A_MATRIX": amat.ravel(),
            "B_MATRIX": np.zeros(side_fit**2), "NOISE_MATRIX": np.zeros(side_fit**2),
            "COVARIANCES": cov.ravel(), "COVARIANCES_MODEL": cov.ravel(),
            "COVARIANCES_SQRT_WEIGHTS": (1.0 / (0.01 * np.abs(cov))).ravel(),
            "FINAL_MEANS": mu, "FINAL_VARS": mu / gain, "NPIXEL_COVARIANCES": 1000000}


def _write_cp(path, rows, *, bad_amps=("C10",), obstype="PTC", version=2.6, drop=()):
    """A PTC dataset FITS in cp_pipe's layout: empty primary HDU, per-amp table in HDU 1."""
    bad = np.array(bad_amps, dtype="U3")
    t = Table([{k: v for k, v in r.items() if k not in drop} | {"BAD_AMPS": bad} for r in rows])
    t.meta = {"OBSTYPE": obstype, "PTC_SCHEMA": "Gen3 Photon Transfer Curve",
              "PTC_VERSION": version, "PTC_FIT_TYPE": rows[0]["PTC_FIT_TYPE"], "DETECTOR": 94,
              "CALIBCLS": "lsst.ip.isr.ptcDataset.PhotonTransferCurveDataset"}
    with warnings.catch_warnings():  # long keys become HIERARCH cards (as in cp_pipe)
        warnings.simplefilter("ignore", fits.verify.VerifyWarning)
        hdu = fits.table_to_hdu(t)
    fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(path)
    return str(path)


@pytest.fixture
def amats():
    return {n: _amatrix(2, a00=-1e-6 * (1 + 0.1 * k))[0] for k, n in enumerate(("C00", "C01",
                                                                                  "C10"))}


def test_cp_pipe_fullcovariance(tmp_path, amats):
    rows = [_cp_row(n, 6, 4, 3, "FULLCOVARIANCE", 1.5 + 0.1 * k, amats[n], turnoff=4500.0)
            for k, n in enumerate(amats)]
    path = _write_cp(tmp_path / "ptc.fits", rows)
    assert detect_input_kind(path) == "cp_pipe"
    d = read_calibration_input(path, amp="C01")
    assert d.kind == "cp_pipe" and d.amp == "C01" and d.bad_amps == ["C10"]
    assert_allclose(d.a, amats["C01"], rtol=0)  # [serial, parallel] as stored: no transpose
    assert d.a_sigma is None and d.a00_measured is True
    assert d.gain == pytest.approx(1.6) and d.gain_err == pytest.approx(0.01)
    assert d.meta["PTC_VERSION"] == 2.6 and d.meta["CALIBCLS"].endswith("TransferCurveDataset")
    # levels 1000..6000 ADU: 2000 rejected by EXP_ID_MASK (index 1 of the reversed list is
    # 5000), 5000 and 6000 past the turn-off at 4500
    assert_allclose(d.mu, [1000.0, 2000.0, 3000.0, 4000.0])
    assert_allclose(d.var, d.mu / 1.6)
    assert_allclose(d.exptime, d.mu / 500.0)
    reasons = {p["mu"]: p["reason"] for p in d.pairs_dropped}
    assert set(reasons) == {5000.0, 6000.0}
    assert "EXP_ID_MASK" in reasons[5000.0] and "turn-off at 4500" in reasons[6000.0]
    # cov[k, i, j] from the raveled (n, M, M) column
    assert d.cov.shape == (4, 4, 4)
    assert_allclose(d.cov[:, 1, 0], d.mu * 11e-3)
    assert_allclose(d.cov[:, 0, 2], d.mu * 3e-3)
    assert_allclose(d.cov_sigma[:, 2, 1], 0.01 * d.mu * 22e-3)
    assert d.amps["C00"]["npixel_covariances"] == 1000000
    json.dumps(d.summary(), allow_nan=False)
    t = read_calibration_input(path, amp="C00", max_lag=1)
    assert t.a.shape == (2, 2) and t.cov.shape == (4, 2, 2)
    assert sum("truncated" in n for n in t.notes) == 2


def test_cp_pipe_amp_choice(tmp_path, amats):
    rows = [_cp_row(n, 5, 3, 3, "FULLCOVARIANCE", 1.5, amats[n]) for n in amats]
    path = _write_cp(tmp_path / "ptc.fits", rows)
    with pytest.raises(ValueError, match=re.escape(path) + r": 2 good amplifiers \['C00', "
                                         r"'C01'\] \(badAmps \['C10'\]\).*no errors.*amp="):
        read_calibration_input(path)
    with pytest.raises(ValueError, match=r"amplifier 'C10' is in badAmps \['C10'\]"):
        read_calibration_input(path, amp="C10")
    with pytest.raises(ValueError, match=r"no amplifier 'C99'; the file holds \['C00', 'C01', "
                                         r"'C10'\]"):
        read_calibration_input(path, amp="C99")
    # the only good amplifier is taken by default
    one = _write_cp(tmp_path / "one.fits", rows[:1], bad_amps=())
    d = read_calibration_input(one)
    assert d.amp == "C00" and d.bad_amps == []
    assert_allclose(d.a, amats["C00"])


def test_cp_pipe_expapproximation_averaged(tmp_path):
    a00 = {"C00": -1.0e-6, "C01": -1.3e-6, "C02": -9.0e-7}
    err = {"C00": 1.0e-8, "C01": 2.0e-8, "C02": 4.0e-8}
    # variable-length rows: the amplifiers have different numbers of points
    rows = [_cp_row(n, 5 + k, 3, 3, "EXPAPPROXIMATION", 1.5, np.array([[a00[n]]]), err[n])
            for k, n in enumerate(a00)]
    path = _write_cp(tmp_path / "ptc.fits", rows, bad_amps=())
    d = read_calibration_input(path)
    w = np.array([err[n] ** -2 for n in a00])
    assert_allclose(d.a, [[np.sum(w * np.array(list(a00.values()))) / w.sum()]], rtol=1e-12)
    assert_allclose(d.a_sigma, [[w.sum() ** -0.5]], rtol=1e-12)
    assert d.amp == "average of C00, C01, C02" and d.mu is None and d.gain is None
    d2 = read_calibration_input(path, amp="C02")
    assert d2.mu.size == 6  # 7 points, one rejected by EXP_ID_MASK
    assert_allclose(d2.a, [[-9.0e-7]])
    assert_allclose(d2.a_sigma, [[4.0e-8]])


def test_cp_pipe_old_version_without_full_fit_side(tmp_path, amats):
    rows = [_cp_row("C00", 5, 3, 3, "FULLCOVARIANCE", 1.5, amats["C00"])]
    path = _write_cp(tmp_path / "old.fits", rows, bad_amps=(), version=1.4,
                     drop=("COV_MATRIX_SIDE_FULL_COV_FIT", "NPIXEL_COVARIANCES"))
    d = read_calibration_input(path)
    assert_allclose(d.a, amats["C00"])
    assert d.amps["C00"]["cov_matrix_side_full_cov_fit"] == 3


def test_not_a_cp_pipe_dataset(tmp_path, amats):
    rows = [_cp_row("C00", 5, 3, 3, "FULLCOVARIANCE", 1.5, amats["C00"])]
    wrong = _write_cp(tmp_path / "bfk.fits", rows, obstype="BFK")
    with pytest.raises(ValueError, match=re.escape(wrong) + r": not a cp_pipe PTC dataset .*"
                                         r"'Gen3 Photon Transfer Curve'.*OBSTYPE = 'PTC'.*; "
                                         r"found OBSTYPE = 'BFK'"):
        read_calibration_input(wrong)
    short = _write_cp(tmp_path / "short.fits", rows, drop=("A_MATRIX", "RAW_VARS"))
    with pytest.raises(ValueError, match=re.escape(short) + r": not a cp_pipe PTC dataset.*"
                                         r"missing \['RAW_VARS', 'A_MATRIX'\]"):
        read_calibration_input(short)
    assert set(CP_PIPE_COLUMNS) <= set(rows[0]) | {"BAD_AMPS"}


# --------------------------------------------------------------------------- detection and mixing

def test_mixing_kinds_is_an_error(tmp_path, rng):
    flat = _write_flat(tmp_path / "flat.fits", _flat(rng, 500.0))
    with pytest.raises(ValueError, match=r"inputs of different kinds in one call \(flats, ptc, "
                                         r"amatrix\):.*flat\.fits: flats.*eotest.*: ptc"):
        read_calibration_input([flat, EOTEST, ITL])
    copy = tmp_path / "copy.txt"
    with open(EOTEST) as fh:
        copy.write_text(fh.read())
    with pytest.raises(ValueError, match=r"copy\.txt: only one ptc file can be read at a time"):
        read_calibration_input([EOTEST, copy])
    with pytest.raises(ValueError, match=r"amp='C00' given, but the input is amatrix"):
        read_calibration_input(ITL, amp="C00")


def test_unrecognised_files(tmp_path):
    three = tmp_path / "three.txt"
    three.write_text("1 2 3\n4 5 6\n")
    with pytest.raises(ValueError, match=r"three\.txt: text file with 3 numeric columns; "
                                         r"accepted are 2 columns"):
        read_calibration_input(three)
    blob = tmp_path / "blob.bin"
    blob.write_bytes(bytes(range(128, 256)))
    with pytest.raises(ValueError, match=r"blob\.bin: neither FITS nor text"):
        read_calibration_input(blob)
    with pytest.raises(FileNotFoundError, match=r"nothere\.fits: no such file"):
        read_calibration_input(tmp_path / "nothere.fits")
    empty = tmp_path / "empty.fits"
    fits.PrimaryHDU().writeto(empty)
    with pytest.raises(ValueError, match=r"empty\.fits: FITS file with neither a 2-d image HDU"):
        read_calibration_input(empty)


def test_a_refusal_on_many_flats_names_the_directory_and_the_count(tmp_path):
    """Issue 41: a refusal on 80 flats names their directory and count, and groups
    the dropped files by reason, instead of printing 80 paths."""
    from lsst_bfdrift.ptc.data import describe_paths
    from lsst_bfdrift.ptc.inputs import read_flat_pairs

    rng = np.random.default_rng(2)
    d = tmp_path / "flats"
    d.mkdir()
    paths = []
    for k in range(80):  # every flat at its own EXPTIME: no pair anywhere
        hdr = fits.Header({"EXPTIME": 1.0 + k, "BUNIT": "adu"})
        p = d / f"flat_{k:03d}.fits"
        fits.PrimaryHDU(rng.poisson(1000.0, (16, 16)).astype(np.float32), header=hdr).writeto(p)
        paths.append(str(p))
    with pytest.raises(ValueError) as info:
        read_flat_pairs(paths, drop_single=True)
    msg = str(info.value)
    assert msg.startswith(f"{d}/ (80 files): 0 distinct signal level(s) with a pair of flats")
    assert "dropped 80 for the same reason (" in msg and "(80 files)" in msg
    assert msg.count("flat_0") <= 2 and len(msg) < 700
    assert describe_paths(paths[:3]) == ", ".join(paths[:3])
    other = [str(tmp_path / "x.fits")] + paths[:5]
    assert describe_paths(other) == f"{other[0]} ... (6 files in 2 directories)"


# --------------------------------------------------------------------------- issue 44

def test_amatrix_of_a00_alone_is_read(tmp_path):
    """Issue 44 item 1: a table of the a00 row alone (a header and one row) is read,
    with nothing to orient and no sum rule to check, instead of ending in an
    IndexError; calibrate's a-matrix is then a00 alone, as from a PTC."""
    from lsst_bfdrift.calibration.tuning import measured_acoeffs
    from lsst_bfdrift.ptc.acoeffs import read_acoeff_table

    path = tmp_path / "a00.txt"
    path.write_text("i j a sigma\n0 0 -1.333030e-06 1.334e-07\n")
    before = _digest([path])
    d = read_calibration_input(path)
    assert d.kind == "amatrix" and d.a.shape == (1, 1) and d.a00_measured is True
    assert_allclose(d.a, [[-1.333030e-06]], rtol=1e-15)
    assert_allclose(d.a_sigma, [[1.334e-07]], rtol=1e-15)
    assert "a00 only: no nearest neighbours, nothing to orient" in d.notes
    assert any("alone: no other lag to check the sum rule" in n for n in d.notes)
    table = measured_acoeffs(d)
    assert table.mask().tolist() == [[True]]
    t = read_acoeff_table(path)
    assert_allclose(t.a, d.a, rtol=1e-15)
    assert not t.exclude_a00
    assert _digest([path]) == before  # the input is never modified


@pytest.mark.parametrize("text, line, field", [
    ("0 0 -1.333e-06 x\n0 1 1e-7 1e-8\n1 0 5e-8 1e-8\n1 1 2e-8 1e-8\n", 1, "4 ('x')"),
    ("i j a sigma\n0 0 -1.333e-06 1e-7\n0 1 1e-7 1e-8,\n1 0 5e-8 1e-8q\n", 4, "4 ('1e-8q')"),
    ("100 x\n200 400\n300 600\n", 1, "2 ('x')"),
])
def test_malformed_row_is_named_not_taken_for_a_header(tmp_path, text, line, field):
    """Issue 44 item 8: a row mixing numbers and another field is malformed, named by
    its line and field (not skipped as a header, which made the error say that the
    a00 row was missing); a header has no number in it."""
    from lsst_bfdrift.ptc.acoeffs import read_acoeff_table

    path = tmp_path / "t.txt"
    path.write_text(text)
    msg = re.escape(f"{path}:{line}: field {field} of the row ") + r".*is not a number"
    with pytest.raises(ValueError, match=msg) as info:
        read_calibration_input(path)
    assert "a00" not in str(info.value)
    if text.startswith("0 0"):
        with pytest.raises(ValueError, match=msg + r".*malformed row, not a header"):
            read_acoeff_table(path)
    # a header line (no number in it) is still a header, for both text kinds
    path.write_text("lag_i lag_j a sigma\n" + text.replace(" x\n", " 1e-7\n").replace(
        "q\n", "\n").replace(",\n", "\n").replace("i j a sigma\n", ""))
    kind = detect_input_kind(path)
    assert kind == ("ptc" if text.startswith("100") else "amatrix")


def test_a_pair_of_one_exposure_twice_is_excluded_and_named(tmp_path, rng):
    """Issue 44 item 9: a pair whose second file is a copy of the first (zero
    difference variance) is excluded and named with its reason before the turn-off
    is sought: the brighter pairs stay, none is dropped as past a turn-off. Two
    constant images are saturation above every other pair (the turn-off below them),
    and are excluded, not taken for saturation, below brighter pairs."""
    import shutil

    from lsst_bfdrift.ptc.covariances import identical_flats

    levels = {1.0: 500.0, 2.0: 1000.0, 4.0: 2000.0, 8.0: 4000.0, 16.0: 8000.0}
    paths = _flat_set(tmp_path, rng, levels)
    shutil.copyfile(paths[2], paths[3])  # the pair at 2 s: one exposure twice
    for t, value in ((32.0, 60000.0), (3.0, 1500.0)):  # constant pairs
        for k in range(2):
            paths.append(_write_flat(tmp_path / f"flat_const_{t:04.1f}_{k}.fits",
                                     np.full(SHAPE, value), exptime=t))
    before = _digest(paths)
    d = read_calibration_input(paths, max_lag=1, min_pixels=500)
    assert _digest(paths) == before
    assert_allclose(d.exptime, [1.0, 4.0, 8.0, 16.0])  # the brighter pairs all kept
    assert d.turnoff == d.mu[-1]  # below the saturated pair, not below the copy
    copy, low, sat = d.pairs_dropped
    assert copy["files"] == paths[2:4] and copy["exptime"] == 2.0
    assert copy["reason"].startswith("the two images are one exposure (identical pixel for "
                                     "pixel after scaling to one mean: zero difference "
                                     "variance), e.g. a copied file")
    assert "turn-off" not in copy["reason"]
    assert sat["files"] == paths[-4:-2] and sat["reason"].startswith(
        f"past the PTC turn-off at {d.turnoff:.6g} adu: both images are constant (60000 and "
        "60000: zero difference variance): saturation")
    assert low["files"] == paths[-2:] and low["reason"].endswith(
        "below brighter pairs, so not saturation: pair excluded")
    assert "1 pair(s) of one exposure twice (zero difference variance) excluded" in d.notes[0]
    # the check itself: a scaled copy is one exposure too; two exposures are not
    a, b = _flat(rng, 500.0), _flat(rng, 500.0)
    assert identical_flats(a, 1.5 * a)[0] == "copies"
    assert identical_flats(a, b) is None
    assert identical_flats(np.full(SHAPE, 7.0), np.full(SHAPE, 7.0))[0] == "constant"
    a[0, 0] = np.nan
    assert identical_flats(a, a.copy(), mask=np.zeros(SHAPE, bool))[0] == "copies"


# --------------------------------------------------------------------------- issue 43 item 1

def test_levels_not_proportional_to_exptime_are_said_at_once(tmp_path, rng):
    """Flats whose levels do not follow their EXPTIME (here: times 1, 2, 3, 4 s
    for levels 500 to 4000 ADU) are said when read, naming the files and levels,
    before any fit; the data are still returned."""
    from lsst_bfdrift.ptc.inputs import ExposureLevelWarning
    paths = _flat_set(tmp_path, rng, levels={1.0: 500.0, 2.0: 1000.0, 3.0: 2000.0,
                                             4.0: 4000.0})
    with pytest.warns(ExposureLevelWarning, match=r"not proportional to EXPTIME: 2 of 4 "
                      r"pair\(s\).*flat_001\.0_0\.fits, flat_001\.0_1\.fits: EXPTIME 1 s, "
                      r"level 49\d(\.\d+)? \(49\d(\.\d+)? per s\);.*flat_004\.0_0\.fits, "
                      r"flat_004\.0_1\.fits: EXPTIME 4 s, level 4\d+(\.\d+)? \(\d+(\.\d+)? "
                      r"per s\) <-"):
        d = read_calibration_input(paths, max_lag=1, min_pixels=500)
    assert any("not proportional to EXPTIME" in n for n in d.notes)
    assert d.mu.size == 4


def test_exptime_level_problem_tolerates_a_shutter_delay():
    from lsst_bfdrift.ptc.inputs import exptime_level_problem
    t = np.array([0.5, 1.0, 2.0, 4.0, 8.0])
    files = [[f"f{k}a", f"f{k}b"] for k in range(5)]
    assert exptime_level_problem(t, 1000.0 * (t + 0.02), files) is None  # 20 ms: 4 % at 0.5 s
    assert "f0a, f0b" in exptime_level_problem(t, 1000.0 * (t + 0.2), files)
    assert exptime_level_problem(t, 1000.0 * 1.5 ** np.arange(5), files) is not None


def test_reading_flats_reports_progress_from_the_start(tmp_path, rng):
    """progress(done, total): first (0, total) before any file is read, then
    never back, ending at total."""
    paths = _flat_set(tmp_path, rng)
    calls = []
    read_calibration_input(paths, max_lag=1, min_pixels=500,
                           progress=lambda done, total: calls.append((done, total)))
    assert calls[0][0] == 0 and calls[-1][0] == calls[-1][1]
    fractions = [d / t for d, t in calls]
    assert fractions == sorted(fractions) and len(calls) >= len(paths)
