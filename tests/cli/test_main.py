"""Tests of the bfdrift command line (run in-process through main())."""

import json
import os
import pathlib

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.templates.template import DistortionTemplate, load_default_template


#: A header that says the image is in electrons (the unit rule).
ELECTRONS = fits.Header({"BUNIT": "electron"})


def _run(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_summary_of_default_template(capsys):
    code, out, _ = _run(capsys, "template", "summary", "--json")
    assert code == 0
    s = json.loads(out)
    ref = load_default_template().summary()
    for key in ("A00", "A01", "A10", "A11", "ratio_01_10", "area_sum_error",
                "aggressor_charge"):
        assert s[key] == pytest.approx(ref[key], rel=1e-12)
    assert s["ratio_01_10"] == pytest.approx(np.log(s["A01"]) / np.log(s["A10"]))


def test_build_from_config_then_summary_and_plot(capsys, tmp_path):
    cfg = tmp_path / "cfg.toml"
    cfg.write_text('[sensor]\nchannel_depth = 3.0\n[template]\nsize = 3\nedge_samples = 2\n'
                   'tol = 1e-3\nworkers = 1\n')
    out_file = tmp_path / "t.fits"
    code, out, err = _run(capsys, "template", "build", "--out", str(out_file), "--config",
                          str(cfg), "--json")
    assert code == 0, err
    s = json.loads(out)
    t = DistortionTemplate.load(out_file)
    assert t.meta["params"]["channel_depth"] == 3.0
    assert s["size"] == 3 and s["A00"] == t.summary()["A00"]
    assert "template" in err  # progress bar on stderr
    png = tmp_path / "t.png"
    code, out, _ = _run(capsys, "template", "plot", str(out_file), "--out", str(png))
    assert code == 0 and png.read_bytes()[:4] == b"\x89PNG"
    code, _, err = _run(capsys, "template", "build", "--out", str(out_file), "--quiet")
    assert code == 3 and "exists" in err


def test_import_galsim(capsys, tmp_path):
    out_file = tmp_path / "itl.fits"
    code, out, _ = _run(capsys, "template", "import-galsim", "lsst_itl_50_8", "--out",
                        str(out_file), "--json")
    assert code == 0
    s = json.loads(out)
    assert s["aggressor_charge"] == 1e5 and s["size"] == 9


def test_maps_on_sample(capsys, tmp_path):
    out_file = tmp_path / "maps.fits"
    code, out, _ = _run(capsys, "maps", "--json", "--quiet", "--out", str(out_file))
    assert code == 0
    s = json.loads(out)
    assert s["shape"] == [64, 64] and s["area_min"] < 0.98 < 1.0 < s["area_max"]
    with fits.open(out_file) as hdul:
        assert [h.name for h in hdul[1:]] == ["AREA", "DX", "DY", "IXX", "IYY", "IXY", "E1",
                                               "E2"]
        assert hdul["AREA"].data.min() == pytest.approx(s["area_min"])


def test_maps_with_resampled_edges(capsys, tmp_path):
    """--samples 8 gives the full maps to ~1e-5 of their signal and records
    the sample count; nonsense values are refused."""
    full, fast = tmp_path / "full.fits", tmp_path / "fast.fits"
    assert _run(capsys, "maps", "--quiet", "--json", "--out", str(full))[0] == 0
    code, out, _ = _run(capsys, "maps", "--quiet", "--json", "--samples", "8", "--out",
                        str(fast))
    assert code == 0 and json.loads(out)["edge_samples"] == 8
    with fits.open(full) as a, fits.open(fast) as b:
        assert b[0].header["BFGSAMP"] == 8 and a[0].header["BFGSAMP"] == 32
        signal = np.abs(a["AREA"].data - 1.0).max()
        assert np.abs(b["AREA"].data - a["AREA"].data).max() < 1e-3 * signal
    code, _, err = _run(capsys, "maps", "--quiet", "--samples", "0")
    assert code == 2 and "samples" in err


def test_maps_masks_nan_pixels(capsys, tmp_path):
    img = np.full((20, 20), 1000.0)
    img[10, 10] = 5e4
    img[3, 4] = np.nan
    path = tmp_path / "img.fits"
    fits.PrimaryHDU(img, header=ELECTRONS).writeto(path)
    code, out, _ = _run(capsys, "maps", str(path), "--json", "--quiet")
    assert code == 0 and json.loads(out)["masked_pixels"] == 1
    with fits.open(path) as hdul:
        assert np.isnan(hdul[0].data[3, 4])  # input file untouched


@pytest.mark.parametrize("argv, match", [
    (["template", "summary", "/nonexistent/t.fits"], "does not exist"),
    (["maps", "--gain", "-1", "--quiet"], "gain"),
])
def test_errors_are_reported(capsys, argv, match):
    code, _, err = _run(capsys, *argv)
    assert code == 2 and match in err


@pytest.mark.parametrize("gain", ["0", "nan", "-1", "inf"])
def test_bad_gain_is_one_usage_error(capsys, tmp_path, gain):
    """--gain 0 and --gain nan are the same mistake: exit 2 before any file is read."""
    from lsst_bfdrift.cli.main import EXIT_INPUT, sample_image_path
    out_file = tmp_path / "corr.fits"
    code, _, err = _run(capsys, "correct", sample_image_path(), str(out_file), "--gain", gain,
                        "--quiet")
    assert code == EXIT_INPUT == 2 and "gain" in err and not out_file.exists()
    code, _, err = _run(capsys, "maps", "--gain", gain, "--quiet")
    assert code == 2 and "gain" in err


def test_exit_codes_follow_the_error_kind():
    from lsst_bfdrift.cli.main import exit_code
    from lsst_bfdrift.utils import errors
    assert exit_code(errors.InputError("x")) == 2
    assert exit_code(errors.InputNotFoundError("x", "f")) == 2
    assert exit_code(FileNotFoundError(2, "No such file", "f")) == 2
    assert exit_code(errors.OutputExistsError("x")) == 3
    assert exit_code(errors.FitError("x")) == 4
    assert exit_code(errors.ComputationError("x")) == 4
    assert exit_code(PermissionError(13, "Permission denied")) == 1
    assert exit_code(errors.BfdriftError("x")) == 1


def test_only_package_errors_and_oserror_are_caught(capsys, monkeypatch):
    """A bug (any other exception) keeps its traceback; a package error does not."""
    from lsst_bfdrift.cli import template_commands as cli  # build_parser() reads it per call
    from lsst_bfdrift.utils.errors import FitError

    def boom(args):
        raise ZeroDivisionError("a bug")
    monkeypatch.setattr(cli, "cmd_template_summary", boom)
    with pytest.raises(ZeroDivisionError, match="a bug"):
        main(["template", "summary"])

    def fit_fails(args):
        raise FitError("poor fit")
    monkeypatch.setattr(cli, "cmd_template_summary", fit_fails)
    assert _run(capsys, "template", "summary")[:3:2] == (4, "bfdrift: error: poor fit\n")


def test_unknown_config_key(capsys, tmp_path):
    cfg = tmp_path / "cfg.json"
    cfg.write_text(json.dumps({"sensor": {"thickness": 100, "bogus": 1}}))
    code, _, err = _run(capsys, "template", "build", "--out", str(tmp_path / "x.fits"),
                        "--config", str(cfg))
    assert code == 2 and "bogus" in err


def test_ptc_on_measured_text_file(capsys):
    code, out, _ = _run(capsys, "ptc", "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt",
                        "--json")
    assert code == 0
    s = json.loads(out)
    assert s["gain"] == pytest.approx(0.7713, rel=0.01)
    assert s["a01"] is None


def test_ptc_on_fits_pairs(capsys, tmp_path, rng):
    """Poisson flats without BF: gain recovered, a_ij consistent with zero."""
    gain = 1.3
    files = []
    for k, m in enumerate(np.geomspace(300, 3e4, 6)):
        for p in range(3 if k == 2 else 2):  # a third flat at one level: the odd one out
            path = tmp_path / f"flat_{k}_{p}.fits"
            hdr = fits.Header({"EXPTIME": m / 1e3})
            fits.PrimaryHDU(rng.poisson(m * gain, (120, 120)) / gain, header=hdr).writeto(path)
            files.append(str(path))
    code, out, err = _run(capsys, "ptc", *files, "--json", "--max-lag", "1")
    assert code == 0, err
    s = json.loads(out)
    assert s["gain"] == pytest.approx(gain, abs=4 * s["gain_err"] + 0.01)
    assert abs(s["a10"]) < 4 * s["a10_err"] + 1e-9
    # the reader states which pairs it used and which file it dropped, and why
    assert len(s["pairs_used"]) == 6 and s["npairs"] == 6
    (drop,) = s["pairs_dropped"]
    assert drop["files"] == [files[6]] and "odd file out" in drop["reason"]
    code, text, err = _run(capsys, "ptc", *files, "--max-lag", "1")
    assert code == 0 and "6 pair(s) at 6 level(s)" in text and "flat_2_2.fits (odd file" in text
    (tmp_path / ".tmp-killed.fits").write_bytes(b"")  # a leftover is never a flat
    (tmp_path / f".tmp-{os.getpid()}-host-abcd1234.fits").write_bytes(b"")  # nor a live one
    code, out2, err = _run(capsys, "ptc", str(tmp_path), "--json", "--max-lag", "1")
    assert code == 0, err
    assert json.loads(out2)["gain"] == s["gain"]


def test_ptc_needs_pairs(capsys, tmp_path):
    code, _, err = _run(capsys, "ptc", "a.fits", "b.fits", "c.fits")
    assert code == 2 and "a.fits" in err


def test_flat_sim(capsys, tmp_path):
    png, ecsv = tmp_path / "fs.png", tmp_path / "fs.ecsv"
    code, out, err = _run(capsys, "flat-sim", "--n-images", "64", "--size", "8", "--steps",
                          "3", "--step", "2000", "--max-lag", "2", "--responsivity=-1e-5",
                          "--json", "--quiet", "--plot", str(png), "--out", str(ecsv))
    assert code == 0, err
    s = json.loads(out)
    assert len(s["steps"]) == 3 and s["steps"][-1]["mu"] == pytest.approx(6000, rel=0.01)
    # rescaled to dlnA00 = -1e-5 per e: the template charge changed accordingly
    t = load_default_template()
    own = np.log(t.moments().area[t.center, t.center]) / t.charge
    assert s["template_charge"] == pytest.approx(t.charge * own / -1e-5)
    assert png.read_bytes()[:4] == b"\x89PNG"
    from astropy.table import Table
    assert len(Table.read(ecsv)) == 3


def test_star_sim(capsys, tmp_path):
    png = tmp_path / "star.png"
    code, out, err = _run(capsys, "star-sim", "--flux", "30000", "--psf", "moffat", "--json",
                          "--quiet", "--plot", str(png), "--stamp", "21")
    assert code == 0, err
    s = json.loads(out)
    assert s["T_growth"] > 0 and s["central_counts"] < s["central_counts_square_pixels"]
    assert s["steps"][-1]["counts"] == 30000
    assert png.read_bytes()[:4] == b"\x89PNG"
    # issue 43 item 5: every panel titled, the run's parameters on the figure
    from astropy.table import Table
    from lsst_bfdrift.simulation.plots import STAR_PANEL_TITLES, plot_star_history
    hist = tmp_path / "h.ecsv"
    assert _run(capsys, "star-sim", "--flux", "30000", "--quiet", "--stamp", "21", "--out",
                str(hist))[0] == 0
    fig = plot_star_history(Table.read(hist), title="moffat 0.7\"")
    titles = [a.get_title() for a in fig.axes if a.get_title()]
    assert titles == [t for row in STAR_PANEL_TITLES for t in row]
    assert fig._suptitle.get_text() == "moffat 0.7\""


def test_star_sim_bad_psf(capsys):
    """An unknown PSF is a usage error (exit 2) that lists the choices."""
    with pytest.raises(SystemExit) as exc:
        main(["star-sim", "--psf", "airy", "--quiet"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "invalid choice: 'airy'" in err and "kolmogorov" in err


def test_correct(capsys, tmp_path):
    from lsst_bfdrift.cli.main import sample_image_path
    out_file = tmp_path / "corr.fits"
    code, out, err = _run(capsys, "correct", sample_image_path(), str(out_file), "--json",
                          "--quiet", "--geometry")
    assert code == 0, err
    s = json.loads(out)
    assert s["files"][0]["converged"]
    with fits.open(out_file) as hdul:
        assert hdul[0].header["BFDRIFT"] is True
        with fits.open(sample_image_path()) as src:
            assert hdul[0].data.sum() == pytest.approx(src[0].data.sum(), rel=1e-6)
        assert "AREA" in hdul and "FLUX_MOVED" in hdul
    code, _, err = _run(capsys, "correct", sample_image_path(), sample_image_path(), "--quiet")
    assert code == 3 and "refusing" in err
    code, out, err = _run(capsys, "correct", sample_image_path(), "--out-dir",
                          str(tmp_path / "many"), "--method", "astier23", "--quiet", "--json")
    assert code == 0 and json.loads(out)["method"] == "astier23"


@pytest.mark.slow
def test_correct_many_files_on_dask_cluster(capsys, tmp_path):
    """dask LocalCluster (threads) gives the serial outputs bit for bit; a
    corrupt file fails alone; existing outputs are kept without --overwrite."""
    from lsst_bfdrift.correction.batch import correct_files, output_pairs
    rng = np.random.default_rng(3)
    src = tmp_path / "in"
    src.mkdir()
    names = []
    for k in range(4):
        img = rng.poisson(500.0, (48, 48)).astype(np.float32)
        img[20:25, 18:23] += np.float32(3e4 * (k + 1))
        path = src / f"img{k}.fits"
        fits.PrimaryHDU(img, header=ELECTRONS).writeto(path)
        names.append(str(path))
    bad = src / "bad.fits"
    bad.write_bytes(b"SIMPLE  = not a fits file")
    names.insert(2, str(bad))
    serial = correct_files(output_pairs(names, tmp_path / "serial"))
    code, out, err = _run(capsys, "correct", *names, "--out-dir", str(tmp_path / "dask"),
                          "--scheduler", "local", "--json", "--quiet")
    assert code == 1 and "bad.fits" in err
    res = json.loads(out)
    assert res["failed"] == 1 and [r["input"] for r in res["files"]] == names
    assert res["files"][2]["error"] and serial[2]["error"]
    assert not (tmp_path / "dask" / "bad.fits").exists()
    for r_serial, r_dask in zip(serial, res["files"]):
        if r_serial["error"]:
            continue
        assert r_dask["error"] is None
        with fits.open(r_serial["output"]) as a, fits.open(r_dask["output"]) as b:
            assert np.array_equal(a[0].data, b[0].data)
            assert np.array_equal(a["FLUX_MOVED"].data, b["FLUX_MOVED"].data)
            with fits.open(r_serial["input"]) as s:
                assert abs(float(a[0].data.sum()) - float(s[0].data.sum())) < 1e-4 * float(
                    s[0].data.sum())
    # no temporary files left behind (atomic writes)
    assert not [p for p in (tmp_path / "dask").iterdir() if p.name.startswith(".tmp-")]
    # outputs exist now: refused per file without --overwrite, replaced with it
    before = (tmp_path / "dask" / "img0.fits").stat().st_mtime_ns
    results = correct_files(output_pairs(names[:2], tmp_path / "dask"), scheduler=None)
    assert all("exists" in r["error"] for r in results)
    assert (tmp_path / "dask" / "img0.fits").stat().st_mtime_ns == before
    results = correct_files(output_pairs(names[:2], tmp_path / "dask"), overwrite=True)
    assert all(r["error"] is None for r in results)
    with pytest.raises(ValueError, match="same output"):
        output_pairs([names[0], names[0]], tmp_path)


@pytest.mark.slow
def test_correct_files_through_a_scheduler_address(capsys, tmp_path, monkeypatch):
    """``--scheduler ADDRESS``: a dask scheduler with a worker in another
    process, reached by its tcp address, gives the serial outputs bit for bit;
    relative paths work although the worker runs in another directory."""
    from distributed import Client, LocalCluster

    from lsst_bfdrift.correction.batch import correct_files, output_pairs
    rng = np.random.default_rng(8)
    names = []
    for k in range(2):
        img = rng.poisson(800.0, (40, 40)).astype(np.float32)
        img[15:20, 15:20] += np.float32(5e4)
        path = tmp_path / f"star{k}.fits"
        fits.PrimaryHDU(img, header=ELECTRONS).writeto(path)
        names.append(str(path))
    serial = correct_files(output_pairs(names, tmp_path / "serial"))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, protocol="tcp",
                      dashboard_address=":0") as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tcp://")
        with Client(address) as c:
            c.run(os.chdir, "/")  # the worker's directory is not ours
        monkeypatch.chdir(tmp_path)
        rel = [os.path.basename(n) for n in names]
        code, out, err = _run(capsys, "correct", *rel, "--out-dir", "remote",
                              "--scheduler", address, "--json", "--quiet")
    assert code == 0, err
    res = json.loads(out)
    assert res["failed"] == 0 and [r["input"] for r in res["files"]] == rel
    res["files"] = [dict(r, output=str(tmp_path / r["output"])) for r in res["files"]]
    for r_serial, r_remote in zip(serial, res["files"]):
        with fits.open(r_serial["output"]) as a, fits.open(r_remote["output"]) as b:
            assert np.array_equal(a[0].data, b[0].data)
            assert a[0].header["BFMETHOD"] == b[0].header["BFMETHOD"]


def test_validate_stars_defaults(capsys):
    """validate-stars defaults to converged GalSim updates and the transfer-matched
    import (benchmarks/correction/probe_validation_cadence_results.txt, docs/benchmarks.rst)."""
    import inspect

    from lsst_bfdrift.cli.main import build_parser
    from lsst_bfdrift.validation.stars import draw_star_pairs
    args = build_parser().parse_args(["validate-stars"])
    assert (args.match, args.updates, args.min_nrecalc) == ("transfers", 1000.0, 100.0)
    sig = inspect.signature(draw_star_pairs).parameters
    assert (sig["updates"].default, sig["min_nrecalc"].default) == (1000, 100)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["validate-stars", "--match", "polygons"])
    assert "invalid choice" in capsys.readouterr().err


def test_calibrate_from_a_ptc_and_refusals(capsys, tmp_path):
    """bfdrift calibrate on the measured e2v PTC (a00 from its curvature):
    one parameter, the template and a plot written; an existing --out and an
    --out that is an input are refused with nothing written."""
    from lsst_bfdrift.templates.template import DistortionTemplate

    ptc = "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt"
    out, png = tmp_path / "cal.fits", tmp_path / "cal.png"
    code, text, _ = _run(capsys, "calibrate", ptc, "--out", str(out), "--plot", str(png),
                         "--json", "--quiet")
    assert code == 0
    s = json.loads(text)
    assert s["names"] == ["channel_depth"] and s["dof"] == 0
    assert -3e-6 < s["lags"][0]["a"] < -2e-6 and abs(s["lags"][0]["pull"]) < 0.1
    assert s["input"]["kind"] == "ptc" and png.exists()
    tpl = DistortionTemplate.load(out)
    assert tpl.meta["calibration"]["inputs"] == [ptc]
    # the text report says what uncertainty the file stores (one parameter: one mode)
    assert tpl.meta["calibration"]["uncertainty"]["parameter_modes"]["kept"] == [0]
    code, text, _ = _run(capsys, "calibrate", ptc, "--out", str(tmp_path / "text.fits"),
                         "--quiet")
    assert code == 0 and "uncertainty stored: the a_ij errors and 1 parameter mode(s)" in text
    code, text, _ = _run(capsys, "calibrate", ptc, "--out", str(tmp_path / "bare.fits"),
                         "--no-parameter-modes", "--quiet")
    assert code == 0 and "uncertainty stored" not in text
    bare = DistortionTemplate.load(tmp_path / "bare.fits").meta["calibration"]["uncertainty"]
    assert "parameter_modes" not in bare and bare["kind"] == "data"
    code, _, err = _run(capsys, "calibrate", ptc, "--out", str(out), "--quiet")
    assert code == 3 and "exists" in err
    code, _, err = _run(capsys, "calibrate", ptc, "--out", ptc, "--overwrite", "--quiet")
    assert code != 0 and "one of the inputs" in err
    code, _, err = _run(capsys, "calibrate", ptc, "--out", str(tmp_path / "s.fits"), "--stars",
                        str(tmp_path / "nofield.fits"), "--quiet")
    assert code == 2 and "nofield.fits: no such file" in err
    field = _small_image(tmp_path / "field.fits")
    code, _, err = _run(capsys, "calibrate", ptc, "--out", field, "--stars", field,
                        "--overwrite", "--quiet")
    assert code == 3 and "input" in err
    assert not (tmp_path / "s.fits").exists()


def test_calibrate_poor_fit_refused_unrefined_and_written_refined(capsys, tmp_path):
    """issue 41: refined to the data, a poor physics fit is written with its misfit
    stated and carried into the uncertainty; without refinement it is refused and
    nothing is written (separate from the PTC test so the two run on two workers)."""
    from lsst_bfdrift.templates.template import DistortionTemplate

    tight = tmp_path / "tight.txt"
    itl = np.loadtxt("/work/shared/data/measured/itl_covariances_21oct19.txt", skiprows=1)
    itl[:, 3] = 1e-4 * np.abs(itl[:, 2]) + 1e-14  # errors no model meets
    a11 = (itl[:, 0] == 1) & (itl[:, 1] == 1)
    itl[a11, 3] = 0.5 * np.abs(itl[a11, 2])  # but S1 measured to only 23 %: said
    # lags 0-1: 3 dof for one free parameter, and each model evaluation is cheaper
    np.savetxt(tight, itl[(itl[:, 0] <= 1) & (itl[:, 1] <= 1)], header="i j a sigma")
    bad = tmp_path / "bad.fits"
    # a fit that cannot meet 0.01 % errors is poor however long it searches: 6 evaluations
    code, _, err = _run(capsys, "calibrate", str(tight), "--out", str(bad), "--free", "v_bss",
                        "--quiet", "--no-refine", "--max-evaluations", "6")
    assert code == 4 and "poor fit" in err and "worst lags" in err and not bad.exists()
    code, out, err = _run(capsys, "calibrate", str(tight), "--out", str(bad), "--free", "v_bss",
                          "--quiet", "--max-evaluations", "6")
    assert code == 0 and "warning: poor fit" in err and "Birge ratio" in err
    r = {(int(i), int(j)): a for i, j, a, _ in itl}
    s1 = r[0, 0] + 2 * (r[0, 1] + r[1, 0]) + 4 * r[1, 1]
    assert f"near field S1 = a00 + 2 (a01 + a10) + 4 a11 (sets the stars' size correction): " \
           f"data {s1:+.3e} +- {2 * abs(r[1, 1]):.1e} (23 %)" in out
    assert "note: this a-matrix measures S1 to 23 %" in out
    misfit = DistortionTemplate.load(bad).meta["calibration"]["misfit"]
    assert misfit["birge"] > 10 and misfit["template_chi2"] < misfit["template_lags"]
    code, _, err = _run(capsys, "calibrate", str(tight), "--out", str(tmp_path / "x.fits"),
                        "--max-evaluations", "0", "--quiet")
    assert code == 2 and "max_evaluations must be a positive integer, got 0" in err



def test_calibrate_with_converged_model_numerics(capsys, tmp_path):
    """--model-numerics converged fits with CONVERGED_MODEL_SETTINGS (the start
    Jacobian computed, the package data being the fit's) and records them in
    the template."""
    from lsst_bfdrift.calibration.fit_model import CONVERGED_MODEL_SETTINGS
    from lsst_bfdrift.templates.template import DistortionTemplate

    small = tmp_path / "small.txt"
    itl = np.loadtxt("/work/shared/data/measured/itl_covariances_21oct19.txt", skiprows=1)
    np.savetxt(small, itl[(itl[:, 0] <= 1) & (itl[:, 1] <= 1)], header="i j a sigma")
    out = tmp_path / "converged.fits"
    code, text, err = _run(capsys, "calibrate", str(small), "--out", str(out), "--free", "v_bss",
                           "--max-evaluations", "1", "--model-numerics", "converged",
                           "--no-refine", "--json", "--quiet")
    assert code == 0, err
    assert json.loads(text)["jacobian_source"] == "computed"
    calibration = DistortionTemplate.load(out).meta["calibration"]
    assert calibration["model_settings"] == CONVERGED_MODEL_SETTINGS

def test_template_export_galsim(capsys, tmp_path):
    """bfdrift template export-galsim writes files galsim.SiliconSensor
    reads, and refuses to overwrite them."""
    import galsim

    prefix = tmp_path / "default"
    code, out, _ = _run(capsys, "template", "export-galsim", str(tmp_path / "missing.fits"),
                        str(prefix))
    assert code != 0
    from lsst_bfdrift.templates.template import default_template_path
    code, out, _ = _run(capsys, "template", "export-galsim", default_template_path(),
                        str(prefix), "--vertices", "8", "--json")
    assert code == 0 and json.loads(out)["num_vertices"] == 8
    sensor = galsim.SiliconSensor(str(prefix), diffusion_factor=0.0)
    img = galsim.ImageD(5, 5, scale=0.2)
    img.setCenter(0, 0)
    img[0, 0] = 1e4
    assert sensor.calculate_pixel_areas(img)[0, 0] < 0.995
    code, _, err = _run(capsys, "template", "export-galsim", default_template_path(),
                        str(prefix))
    assert code != 0 and "exists" in err


def _small_image(path):
    fits.writeto(path, np.random.default_rng(20).normal(1000.0, 30.0, (16, 16)))
    return str(path)


@pytest.mark.parametrize("argv", [
    ["maps", "{img}", "--out", "{old}", "--quiet"],
    ["maps", "{img}", "--plot", "{old}", "--quiet"],
    ["template", "plot", "--out", "{old}"],
    ["flat-sim", "--out", "{old}", "--quiet"],
    ["flat-sim", "--plot", "{old}", "--quiet"],
    ["star-sim", "--out", "{old}", "--quiet"],
    ["validate-sky", "{img}", "--catalog", "{old}", "--quiet"],
    ["validate-sky", "{img}", "--plot", "{old}", "--quiet"],
    ["calibrate", "{img}", "--out", "{new}", "--plot", "{old}", "--quiet"],
])
def test_existing_output_needs_overwrite(capsys, tmp_path, argv):
    """F1: no command replaces an existing file without --overwrite (exit 3,
    the file untouched, checked before any work)."""
    old = tmp_path / "old.out"
    old.write_text("keep me")
    fmt = {"img": _small_image(tmp_path / "img.fits"), "old": str(old),
           "new": str(tmp_path / "new.fits")}
    code, _, err = _run(capsys, *[a.format(**fmt) for a in argv])
    assert code == 3 and "exists" in err and "--overwrite" in err, err
    assert old.read_text() == "keep me" and not (tmp_path / "new.fits").exists()


@pytest.mark.parametrize("argv", [
    ["maps", "{img}", "--out", "{img}"],
    ["maps", "{img}", "--plot", "{img}"],
    ["maps", "{img}", "--template", "{tpl}", "--out", "{tpl}"],
    ["template", "plot", "{tpl}", "--out", "{tpl}"],
    ["flat-sim", "--template", "{tpl}", "--out", "{tpl}"],
    ["star-sim", "--template", "{tpl}", "--plot", "{tpl}"],
    ["validate-sky", "{img}", "--catalog", "{img}"],
    ["calibrate", "{img}", "--out", "{new}", "--plot", "{img}"],
    ["correct", "{img}", "{img}"],
    ["correct", "{img}", "{link}"],
])
def test_output_is_never_an_input(capsys, tmp_path, argv):
    """F1: `bfdrift maps IMG --out IMG` replaced the image; an input is never
    an output, even with --overwrite or through a symbolic link."""
    img = _small_image(tmp_path / "img.fits")
    tpl = tmp_path / "tpl.fits"
    load_default_template().save(tpl)
    (tmp_path / "link.fits").symlink_to(img)
    before = {p: pathlib.Path(p).read_bytes() for p in (img, tpl)}
    fmt = {"img": img, "tpl": str(tpl), "new": str(tmp_path / "new.fits"),
           "link": str(tmp_path / "link.fits")}
    quiet = [] if argv[0] == "template" else ["--quiet"]
    code, _, err = _run(capsys, *[a.format(**fmt) for a in argv], "--overwrite", *quiet)
    assert code == 3 and "one of the inputs" in err, err
    assert {p: pathlib.Path(p).read_bytes() for p in (img, tpl)} == before


def test_two_outputs_may_not_share_a_file(capsys, tmp_path):
    out = str(tmp_path / "x.fits")
    code, _, err = _run(capsys, "maps", "--out", out, "--plot", out, "--quiet")
    assert code == 3 and "also given to --out" in err


def test_overwrite_replaces_an_existing_plot(capsys, tmp_path):
    png = tmp_path / "t.png"
    png.write_text("old")
    code, _, err = _run(capsys, "template", "plot", "--out", str(png), "--overwrite")
    assert code == 0, err
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert sorted(os.listdir(tmp_path)) == ["t.png"]  # no .tmp-* left


def test_crashes_are_clear_errors(capsys, tmp_path):
    """ptc --max-lag 0 (IndexError), diagnose with lag 100000 (MemoryError),
    a template with non-integer offsets (IndexError): exit 2, message."""
    from astropy.table import Table
    rng = np.random.default_rng(21)
    files = []
    for k, m in enumerate(np.geomspace(300, 3e4, 5)):
        for p in range(2):
            files.append(str(tmp_path / f"f{k}{p}.fits"))
            fits.PrimaryHDU(rng.poisson(m, (32, 32)).astype(float)).writeto(files[-1])
    code, _, err = _run(capsys, "ptc", *files, "--max-lag", "0")
    assert code == 2 and "--max-lag must be >= 1" in err
    big = tmp_path / "big.txt"
    big.write_text("i j a sigma\n0 0 -2e-6 1e-8\n0 1 1e-7 1e-9\n1 0 5e-8 1e-9\n"
                   "100000 0 1e-9 1e-9\n")
    code, _, err = _run(capsys, "diagnose", str(big))
    assert code == 2 and "big.txt: lag (100000, 0) is beyond 64" in err
    from lsst_bfdrift.templates.template import default_template_path
    with fits.open(default_template_path()) as hdul:
        hdus = fits.HDUList([h.copy() for h in hdul])
    t = Table(hdus["TEMPLATE"].data)
    t["di"] = t["di"].astype(float) + 0.5
    hdus["TEMPLATE"] = fits.BinTableHDU(t, header=hdus["TEMPLATE"].header, name="TEMPLATE")
    bad = tmp_path / "nonint.fits"
    hdus.writeto(bad, checksum=True)
    code, _, err = _run(capsys, "template", "summary", str(bad))
    assert code == 2 and "nonint.fits: column 'di' holds non-integer pixel offsets" in err
    hdus[0].header["BFMETA"] = "[1, 2]"
    hdus["TEMPLATE"] = fits.BinTableHDU(t[:0], header=hdus["TEMPLATE"].header, name="TEMPLATE")
    hdus.writeto(bad, checksum=True, overwrite=True)
    code, _, err = _run(capsys, "template", "summary", str(bad))
    assert code == 2 and "not an object" in err


def _subparsers(parser, path=()):
    import argparse
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _subparsers(child, path + (name,))


def test_every_option_has_a_help_line_and_its_default(capsys):
    """--help of every command lists each option with a description, its default
    and its choices (issue 19: the CLI explains itself)."""
    from lsst_bfdrift.cli.main import build_parser
    n = 0
    for path, parser in _subparsers(build_parser()):
        for action in parser._actions:
            if action.option_strings and action.dest != "help":
                assert action.help, (path, action.option_strings)
                n += 1
        if not path:
            continue
        with pytest.raises(SystemExit):
            main(list(path) + ["--help"])
        out = capsys.readouterr().out
        if path == ("correct",):
            assert "{drift,astier23,coulton18}" in out and "(default: 2)" in out
        if path == ("star-sim",):
            assert "{gaussian,moffat,kolmogorov}" in out and "(default: gaussian)" in out
    assert n > 100


def test_version(capsys):
    import lsst_bfdrift
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"bfdrift {lsst_bfdrift.__version__}"


def test_one_meaning_of_gain(capsys, tmp_path):
    """Issue 19 rows 2-3: --gain means the image is in ADU in every command. An ADU
    image without BUNIT is converted (not silently taken as electrons); an image whose
    BUNIT says electron with a --gain is an error in correct, maps and validate-sky;
    one that states neither a unit nor a gain is refused by all three, with the same
    words (the unit rule)."""
    from lsst_bfdrift.cli.main import sample_image_path
    with fits.open(sample_image_path()) as h:
        electrons = np.array(h[0].data, dtype=np.float64)
    gain = 2.27
    fits.PrimaryHDU(electrons / gain).writeto(tmp_path / "adu.fits")  # no BUNIT
    fits.PrimaryHDU(electrons, header=ELECTRONS).writeto(tmp_path / "e.fits")
    assert _run(capsys, "correct", str(tmp_path / "adu.fits"), str(tmp_path / "adu_out.fits"),
                "--gain", str(gain), "--quiet")[0] == 0
    assert _run(capsys, "correct", str(tmp_path / "e.fits"), str(tmp_path / "e_out.fits"),
                "--quiet")[0] == 0
    with fits.open(tmp_path / "adu_out.fits") as a, fits.open(tmp_path / "e_out.fits") as b:
        assert a[0].header["BFGAIN"] == gain
        # the same correction in electrons: moved flux equal, image = electrons / gain
        assert_allclose(a["FLUX_MOVED"].data, b["FLUX_MOVED"].data, rtol=1e-4,
                        atol=1e-3 * np.abs(b["FLUX_MOVED"].data).max())
        assert np.abs(b["FLUX_MOVED"].data).max() > 10.0
    code, out, _ = _run(capsys, "maps", str(tmp_path / "adu.fits"), "--gain", str(gain),
                        "--json", "--quiet")
    assert code == 0 and json.loads(out)["gain"] == gain
    hdr = fits.Header({"BUNIT": "electron"})
    fits.PrimaryHDU(electrons, header=hdr).writeto(tmp_path / "stated.fits")
    for argv in (["correct", str(tmp_path / "stated.fits"), str(tmp_path / "x.fits")],
                 ["maps", str(tmp_path / "stated.fits")],
                 ["validate-sky", str(tmp_path / "stated.fits")]):
        code, _, err = _run(capsys, *argv, "--gain", "2.0", "--quiet")
        assert code in (1, 2) and "states it is in electrons" in err, (argv, err)
    for argv in (["correct", str(tmp_path / "adu.fits"), str(tmp_path / "y.fits")],
                 ["maps", str(tmp_path / "adu.fits")],
                 ["validate-sky", str(tmp_path / "adu.fits")]):
        code, _, err = _run(capsys, *argv, "--quiet")
        assert code in (1, 2) and "adu.fits: the image states no unit (no BUNIT or LSST ISR " \
            "UNITS) and no gain" in err and "BUNIT = 'electron'" in err, (argv, err)


def test_correct_saturation_and_template_options(capsys, tmp_path):
    """Issue 19 item 7: SATURATE (image units) blocks pixels, --saturation overrides it,
    --template names the template used; flux is conserved either way."""
    rng = np.random.default_rng(21)
    yy, xx = np.mgrid[:48, :48]
    img = rng.poisson(700.0, (48, 48)) + 3e5 * np.exp(-((yy - 24)**2 + (xx - 23)**2) / 4.5)
    gain = 2.0
    hdr = fits.Header({"BUNIT": "adu", "GAIN": gain, "SATURATE": 5e4})  # 1e5 e
    fits.PrimaryHDU(img / gain, header=hdr).writeto(tmp_path / "in.fits")
    tpl = tmp_path / "tpl.fits"
    load_default_template().save(tpl)
    counts = {}
    for label, extra in (("header", []), ("option", ["--saturation", "1.4e5"])):
        out = tmp_path / f"{label}.fits"
        code, _, err = _run(capsys, "correct", str(tmp_path / "in.fits"), str(out),
                            "--template", str(tpl), "--no-geometry", "--quiet", *extra)
        assert code == 0, err
        with fits.open(out) as h:
            blocked = (h["BFFLAGS"].data & 1) != 0
            counts[label] = int(blocked.sum())
            sat_e = {"header": 1e5, "option": 2.8e5}[label]
            assert h[0].header["BFSATUR"] == sat_e
            assert_allclose(blocked, img >= sat_e)
            assert h[0].header["BFTMPL"] == "tpl.fits" and "AREA" not in h
            assert abs(float(h[0].data.sum()) - float((img / gain).sum())) < 1e-6 * img.sum()
    assert counts["header"] > counts["option"] > 0


def test_correct_skip_existing_resumes(capsys, tmp_path):
    """Issue 19 item 6: --skip-existing corrects only the inputs without an output."""
    rng = np.random.default_rng(5)
    names = []
    for k in range(3):
        path = tmp_path / f"in{k}.fits"
        fits.PrimaryHDU(rng.poisson(600.0, (32, 32)).astype(np.float32),
                        header=ELECTRONS).writeto(path)
        names.append(str(path))
    out = tmp_path / "out"
    assert _run(capsys, "correct", names[0], "--out-dir", str(out), "--quiet",
                "--no-geometry")[0] == 0
    first = (out / "in0.fits").stat().st_mtime_ns
    code, text, _ = _run(capsys, "correct", *names, "--out-dir", str(out), "--quiet",
                         "--no-geometry", "--skip-existing", "--json")
    res = json.loads(text)
    assert code == 0 and [bool(r.get("skipped")) for r in res["files"]] == [True, False, False]
    assert (out / "in0.fits").stat().st_mtime_ns == first and (out / "in2.fits").exists()
    code, _, err = _run(capsys, "correct", *names, "--out-dir", str(out), "--skip-existing",
                        "--overwrite")
    assert code == 2 and "contradict" in err


def test_correct_removes_stale_partial_files_and_says_so(capsys, tmp_path):
    """Issue 20, leftovers: a partial .tmp-* file of a killed run (its PID is
    gone) next to the output is removed when the next command starts and
    listed on stderr; one of a running process is kept."""
    import subprocess
    import sys

    from lsst_bfdrift.cli.main import sample_image_path
    from lsst_bfdrift.utils.io import _host_tag
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    stale = [out_dir / f".tmp-{proc.pid}-{_host_tag()}-abcd{k}xyz.fits" for k in range(2)]
    live = out_dir / f".tmp-{os.getpid()}-{_host_tag()}-abcd9xyz.fits"
    for path in stale + [live]:
        path.write_bytes(b"partial")
    code, _, err = _run(capsys, "correct", sample_image_path(), str(out_dir / "c.fits"),
                        "--quiet", "--no-geometry")
    assert code == 0, err
    assert "removed 2 stale partial files" in err
    assert all(str(p) in err for p in stale) and str(live) not in err
    assert sorted(os.listdir(out_dir)) == sorted(["c.fits", live.name])
    # the same for any command writing into a directory (here: --out-dir, maps --out)
    stale[0].write_bytes(b"partial")
    code, _, err = _run(capsys, "maps", "--out", str(out_dir / "m.fits"), "--samples", "2",
                        "--quiet", "--json")
    assert code == 0 and "removed 1 stale partial file of killed runs" in err
    code, _, err = _run(capsys, "correct", sample_image_path(), "--out-dir", str(out_dir),
                        "--quiet", "--no-geometry", "--overwrite")
    assert "stale" not in err
    assert live.exists()


def test_sigterm_removes_the_partial_output(tmp_path):
    """SIGTERM during a write (a killed `bfdrift correct`) ends the command
    through an exception: the partial file is removed, the output never
    appears and the exit status is 143."""
    import signal
    import subprocess
    import sys
    script = (
        "import sys, time\n"
        "from lsst_bfdrift.cli._common import sigterm_raises\n"
        "from lsst_bfdrift.utils.io import atomic_output\n"
        "with sigterm_raises():\n"
        f"    with atomic_output({str(tmp_path / 'out.fits')!r}) as tmp:\n"
        "        open(tmp, 'w').write('partial')\n"
        "        print('writing', flush=True)\n"
        "        time.sleep(60)\n")
    env = dict(os.environ, PYTHONPATH=str(pathlib.Path(__file__).resolve().parents[2]))
    with subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, env=env,
                          text=True) as proc:
        assert proc.stdout.readline().strip() == "writing"
        assert [p.name for p in tmp_path.iterdir()][0].startswith(".tmp-")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 128 + signal.SIGTERM
    assert list(tmp_path.iterdir()) == []


def test_correct_shows_progress_inside_a_file(capsys, tmp_path):
    """Issue 19, item 8: one file's correction reports its stages (read,
    correct, maps, write) on stderr unless --quiet (the CLI's one progress switch;
    a log gets a line per 10 %); the corrected file is the same either way.
    Several files logged to a file keep the one bar of files finished."""
    from lsst_bfdrift.cli.main import sample_image_path
    a, b = tmp_path / "a.fits", tmp_path / "b.fits"
    code, _, err = _run(capsys, "correct", sample_image_path(), str(a), "--geometry")
    assert code == 0, err
    lines = [ln for ln in err.splitlines() if ln.startswith("correct sample_star.fits: ")]
    stages = [ln.split(": ")[1].split()[0] for ln in lines]
    assert {"read", "maps", "write"} <= set(stages), err
    # the linear maps (the default) come from the correction's first pass, after it
    assert stages == sorted(stages, key=["read", "correct", "maps", "write", "done"].index)
    assert "100.0%" in lines[-1]
    code, _, err = _run(capsys, "correct", sample_image_path(), str(b), "--geometry", "--quiet")
    assert code == 0 and err == ""
    with fits.open(a) as ha, fits.open(b) as hb:
        assert [h.name for h in ha] == [h.name for h in hb]
        for x, y in zip(ha, hb):
            assert (x.data is None and y.data is None) or np.array_equal(x.data, y.data), x.name
    other = tmp_path / "other.fits"
    other.write_bytes(pathlib.Path(sample_image_path()).read_bytes())
    code, _, err = _run(capsys, "correct", sample_image_path(), str(other), "--out-dir",
                        str(tmp_path / "many"), "--no-geometry")
    assert code == 0, err
    assert "correct 100.0%" in err and ".fits: " not in err


def test_diagnose_reports_the_template_change(tmp_path, capsys, monkeypatch):
    """An a_ij table with a charge cloud injected through the basis (the
    package's own effect model): diagnose adds it and hands the result to
    template_change (stubbed here; its calibrations take minutes and are
    tested in tests/diagnosis/test_consequence.py); --no-template-change
    skips it."""
    from lsst_bfdrift.diagnosis import consequence
    from lsst_bfdrift.calibration.acoeff_model import load_default_basis
    from lsst_bfdrift.simulation.effects import effect_library

    basis = load_default_basis()
    a = basis.a([basis.x0[n] for n in basis.names], 3)
    cloud = {e.name: e for e in effect_library(max_lag=3)}["charge_cloud"]
    a = cloud.apply_a(a, [0.15, 0.05], basis)
    sig = 0.02 * np.abs(a) + 2e-10
    a = a + np.random.default_rng(7).normal(0.0, sig)
    path = tmp_path / "table.txt"
    path.write_text("".join(f"{i} {j} {a[i, j]:.6e} {sig[i, j]:.3e}\n"
                            for i in range(4) for j in range(4)))
    seen = []

    def stub(d, b, **kw):
        seen.append((d["effects_added"], b))
        return {"available": True, "changed": False, "threshold": 1.0, "largest_shift": 3.0,
                "largest_shift_lag": [1, 0], "shift": {"1,0": {
                    "before": 1.0, "after": 2.0, "error": 0.3, "sigma": 3.0}}}

    monkeypatch.setattr(consequence, "template_change", stub)
    code, out, _ = _run(capsys, "diagnose", str(path), "--json")
    d = json.loads(out)
    assert code == 0 and d["effects_added"] == ["charge_cloud"]
    assert seen and seen[0][0] == ["charge_cloud"] and seen[0][1] is not None
    assert d["template_change"]["largest_shift"] == 3.0
    code, out, _ = _run(capsys, "diagnose", str(path), "--no-template-change")
    assert code == 0 and "charge_cloud" in out and "largest shift" not in out
    assert len(seen) == 1


def test_calibrate_fit_slopes_option(capsys):
    """--fit-slopes defaults to the API's fitted_slopes (size) and takes only
    size, e1 and e2."""
    import inspect

    from lsst_bfdrift.calibration.star_fit import calibrate_with_stars
    from lsst_bfdrift.cli.main import build_parser
    default = inspect.signature(calibrate_with_stars).parameters["fitted_slopes"].default
    args = build_parser().parse_args(["calibrate", "a.txt", "--out", "o.fits", "--stars", "f.fits"])
    assert tuple(args.fit_slopes) == tuple(default) == ("size",)
    args = build_parser().parse_args(["calibrate", "a.txt", "--out", "o.fits", "--stars", "f.fits",
                                      "--fit-slopes", "size", "e1"])
    assert args.fit_slopes == ["size", "e1"]
    with pytest.raises(SystemExit):
        build_parser().parse_args(["calibrate", "a.txt", "--out", "o.fits", "--fit-slopes", "e3"])
    assert "invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize("goal", ["0", "-3", "nan"])
def test_calibrate_size_goal_option(capsys, tmp_path, goal):
    """--size-goal defaults to the API's size_goal (3 %), and a goal that is not
    a positive precision is a usage error before any file is read."""
    import inspect

    from lsst_bfdrift.calibration.star_fit import calibrate_with_stars
    from lsst_bfdrift.cli.main import build_parser
    default = inspect.signature(calibrate_with_stars).parameters["size_goal"].default
    args = build_parser().parse_args(["calibrate", "a.txt", "--out", "o.fits", "--stars", "f.fits"])
    assert args.size_goal == default == 3.0
    flats, field = tmp_path / "a.txt", tmp_path / "f.fits"
    flats.write_text("not read\n")
    field.write_bytes(b"not read")
    out = tmp_path / "o.fits"
    code, _, err = _run(capsys, "calibrate", str(flats), "--out", str(out), "--stars", str(field),
                        "--size-goal", goal, "--quiet")
    assert code == 2 and "--size-goal must be a finite precision > 0" in err
    assert not out.exists()


def test_calibrate_with_lsst_routes(capsys, tmp_path):
    """bfdrift calibrate --model astier23 / coulton18 on the measured ITL a-matrix:
    a template meant for that method and LSST's product, read back; options of the
    package's own model and a PTC's a00 alone are refused with nothing written."""
    from lsst_bfdrift.calibration.lsst_products import read_bfk, read_distortion_matrix
    from lsst_bfdrift.templates.template import DistortionTemplate

    itl = "/work/shared/data/measured/itl_covariances_21oct19.txt"
    out, prod = tmp_path / "k.fits", tmp_path / "bfk.fits"
    code, text, _ = _run(capsys, "calibrate", itl, "--model", "coulton18", "--out", str(out),
                         "--product", str(prod), "--json")
    assert code == 0 and json.loads(text)["method"] == "coulton18"
    assert DistortionTemplate.load(out).meta["method"] == "coulton18"
    assert read_bfk(prod).kernel.shape == (17, 17)
    out, prod = tmp_path / "ar.fits", tmp_path / "dm.fits"
    code, text, _ = _run(capsys, "calibrate", itl, "--model", "astier23", "--out", str(out),
                         "--product", str(prod))
    assert code == 0 and "correct with --method astier23" in text
    assert read_distortion_matrix(prod).free_params[0] == "alpha"
    for extra, match in ((["--free", "xi0"], "--free: options of --model electrostatic"),
                         (["--stars", itl], "--stars: options of --model electrostatic")):
        code, _, err = _run(capsys, "calibrate", itl, "--model", "astier23", "--out",
                            str(tmp_path / "no.fits"), *extra)
        assert code == 2 and match in err
    code, _, err = _run(capsys, "calibrate", itl, "--out", str(tmp_path / "no.fits"),
                        "--product", str(tmp_path / "p.fits"))
    assert code == 2 and "--product writes LSST's product" in err
    ptc = "/work/shared/data/measured/eotest_e2v_ptc_amp05.txt"
    code, _, err = _run(capsys, "calibrate", ptc, "--model", "astier23", "--out",
                        str(tmp_path / "no.fits"))
    assert code == 4 and "this input has 1" in err
    assert not (tmp_path / "no.fits").exists() and not (tmp_path / "p.fits").exists()


def test_hostile_inputs_of_correct_and_maps(capsys, tmp_path):
    """Issue 44 items 3, 5, 6, 11, 12, 13: each case a clear error naming the option or
    file (no traceback, no internal source path), never a silent success."""
    from lsst_bfdrift.cli.main import sample_image_path

    star = str(tmp_path / "star.fits")
    with fits.open(sample_image_path()) as h:
        data = np.array(h[0].data, dtype=np.float32)
    fits.PrimaryHDU(data, header=ELECTRONS).writeto(star)
    # 11: a bad --gain / --saturation is named by its option, no source path shown
    for opt, val in (("--gain", "0"), ("--gain", "-1"), ("--gain", "nan"),
                     ("--saturation", "nan")):
        code, _, err = _run(capsys, "correct", star, str(tmp_path / "o.fits"), opt, val,
                            "--quiet")
        assert code == 2 and opt in err and ".py" not in err, (opt, val, err)
    # 12: --out-dir that is a file
    code, _, err = _run(capsys, "correct", star, "--out-dir", star, "--quiet")
    assert code == 2 and "--out-dir" in err and "is not a directory" in err
    # 5: an all-negative image: a warning, and --strict refuses it
    neg = str(tmp_path / "neg.fits")
    fits.PrimaryHDU(-data, header=ELECTRONS).writeto(neg)
    code, _, err = _run(capsys, "correct", neg, str(tmp_path / "n.fits"), "--quiet",
                        "--strict", "--no-geometry")
    assert code == 1 and "mostly negative" in err and not (tmp_path / "n.fits").exists()
    # 6 and 13: an all-NaN image is refused by correct and maps, and the JSON stays strict
    nan = str(tmp_path / "nan.fits")
    fits.PrimaryHDU(np.full((20, 20), np.nan, np.float32), header=ELECTRONS).writeto(nan)
    code, _, err = _run(capsys, "correct", nan, str(tmp_path / "x.fits"), "--quiet")
    assert code == 1 and "there is no charge to correct" in err
    assert "converged" not in capsys.readouterr().out
    code, out, err = _run(capsys, "maps", nan, "--json", "--quiet")
    assert code == 2 and "no charge to map" in err and "NaN" not in out
    # 3: --skip-existing skips only a complete output of bfdrift correct
    d = tmp_path / "out"
    d.mkdir()
    fits.PrimaryHDU(np.zeros((4, 4))).writeto(d / "star.fits")  # unrelated
    code, out, err = _run(capsys, "correct", star, "--out-dir", str(d), "--skip-existing",
                          "--quiet")
    assert code == 1 and "no BFDRIFT card" in err
    (d / "star.fits").write_bytes(b"SIMPLE  =                    T")  # cut short
    code, out, err = _run(capsys, "correct", star, "--out-dir", str(d), "--skip-existing",
                          "--quiet")
    assert code == 1 and "not a readable FITS file" in err
    (d / "star.fits").unlink()
    assert _run(capsys, "correct", star, "--out-dir", str(d), "--quiet",
                "--no-geometry")[0] == 0
    code, out, _ = _run(capsys, "correct", star, "--out-dir", str(d), "--skip-existing")
    assert code == 0 and "skipped (the output exists)" in out


def test_print_json_is_strict():
    from lsst_bfdrift.cli._common import print_json
    import io
    import contextlib
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        print_json({"a": float("nan"), "b": [np.float64("inf"), 1.5], "c": np.arange(2.0)})
    assert json.loads(buf.getvalue()) == {"a": None, "b": [None, 1.5], "c": [0.0, 1.0]}


def test_maps_outputs_say_their_units_and_clipping(capsys, tmp_path):
    """Issue 43 item 5: each map HDU states its unit (the input's BUNIT moves to
    BFIUNIT: the file holds no image in it) and the figure says where its colour
    scale clips (the sample star's area reaches 0.96 while 99.5 % of pixels lie
    within +-0.003)."""
    from lsst_bfdrift.geometry.plots import plot_moment_maps
    from lsst_bfdrift.geometry.superpose import moment_maps
    from lsst_bfdrift.templates.template import load_default_template
    from lsst_bfdrift.cli.main import sample_image_path

    out = tmp_path / "maps.fits"
    assert _run(capsys, "maps", "--out", str(out), "--quiet")[0] == 0
    with fits.open(out) as h:
        assert h[0].header["BFIUNIT"] == "electron" and "BUNIT" not in h[0].header
        assert [h[k].header["BUNIT"] for k in ("AREA", "DX", "E1")] == ["pix2", "pix", ""]
    with fits.open(sample_image_path()) as h:
        img = np.array(h[0].data, float)
    maps = moment_maps(load_default_template(), img, samples=8)
    fig = plot_moment_maps(maps, image=img)
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    area = next(t for t in titles if t.startswith("area - 1"))
    assert "scale clipped at 99.5 %: range" in area and f"{maps.area.min() - 1:.3g}" in area


def test_a_stale_partial_file_in_an_input_directory_is_removed(capsys, tmp_path):
    """Issue 43 item 9: a directory of flats given to ``bfdrift ptc`` that holds a
    killed run's .tmp-* file: skipped by the reader and removed, and said so."""
    import subprocess
    import sys

    from lsst_bfdrift.utils.io import _host_tag
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    d = tmp_path / "flats"
    d.mkdir()
    rng = np.random.default_rng(4)
    for k, level in enumerate((2e3, 6e3, 1.2e4, 2.4e4, 4e4)):
        for half in "ab":
            # levels proportional to EXPTIME (a lamp of 2000 e/s; issue 43 item 1)
            hdr = fits.Header({"EXPTIME": level / 2e3, "BUNIT": "adu"})
            fits.PrimaryHDU(rng.poisson(level, (48, 48)).astype(np.float32),
                            header=hdr).writeto(d / f"flat_{k}{half}.fits")
    stale = d / f".tmp-{proc.pid}-{_host_tag()}-abcd0xyz.fits"
    stale.write_bytes(b"partial")
    code, out, err = _run(capsys, "ptc", str(d), "--json")
    assert code == 0, err
    assert "removed 1 stale partial file of killed runs" in err and not stale.exists()


def _flat_dir(path, rng, exptimes, *, levels=(2e3, 6e3, 1.2e4, 2.4e4, 4e4, 6e4),
              constant=()):
    """Flat pairs (48 x 48, ADU) in ``path``: level k at EXPTIME exptimes[k]; the pairs
    in ``constant`` are both constant at 65535 (saturated)."""
    path.mkdir()
    for k, level in enumerate(levels):
        for half in "ab":
            img = (np.full((48, 48), 65535.0) if k in constant
                   else rng.poisson(level, (48, 48)).astype(np.float32))
            hdr = fits.Header({"EXPTIME": float(exptimes[k]), "BUNIT": "adu"})
            fits.PrimaryHDU(img, header=hdr).writeto(path / f"flat_{k}{half}.fits")
    return str(path)


def test_ptc_refusals_name_the_input_and_the_reasons(capsys, tmp_path, rng):
    """Issue 44 items 7 and 10: too few levels for the fit names the input (the
    directory and its count, or the file) and why each level was dropped, as
    calibrate does; a PTC text with a third column is refused, not read in part."""
    zero = _flat_dir(tmp_path / "zero", rng, [0.0, -1.0, 3.0, 4.0, 5.0, 6.0])
    code, out, err = _run(capsys, "ptc", zero)
    assert code == 2 and not out
    # after the reading's progress lines (stderr), the error
    assert (f"\nbfdrift: error: {zero}/ (12 files): 4 distinct signal level(s) with a pair of "
            "flats, fewer than min_levels=5") in "\n" + err
    assert "flat_0a.fits: EXPTIME = 0.0 s is not positive (a bias or dark" in err
    assert "flat_1b.fits: EXPTIME = -1.0 s is not positive" in err
    sat = _flat_dir(tmp_path / "sat", rng, range(1, 6), levels=(2e3, 6e3, 1.2e4, 2.4e4, 4e4),
                    constant=(4,))
    code, _, err = _run(capsys, "ptc", sat)
    assert code == 2 and f"{sat}/ (10 files): 4 distinct signal level(s) remain below" in err
    assert "flat_4b.fits: past the PTC turn-off at" in err and "both images are constant" in err
    for name, text, why in (
            ("dec.txt", "".join(f"{m} {1e5 / m}\n" for m in (100, 200, 300, 400, 500)),
             "1 distinct signal level(s) remain below the PTC turn-off, fewer than "
             "min_levels=4; a photon transfer curve needs at least 4 levels below the "
             "turn-off; dropped 4 for the same reason (points 1, 2, 3, 4): past the PTC "
             "turn-off at 100 ADU"),
            ("two.txt", "100 50\n200 100\n", "2 distinct signal level(s) remain below"),
            ("three.txt", "".join(f"{m} {m / 2} 1\n" for m in (100, 200, 400, 800, 1600)),
             "1: 3 column(s); accepted: two numeric columns (mean ADU, variance ADU^2)")):
        p = tmp_path / name
        p.write_text(text)
        code, out, err = _run(capsys, "ptc", str(p))
        assert code == 2 and not out and f"bfdrift: error: {p}:" in err and why in err, err
        assert "Traceback" not in err


def test_ptc_names_a_pair_of_one_exposure_twice(capsys, tmp_path, rng):
    """Issue 44 item 9: ``bfdrift ptc`` on flats where one pair is a file and its copy:
    that pair is excluded and named (the brighter pairs are not dropped as past a
    turn-off), and the fit uses the other five."""
    import shutil

    d = _flat_dir(tmp_path / "dup", rng, range(1, 7))
    shutil.copyfile(tmp_path / "dup" / "flat_2a.fits", tmp_path / "dup" / "flat_2b.fits")
    code, text, err = _run(capsys, "ptc", d, "--max-lag", "1")
    assert code == 0, err
    assert "5 pair(s) at 5 level(s)" in text
    assert "flat_2a.fits, flat_2b.fits (the two images are one exposure" in text
    assert "turn-off" not in text
