"""Tests of lsst_bfdrift.ptc.covariances: FFT covariances, Astier models and fits."""

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose

from lsst_bfdrift.ptc.covariances import (fit_ptc_exponential, measure_ptc, pair_covariances,
                                          ptc_exponential_model, read_ptc_text)
from lsst_bfdrift.utils.errors import InputError

MEASURED = "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt"


def _direct_cov(d, w, di, dj):
    """Real-space mean product over valid pairs separated by (+di, +dj)."""
    ny, nx = d.shape
    a = d[:ny - dj, :nx - di] * w[:ny - dj, :nx - di]
    b = d[dj:, di:] * w[dj:, di:]
    n = (w[:ny - dj, :nx - di] * w[dj:, di:]).sum()
    return (a * b).sum(), n


@pytest.mark.parametrize("border", [0, 6])
def test_fft_covariances_equal_real_space_sums(rng, border):
    """Against direct real-space sums; with a border, over the pixels inside it."""
    f1 = rng.normal(1000.0, 30.0, (60, 70))
    f2 = rng.normal(1000.0, 30.0, (60, 70))
    f1[0, :] += 500.0  # an edge row that only the border removes
    mask = rng.random((60, 70)) < 0.05
    pc = pair_covariances(f1, f2, max_lag=3, mask=mask, nsig=50.0, min_pixels=100,
                          border=border)
    if border:
        assert pc.nmasked == mask.sum()  # masked pixels counted, the border itself not
        mask = mask.copy()
        mask[:border] = mask[-border:] = True
        mask[:, :border] = mask[:, -border:] = True
    mu1, mu2 = f1[~mask].mean(), f2[~mask].mean()
    diff = f1 - f2 * mu1 / mu2
    d = np.where(mask, 0.0, diff - diff[~mask].mean())
    w = (~mask).astype(float)
    for di in range(4):
        for dj in range(4):
            s1, n1 = _direct_cov(d, w, di, dj)
            # (di, -dj): flip rows
            s2, n2 = _direct_cov(d[::-1], w[::-1], di, dj)
            assert_allclose(pc.cov[di, dj], 0.5 * (s1 + s2) / (n1 + n2), rtol=1e-9)
            assert pc.npix[di, dj] == (n1 + n2) // 2
    assert pc.mu == pytest.approx(0.5 * (mu1 + mu2))


def test_poisson_flats_have_variance_mu_over_gain(rng):
    gain = 1.7
    pairs = [(rng.poisson(m * gain, (200, 200)) / gain, rng.poisson(m * gain, (200, 200)) / gain)
             for m in (500.0, 2000.0, 8000.0)]
    t = measure_ptc(pairs, max_lag=2)
    assert_allclose(t["cov"][:, 0, 0], t["mu"] / gain, rtol=0.02)
    assert np.all(np.abs(t["cov"][:, 1, 0]) < 0.02 * t["mu"] / gain)


def test_sigma_clipping_masks_cosmic_rays(rng):
    f1 = rng.normal(1000.0, 30.0, (100, 100))
    f2 = rng.normal(1000.0, 30.0, (100, 100))
    f1[50, 50] = 1e6
    pc = pair_covariances(f1, f2, max_lag=1)
    assert pc.nmasked >= 1
    # var(flat) = 30^2; the cosmic ray neither inflates it nor biases the scaling
    assert pc.cov[0, 0] == pytest.approx(900.0, rel=0.05)


@pytest.mark.parametrize("kw, match", [
    (dict(flat1=np.ones((5, 5)), flat2=np.ones((5, 6))), "equal shape"),
    (dict(flat1=np.ones((50, 50)), flat2=np.ones((50, 50)), max_lag=60), "too large"),
    (dict(flat1=-np.ones((50, 50)), flat2=np.ones((50, 50)), min_pixels=10), "positive"),
    (dict(flat1=np.full((20, 20), np.nan), flat2=np.ones((20, 20))), "valid pixels"),
])
def test_bad_pairs(kw, match):
    with pytest.raises(ValueError, match=match):
        pair_covariances(**kw)


def test_turnoff():
    from lsst_bfdrift.ptc.covariances import ptc_turnoff
    mu = np.array([1.0, 2.0, 3.0, 4.0, 5.0])
    assert ptc_turnoff(mu, [1.0, 2.0, 3.0, 1.0, 5.0]) == 3.0
    assert ptc_turnoff(mu, mu) == np.inf


def test_exponential_fit_recovers_synthetic(rng):
    mu = np.geomspace(100, 1.2e5, 40)
    var = ptc_exponential_model(mu, 0.9, -2.5e-6, 30.0) * (1 + rng.normal(0, 0.003, mu.size))
    r = fit_ptc_exponential(mu, var)
    assert r["gain"] == pytest.approx(0.9, abs=3 * r["gain_err"] + 1e-4)
    assert r["a00"] == pytest.approx(-2.5e-6, abs=3 * r["a00_err"])


def test_measured_e2v_ptc():
    """eotest's own analysis: gain 0.7713 e/ADU, |a00| = 2.68e-6."""
    mu, var = read_ptc_text(MEASURED)
    r = fit_ptc_exponential(mu, var)
    assert r["mu_max"] == pytest.approx(158970.0)  # saturation cut, from the data
    assert r["gain"] == pytest.approx(0.7713, rel=0.01)
    assert abs(r["a00"]) == pytest.approx(2.68e-6, rel=0.1)
    assert r["a00"] < 0
    assert r["gain_err"] < 0.01 and r["a00_err"] < 3e-7


def test_static_term_equals_direct_sums_and_finds_a_common_pattern():
    """S_ij = (Cov(f1 + f2) - Cov(f1 - f2)) / 4 from the FFT estimator equals
    direct numpy sums over the valid pixel pairs (a mask included), and
    measures mu^2 times the variance of a response pattern common to both
    flats (zero without one)."""
    from lsst_bfdrift.ptc.covariances import pair_covariances

    rng = np.random.default_rng(7)
    shape, mu = (120, 100), 2e4
    pattern = rng.normal(0, 3e-3, shape)
    f1 = rng.poisson(mu * (1 + pattern)).astype(float)
    f2 = rng.poisson(mu * (1 + pattern)).astype(float)
    mask = np.zeros(shape, bool)
    mask[10:14, 20:60] = True
    pc = pair_covariances(f1, f2, max_lag=2, mask=mask, nsig=50.0, min_pixels=100, static=True,
                          border=0)
    # direct reference over the same pixels
    ok = ~mask
    m1, m2 = f1[ok].mean(), f2[ok].mean()
    s = np.where(ok, f1 + f2 * m1 / m2, 0.0)
    d = np.where(ok, f1 - f2 * m1 / m2, 0.0)
    s[ok] -= s[ok].mean()
    d[ok] -= d[ok].mean()

    def lagged(x, di, dj):
        num = den = 0.0
        for sgn in (1, -1) if dj else (1,):
            a = x[max(0, -sgn * dj):x.shape[0] - max(0, sgn * dj), :x.shape[1] - di]
            b = x[max(0, sgn * dj):x.shape[0] - max(0, -sgn * dj) or None, di:]
            wa = ok[max(0, -sgn * dj):x.shape[0] - max(0, sgn * dj), :x.shape[1] - di]
            wb = ok[max(0, sgn * dj):x.shape[0] - max(0, -sgn * dj) or None, di:]
            num += (a * b).sum()
            den += (wa & wb).sum()
            if dj == 0:
                num, den = 2 * num, 2 * den  # (i, 0) counted once per sign, as the estimator
        return num / den

    for di in range(3):
        for dj in range(3):
            ref = (lagged(s, di, dj) - lagged(d, di, dj)) / 4.0
            assert_allclose(pc.static[di, dj], ref, rtol=1e-9, atol=1e-9 * mu)
            assert_allclose(pc.cov[di, dj], 0.5 * lagged(d, di, dj), rtol=1e-9, atol=1e-9 * mu)
    assert_allclose(pc.static[0, 0], mu**2 * 9e-6, rtol=0.1)
    clean = pair_covariances(rng.poisson(mu, shape).astype(float),
                             rng.poisson(mu, shape).astype(float), max_lag=1, static=True)
    assert abs(clean.static[0, 0]) < 0.02 * mu
    assert pair_covariances(f1, f2, max_lag=1).static is None


def _flat(path, level, rng, exptime=None, shape=(40, 40)):
    hdu = fits.PrimaryHDU(rng.poisson(level, shape).astype(float))
    if exptime is not None:
        hdu.header["EXPTIME"] = exptime
    hdu.writeto(path)
    return str(path)


def test_pair_with_different_exptime_or_shape_is_refused(tmp_path):
    """F2: the two flats of a pair must match (EXPTIME within 1e-3, shape)."""
    from lsst_bfdrift.ptc.covariances import read_flat_pair
    rng = np.random.default_rng(2)
    a = _flat(tmp_path / "a.fits", 1000, rng, exptime=1.0)
    b = _flat(tmp_path / "b.fits", 2000, rng, exptime=2.0)
    c = _flat(tmp_path / "c.fits", 1000, rng, exptime=1.0005)
    d = _flat(tmp_path / "d.fits", 1000, rng, exptime=1.0, shape=(40, 30))
    e = _flat(tmp_path / "e.fits", 1000, rng)
    with pytest.raises(InputError, match="a.fits and .*b.fits: EXPTIME 1.0 and 2.0 differ"):
        measure_ptc([(a, b)], max_lag=1)
    with pytest.raises(InputError, match="a.fits and .*d.fits: shapes"):
        measure_ptc([(a, d)], max_lag=1)
    with pytest.raises(InputError, match="only one"):
        read_flat_pair(a, e)
    assert read_flat_pair(a, c)[0].shape == (40, 40)  # within the tolerance


@pytest.mark.parametrize("mu, var, match", [
    (np.full(6, 1000.0), np.full(6, 700.0), "1 distinct signal level"),
    (np.repeat([1000.0, 2000.0], 3), np.repeat([700.0, 1400.0], 3), "2 distinct"),
    (np.geomspace(100, 1e5, 8) * 1e-300, np.geomspace(100, 1e5, 8) * 1e-300, "range"),
    (np.geomspace(100, 1e5, 8) * 1e200, np.geomspace(100, 1e5, 8) * 1e200, "range"),
])
def test_degenerate_ptc_is_refused(mu, var, match):
    """F5: identical points or one level are refused, not fitted with zero error;
    extreme values give a clear error, not LinAlgError."""
    with pytest.raises(InputError, match=match):
        fit_ptc_exponential(mu, var)


def test_ptc_text_reader_names_the_file(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("1 2\nx y\n")
    with pytest.raises(InputError, match=r"bad.txt:2: field 1 \('x'\) of the row 'x y' is not "
                                         r"a number \(a line of text among the rows"):
        read_ptc_text(p)
    p.write_text("# nothing\n")
    with pytest.raises(InputError, match="bad.txt: no PTC rows"):
        read_ptc_text(p)


def test_ptc_text_with_a_third_column_is_refused(tmp_path):
    """Issue 44 item 7: a third column (an error of the variance, say) is refused with
    the file, the line and what is accepted, not dropped without a word; a header
    line is allowed."""
    p = tmp_path / "three.txt"
    p.write_text("".join(f"{m} {m / 2} {m / 100}\n" for m in (100, 200, 400, 800, 1600)))
    with pytest.raises(InputError, match=r"three\.txt:1: 3 column\(s\); accepted: two numeric "
                                         r"columns \(mean ADU, variance ADU\^2\).*a third "
                                         r"column, e\.g\. an error of the variance, is not read"):
        read_ptc_text(p)
    p.write_text("mean variance\n200 100\n100 50\n")
    mu, var = read_ptc_text(p)
    assert_allclose(mu, [100.0, 200.0])
    assert_allclose(var, [50.0, 100.0])
