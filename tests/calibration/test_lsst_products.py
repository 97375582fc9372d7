"""Tests of LSST's product files (lsst_bfdrift.calibration.lsst_products) and of
rigid-edge templates (lsst_bfdrift.templates.edge_shifts).

Kinds: round trips (write then read) check consistency; the kernel template
is checked against numpy's discrete Laplacian of the kernel (an independent
reference) and the edge-shift template against the swept areas the shifts
define; files of another OBSTYPE or schema version, written by hand with
astropy, check the refusals.
"""

import numpy as np
import pytest
from astropy.io import fits
from astropy.table import Table
from numpy.testing import assert_allclose

from lsst_bfdrift.calibration import lsst_products as P
from lsst_bfdrift.calibration.astier23_model import Astier23Parameters, astier23_shifts
from lsst_bfdrift.correction.solvers import area_coefficients, coulton18_kernel
from lsst_bfdrift.templates.edge_shifts import (template_edge_shifts, template_from_edge_shifts,
                                                template_from_kernel)
from lsst_bfdrift.templates.swept import swept_area_kernels
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.utils.errors import InputFileError, OutputExistsError


def _laplacian(k):
    p = np.pad(k, 1, mode="edge")
    return p[1:-1, 2:] + p[1:-1, :-2] + p[2:, 1:-1] + p[:-2, 1:-1] - 4 * k


def test_kernel_template_area_is_the_kernels_laplacian():
    rng = np.random.default_rng(3)
    k = rng.normal(0.0, 1e-8, (9, 9))
    k = k + k[::-1] + k[:, ::-1] + k[::-1, ::-1]
    t = template_from_kernel(k)
    kv, kh = swept_area_kernels(t)
    area = (kv[:, 1:] - kv[:, :-1] + kh[1:, :] - kh[:-1, :]) / t.charge
    assert_allclose(area, _laplacian(k), rtol=1e-9, atol=1e-22)


def test_edge_shift_template_sweeps_the_shifts_and_gives_them_back():
    shifts = astier23_shifts(Astier23Parameters(alpha=-2e-7), 6)
    t = template_from_edge_shifts(*shifts)
    assert t.size == 15
    back = template_edge_shifts(t, 6)
    for a, b in zip(shifts, back):
        assert_allclose(b, a, rtol=1e-9, atol=1e-20)
    # the template's linear area response is the sum of the four shifts
    kv, kh = swept_area_kernels(t)
    c = t.center
    area = (kv[:, 1:] - kv[:, :-1] + kh[1:, :] - kh[:-1, :]) / t.charge
    assert_allclose(area[c, c], sum(s[0, 0] for s in shifts), rtol=1e-9)
    assert_allclose(area[c + 1, c + 2], sum(s[2, 1] for s in shifts), rtol=1e-9)


def test_distortion_matrix_round_trip(tmp_path):
    shifts = astier23_shifts(Astier23Parameters(alpha=-2e-7), 5)
    a = np.arange(36.0).reshape(6, 6) * 1e-9
    m = P.DistortionMatrix(a_matrix=a, a_sigma=a + 1e-10, a_model=a * 0.9, shifts=shifts,
                           fit_params={"alpha": -2e-7, "z_q": 0.25}, free_params=["alpha"],
                           fit_errors={"alpha": 1e-9, "z_q": 0.0}, chi2=3.0, reduced_chi2=1.5,
                           covariance=np.array([[1e-18]]), gain={"C00": 1.5, "C01": 1.6},
                           filters={"r_57": shifts})
    path = tmp_path / "dm.fits"
    P.write_distortion_matrix(path, m)
    with fits.open(path) as h:
        assert h[1].header["OBSTYPE"] == "BF_DISTORTION_MATRIX"
        assert h[1].header["BF_DISTORTION_MATRIX_VERSION"] == 1.1
    r = P.read_distortion_matrix(path)
    assert_allclose(r.a_matrix, a)
    for x, y in zip(r.shifts, shifts):
        assert_allclose(x, y)
    assert r.fit_params == pytest.approx(m.fit_params) and r.free_params == ["alpha"]
    assert r.gain == pytest.approx(m.gain) and list(r.filters) == ["r_57"]
    t = r.template(band="r_57")
    assert t.meta["method"] == "astier23"
    with pytest.raises(OutputExistsError):
        P.write_distortion_matrix(path, m)
    with pytest.raises(ValueError, match="filter 'g' is not in this distortion matrix"):
        r.template(band="g")


def test_bfk_round_trip_and_template(tmp_path):
    tpl = load_default_template()
    k = coulton18_kernel(area_coefficients(tpl))
    path = tmp_path / "bfk.fits"
    P.write_bfk(path, k, gain=1.4)
    r = P.read_bfk(path)
    assert_allclose(r.kernel, k)
    t = r.template()
    assert_allclose(area_coefficients(t), area_coefficients(tpl), rtol=0,
                    atol=2e-3 * abs(area_coefficients(tpl)).max())


@pytest.mark.parametrize("reader, obstype, version, match", [
    (P.read_distortion_matrix, "BF_DISTORTION_MATRIX", 2.0, "schema version 2; this "
                                                            "lsst_bfdrift reads versions 1, 1.1"),
    (P.read_distortion_matrix, "bfk", 1.1, "OBSTYPE = 'bfk'; an LSST electroBfDistortionMatrix"),
    (P.read_bfk, "bfk", "x", "bfk_VERSION = 'x' is not a schema version"),
    (P.read_bfk, "PTC", 1.1, "OBSTYPE = 'PTC'; an LSST brighter-fatter kernel"),
])
def test_other_schemas_are_refused(tmp_path, reader, obstype, version, match):
    t = Table([{"A": 1.0}])
    t.meta = {"OBSTYPE": obstype, f"{obstype}_VERSION": version}
    path = tmp_path / "other.fits"
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fits.HDUList([fits.PrimaryHDU(), fits.table_to_hdu(t)]).writeto(path)
    with pytest.raises(InputFileError, match=match):
        reader(path)
    fits.PrimaryHDU(np.zeros((3, 3))).writeto(tmp_path / "image.fits")
    with pytest.raises(InputFileError, match="no binary table HDU"):
        reader(tmp_path / "image.fits")


def test_rigid_templates_survive_a_save(tmp_path):
    """A rigid-edge template (corners means of three edges) is saved and loaded back
    bit for bit: its checksum holds."""
    from lsst_bfdrift.templates.template import DistortionTemplate
    rng = np.random.default_rng(1)
    k = rng.normal(0, 1e-8, (7, 7))
    t = template_from_kernel(k + k[::-1] + k[:, ::-1] + k[::-1, ::-1])
    t.save(tmp_path / "t.fits")
    back = DistortionTemplate.load(tmp_path / "t.fits")
    assert np.array_equal(back.corner_d, t.corner_d) and np.array_equal(back.vedge_d, t.vedge_d)
