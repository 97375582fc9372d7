"""``bfdrift butler-put`` (issue 43 item 2): FITS exposures into a run collection of a
fresh Butler repository with their data IDs, so that the README's Butler lines run
end to end (before, ``pipetask run -i my/isr`` ended with ``MissingCollectionError``
on a fresh repository: nothing said how to put an exposure in)."""

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from astropy.io import fits

pytest.importorskip("lsst.ctrl.mpexec")  # the [lsst] extra; part of [test]

from lsst.daf.butler import Butler, Config  # noqa: E402

import lsst_bfdrift.pipeline as bfpipe  # noqa: E402
from lsst_bfdrift.cli.main import main  # noqa: E402
from lsst_bfdrift.pipeline.ingest import parse_data_id, put_exposures  # noqa: E402
from lsst_bfdrift.utils.errors import InputError  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _exposure(path, seed, **cards):
    """A plain FITS image in electrons, a star on sky, with the given header cards."""
    rng = np.random.default_rng(seed)
    img = rng.poisson(800.0, (48, 48)).astype(np.float32)
    img[20:23, 24:27] += 2e5
    fits.PrimaryHDU(img, header=fits.Header({"BUNIT": "electron", **cards})).writeto(path)
    return str(path)


def _readme_butler_block():
    with open(os.path.join(ROOT, "README.md")) as fh:
        text = fh.read()
    after = text.split("On a Butler repository", 1)[1]
    return re.search(r"```bash\n(.*?)```", after, re.S).group(1)


@pytest.mark.slow
def test_readme_butler_lines_run_on_a_fresh_repository(tmp_path):
    """The README's lines, as written, in a fresh directory holding one post-ISR
    exposure isr_1.fits (EXPID, DETECTOR in its header): the repository is made,
    the exposure put, the pipeline run, and the corrected image is found."""
    block = _readme_butler_block()
    assert "bfdrift butler-put REPO isr_*.fits --run my/isr" in block
    _exposure(tmp_path / "isr_1.fits", 1, EXPID=1, DETECTOR=0, FILTER="r")
    env = dict(os.environ, PYTHONPATH=ROOT, OMP_NUM_THREADS="1",
               PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ["PATH"])
    proc = subprocess.run(["bash", "-e", "-c", block], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=1500, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "MissingCollectionError" not in proc.stderr
    assert re.search(r"bf_corrected_image\s+my/bf", proc.stdout), proc.stdout
    butler = Butler.from_config(str(tmp_path / "REPO"), collections=["my/bf"])
    out = butler.get("bf_corrected_image", instrument="MyCam", exposure=1, detector=0)
    assert out.image.shape == (48, 48)


def test_put_exposures_records_the_data_ids(tmp_path, capsys):
    """Data IDs from the headers or --data-id; the dimension records made once;
    the datasets readable back; refusals name the file and what to do."""
    repo = str(tmp_path / "repo")
    Butler.makeRepo(repo, config=Config(bfpipe.seed_config_path()))
    a = _exposure(tmp_path / "a.fits", 1, EXPID=7, DETECTOR=2, FILTER="i",
                  **{"DATE-OBS": "2026-03-04T05:06:07"})
    b = _exposure(tmp_path / "b.fits", 2)
    done = put_exposures(repo, [a], run="my/isr", instrument="MyCam")
    assert done[0]["data_id"] == {"instrument": "MyCam", "exposure": 7, "detector": 2}
    code = main(["butler-put", repo, b, "--run", "my/isr", "--instrument", "MyCam",
                 "--data-id", "exposure=8,detector=2", "--quiet"])
    out = capsys.readouterr().out
    assert code == 0 and "post_isr_image (instrument=MyCam, exposure=8, detector=2)" in out
    assert "next: pipetask run -b" in out
    butler = Butler.from_config(repo, collections=["my/isr"])
    got = butler.get("post_isr_image", instrument="MyCam", exposure=7, detector=2)
    assert np.array_equal(got.image, fits.getdata(a))
    rec = butler.registry.expandDataId(instrument="MyCam", exposure=7, detector=2)
    assert rec.records["exposure"].physical_filter == "i"
    assert rec.records["exposure"].day_obs == 20260304
    # refusals: no ids in the headers; an id twice; already in the run; a bad --data-id
    with pytest.raises(InputError, match=r"b\.fits: no exposure id in its headers.*--data-id"):
        put_exposures(repo, [b], run="my/isr", instrument="MyCam")
    with pytest.raises(InputError, match="the same data ID exposure=9, detector=1"):
        put_exposures(repo, [a, b], run="other", instrument="MyCam",
                      data_ids=[{"exposure": 9, "detector": 1}] * 2)
    with pytest.raises(InputError, match=r"a\.fits: post_isr_image .* is already in run"):
        put_exposures(repo, [a], run="my/isr", instrument="MyCam")
    with pytest.raises(InputError, match="no detector"):
        parse_data_id("exposure=3")
    code = main(["butler-put", str(tmp_path / "nope"), a, "--run", "r", "--instrument", "X"])
    assert code == 2 and "no such repository; make one first: butler create" in \
        capsys.readouterr().err


def test_a_repository_without_the_seed_config_is_refused(tmp_path):
    repo = str(tmp_path / "plain")
    Butler.makeRepo(repo)
    a = _exposure(tmp_path / "a.fits", 1, EXPID=1, DETECTOR=0)
    with pytest.raises(InputError, match="does not know the storage class 'BfdriftExposure'; "
                                         "create it with the package's seed config"):
        put_exposures(repo, [a], run="my/isr", instrument="MyCam")
