"""Tests of lsst_bfdrift.pipeline: the PipelineTask under ``pipetask run`` on a Butler.

A SQLite Butler repository is made for the tests with the package's seed
config; LSST-layout exposures written with astropy are put into it;
``pipetask run -j 2`` (the real ctrl_mpexec command, in a subprocess) runs the
bundled pipeline; the outputs are read back from the Butler and from the
datastore's files. The corrected images are compared with the same Task run
directly (a consistency check: the pipeline must add nothing and lose
nothing), and flux conservation and untouched masked pixels are checked
against the inputs (conservation laws, independent of the model).
"""

import subprocess
import sys

import numpy as np
import pytest
from astropy.io import fits
from numpy.testing import assert_allclose, assert_array_equal

pytest.importorskip("lsst.ctrl.mpexec")  # the [lsst] extra; part of [test]

from lsst.daf.butler import Butler, Config, DatasetType  # noqa: E402

import lsst_bfdrift.pipeline as bfpipe  # noqa: E402
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402,E501
from lsst_bfdrift.images.exposure import read_exposure  # noqa: E402

DIMS = ("instrument", "exposure", "detector")
EXPOSURES = (1, 2, 3)
DETECTORS = (0, 1)
SHAPE = (72, 80)


def _pipetask():
    return [sys.executable, "-c", "import sys; from lsst.ctrl.mpexec.cli.pipetask import main; "
            "sys.exit(main())"]


def _lsst_file(path, seed):
    """An LSST Exposure FITS file written with astropy: empty primary, IMAGE (e),
    MASK (int32, MP_ cards, a bad row, a saturated star core, a DETECTED plane),
    VARIANCE, and an extra archive-like HDU."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    img = rng.poisson(800.0, SHAPE).astype(np.float32)
    for y0, x0, flux in ((30.3, 40.6, 4e6), (55.0, 20.2, 1e6)):
        img += (flux / (2 * np.pi * 1.6**2) * np.exp(-((yy - y0)**2 + (xx - x0)**2)
                                                     / (2 * 1.6**2))).astype(np.float32)
    mask = np.zeros(SHAPE, np.int32)
    mask[10, :] |= 1 << 0  # BAD row
    mask[30, 40] |= 1 << 1  # SAT
    mask[img > 5000] |= 1 << 5  # DETECTED: must never block
    mh = fits.Header()
    for name, bit in (("BAD", 0), ("SAT", 1), ("INTRP", 2), ("CR", 3), ("EDGE", 4),
                      ("DETECTED", 5), ("SUSPECT", 7), ("NO_DATA", 8)):
        mh[f"MP_{name}" if len(name) <= 5 else f"HIERARCH MP_{name}"] = bit
    ih = fits.Header({"BUNIT": "electron", "INHERIT": True, "EXTTYPE": "IMAGE"})
    hdus = [fits.PrimaryHDU(header=fits.Header({"DETECTOR": seed, "OBSID": f"x{seed}"})),
            fits.ImageHDU(img, header=ih, name="IMAGE"),
            fits.ImageHDU(mask, header=mh, name="MASK"),
            fits.ImageHDU((img + 25.0).astype(np.float32), name="VARIANCE"),
            fits.BinTableHDU.from_columns([fits.Column(name="id", format="J", array=[1, 2])],
                                          name="ARCHIVE_INDEX")]
    fits.HDUList(hdus).writeto(path)
    return path


def _make_repo(root, files, *, storage_class="BfdriftExposure"):
    Butler.makeRepo(root, config=Config(bfpipe.seed_config_path()))
    butler = Butler.from_config(root, writeable=True, run="bf/inputs")
    reg = butler.registry
    reg.insertDimensionData("instrument", {"name": "BFCam", "detector_max": 4,
                                           "exposure_max": 100, "visit_max": 100,
                                           "class_name": "none"})
    reg.insertDimensionData("physical_filter", {"instrument": "BFCam", "name": "r_01",
                                                "band": "r"})
    reg.insertDimensionData("day_obs", {"instrument": "BFCam", "id": 20261124})
    reg.insertDimensionData("group", {"instrument": "BFCam", "name": "g1"})
    for d in DETECTORS:
        reg.insertDimensionData("detector", {"instrument": "BFCam", "id": d,
                                             "full_name": f"R00_S0{d}"})
    for e in EXPOSURES:
        reg.insertDimensionData("exposure", {"instrument": "BFCam", "id": e, "obs_id": f"e{e}",
                                             "physical_filter": "r_01", "group": "g1",
                                             "day_obs": 20261124})
    reg.registerDatasetType(DatasetType("post_isr_image", DIMS, storage_class,
                                        universe=butler.dimensions))
    for (e, d), path in files.items():
        obj = read_exposure(path) if storage_class == "BfdriftExposure" else {"a": 1}
        butler.put(obj, "post_isr_image", instrument="BFCam", exposure=e, detector=d)
    return butler


@pytest.fixture(scope="module")
def pipetask_run(tmp_path_factory):
    """One ``pipetask run -j 2`` over 3 exposures x 2 detectors (6 quanta)."""
    tmp = tmp_path_factory.mktemp("bfpipe")
    files = {(e, d): _lsst_file(str(tmp / f"in_{e}_{d}.fits"), seed=10 * e + d)
             for e in EXPOSURES for d in DETECTORS}
    root = str(tmp / "repo")
    _make_repo(root, files)
    cmd = _pipetask() + ["run", "-b", root, "-i", "bf/inputs", "-o", "bf/out", "-j", "2",
                         "-p", bfpipe.pipeline_path(), "--register-dataset-types",
                         "-c", "brighterFatterDrift:bf.fft_precision=float64"]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return Butler.from_config(root, collections=["bf/out"]), files, proc


def test_pipetask_outputs_keep_the_layout(pipetask_run):
    """Every output exposure comes back in the input's layout: all HDUs and header
    cards kept, masked pixels untouched, variance present, a BF plane declared."""
    butler, files, _ = pipetask_run
    for (e, d), path in files.items():
        ref = butler.find_dataset("bf_corrected_image", instrument="BFCam", exposure=e,
                                  detector=d)
        uri = butler.getURI(ref)
        with fits.open(path) as src, fits.open(uri.ospath) as out:
            assert [h.name for h in out[:len(src)]] == [h.name for h in src]
            for h_in, h_out in zip(src, out):
                for key in h_in.header:
                    if key not in ("CHECKSUM", "DATASUM", "BITPIX"):
                        assert key in h_out.header, (h_in.name, key)
            bits = {k[3:]: v for k, v in out["MASK"].header.items() if k.startswith("MP_")}
            assert "BF" in bits and bits["BF"] not in \
                [v for k, v in bits.items() if k != "BF"]
            m_in, m_out = src["MASK"].data, out["MASK"].data
            assert_array_equal(m_out & ~np.int32(1 << bits["BF"]), m_in)  # nothing lost
            blocked = (m_in & ((1 << 0) | (1 << 1))) != 0
            assert_array_equal(out["IMAGE"].data[blocked], src["IMAGE"].data[blocked])
            assert out["VARIANCE"].data.shape == SHAPE
            assert np.all(out["VARIANCE"].data >= src["VARIANCE"].data - 1e-3)
            assert_array_equal(out["ARCHIVE_INDEX"].data["id"], [1, 2])
            moved = out["IMAGE"].data.astype(float) - src["IMAGE"].data
            assert abs(moved.sum()) < 1e-5 * np.abs(moved).sum() + 1.0  # float32 file
            assert np.abs(moved).max() > 50.0  # a 4e6 e star: the correction did act


def test_pipetask_matches_the_task(pipetask_run):
    """The pipeline's corrected image and maps are the Task's on the same file."""
    butler, files, _ = pipetask_run
    cfg = BrighterFatterDriftConfig(fft_precision="float64")
    task = BrighterFatterDriftTask(config=cfg)
    for (e, d), path in list(files.items())[:2]:
        direct = task.run(read_exposure(path))
        got = butler.get("bf_corrected_image", instrument="BFCam", exposure=e, detector=d)
        assert_allclose(got.image, direct.exposure.image, rtol=1e-6, atol=1e-3)
        maps = butler.get("bf_geometry_maps", instrument="BFCam", exposure=e, detector=d)
        for name in ("area", "centroid_x", "centroid_y", "e1", "e2"):
            assert_allclose(maps[name], getattr(direct, name), rtol=1e-6, atol=1e-12)
        assert_allclose(maps["flux_moved"], direct.flux_moved, atol=1e-6)
        assert maps["converged"] is True or maps["converged"] == 1


def test_wrong_storage_class_is_refused(tmp_path):
    """An input dataset type of another storage class: pipetask fails with a clear message."""
    files = {(1, 0): str(tmp_path / "unused.fits")}
    root = str(tmp_path / "repo")
    _make_repo(root, files, storage_class="StructuredDataDict")
    cmd = _pipetask() + ["run", "-b", root, "-i", "bf/inputs", "-o", "bf/out",
                         "-p", bfpipe.pipeline_path(), "--register-dataset-types"]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False, timeout=600)
    assert proc.returncode != 0
    assert "post_isr_image" in proc.stderr and "StructuredDataDict" in proc.stderr


def test_connections_follow_the_config():
    """exposure_storage_class switches both exposure connections (ExposureF in a full
    stack); compute_geometry=False drops the maps output."""
    cfg = bfpipe.BrighterFatterDriftPipelineConfig()
    cfg.exposure_storage_class = "ExposureF"
    cfg.bf.compute_geometry = False
    conn = bfpipe.BrighterFatterDriftConnections(config=cfg)
    assert conn.input_exposure.storageClass == "ExposureF"
    assert conn.corrected_exposure.storageClass == "ExposureF"
    assert "geometry_maps" not in conn.outputs
    default = bfpipe.BrighterFatterDriftConnections(config=bfpipe.BrighterFatterDriftPipelineConfig())
    assert default.input_exposure.storageClass == "BfdriftExposure"
    assert "geometry_maps" in default.outputs


def test_afw_shaped_exposure_runs_through_the_pipeline_task():
    """An object with afw's Exposure shape goes through run() unchanged in type,
    and the input is not modified."""
    from tests.pipeline._afw_like import FakeExposure
    rng = np.random.default_rng(3)
    img = rng.poisson(500.0, (48, 48)).astype(np.float32)
    img[24, 24] = 3e5
    exp = FakeExposure(img, planes={"BAD": 0, "SAT": 1, "DETECTED": 5})
    exp.mask.array[5, :] = 1
    before = exp.image.array.copy(), exp.mask.array.copy()
    task = bfpipe.BrighterFatterDriftPipelineTask(config=bfpipe.BrighterFatterDriftPipelineConfig())
    res = task.run(exp)
    out = res.corrected_exposure
    assert type(out) is FakeExposure and out is not exp
    assert_array_equal(exp.image.array, before[0])
    assert_array_equal(exp.mask.array, before[1])
    assert "BF" in out.mask.getMaskPlaneDict()
    assert_array_equal(out.image.array[5, :], img[5, :])  # BAD row untouched
    assert abs(out.image.array.astype(float).sum() - img.astype(float).sum()) < 1.0
    assert res.geometry_maps["area"].shape == img.shape


def test_pipeline_files_exist():
    """The bundled pipeline names the task; the seed config declares both storage classes."""
    import yaml
    with open(bfpipe.pipeline_path()) as fh:
        pipe = yaml.safe_load(fh)
    assert pipe["tasks"]["brighterFatterDrift"]["class"] == \
        "lsst_bfdrift.pipeline.BrighterFatterDriftPipelineTask"
    with open(bfpipe.seed_config_path()) as fh:
        seed = yaml.safe_load(fh)
    assert set(seed["storageClasses"]) == set(seed["datastore"]["formatters"]) == \
        {"BfdriftExposure", "BfdriftGeometryMaps"}


def test_run_quantum_corrects_with_the_data_id_band(tmp_path):
    """CONSISTENCY: runQuantum passes the data ID's physical_filter (r_01): a multi-band
    template's r template is used for a file without BAND/FILTER, recorded in BFBAND."""
    from lsst.pipe.base.testUtils import makeQuantum, runTestQuantum

    from lsst_bfdrift.templates.bands import MultiBandTemplate, combine_templates
    from lsst_bfdrift.templates.template import load_default_template
    d = load_default_template()
    half = combine_templates([d], [0.5])
    tpath = tmp_path / "bands.fits"
    MultiBandTemplate({"r": half, "y": d}).save(tpath)
    path = _lsst_file(str(tmp_path / "in.fits"), seed=4)
    butler = _make_repo(str(tmp_path / "repo"), {(1, 0): path})
    butler.registry.registerDatasetType(DatasetType("bf_corrected_image", DIMS,
                                                    "BfdriftExposure",
                                                    universe=butler.dimensions))
    config = bfpipe.BrighterFatterDriftPipelineConfig()
    config.bf.template = str(tpath)
    config.bf.compute_geometry = False
    task = bfpipe.BrighterFatterDriftPipelineTask(config=config)
    data_id = butler.registry.expandDataId(instrument="BFCam", exposure=1, detector=0)
    assert bfpipe.data_id_band(data_id) == "r_01"
    quantum = makeQuantum(task, butler, data_id, {"input_exposure": data_id,
                                                  "corrected_exposure": data_id})
    runTestQuantum(task, butler, quantum, mockRun=False)
    got = butler.get("bf_corrected_image", instrument="BFCam", exposure=1, detector=0)
    direct = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False),
                                     template=half).run(read_exposure(path))
    assert_allclose(got.image, direct.exposure.image, rtol=1e-6, atol=1e-3)
    assert got.header_value("BFBAND") == "r"
    with pytest.raises(ValueError, match=r"gives no band \(read header keywords BAND, FILTER"):
        task.run(read_exposure(path))  # outside the Butler: no data ID, no keyword
