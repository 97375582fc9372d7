"""Tests of the file helpers (atomic output)."""

import json
import os

import pytest

from lsst_bfdrift.utils.io import atomic_output, write_json, write_text


def test_write_text_and_json(tmp_path):
    write_text(tmp_path / "a.txt", "one\ntwo\n")
    assert (tmp_path / "a.txt").read_text() == "one\ntwo\n"
    write_json(tmp_path / "sub" / "b.json", {"x": 1.5, "y": [1, 2]}, indent=2)
    assert json.loads((tmp_path / "sub" / "b.json").read_text()) == {"x": 1.5, "y": [1, 2]}


def test_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    """A write that fails half-way (an object json cannot encode) keeps the
    previous file whole and leaves no temporary file behind."""
    path = tmp_path / "r.json"
    write_json(path, {"ok": True})
    with pytest.raises(TypeError):
        write_json(path, {"ok": True, "bad": object()})
    assert json.loads(path.read_text()) == {"ok": True}
    assert sorted(os.listdir(tmp_path)) == ["r.json"]
    with pytest.raises(FileExistsError, match="exists"):
        with atomic_output(path, overwrite=False):
            pass


def test_temporary_is_removed_on_any_exception_and_named_tmp(tmp_path):
    """KeyboardInterrupt (not an Exception) mid-write leaves no .tmp-* file."""
    from lsst_bfdrift.utils.io import TMP_PREFIX, is_temporary
    seen = []
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(tmp_path / "a.fits") as tmp:
            seen.append(tmp)
            with open(tmp, "w") as fh:
                fh.write("partial")
            raise KeyboardInterrupt
    assert os.path.basename(seen[0]).startswith(TMP_PREFIX) and is_temporary(seen[0])
    assert os.listdir(tmp_path) == []


def test_check_output_one_rule(tmp_path):
    """An existing output needs overwrite; an input is never an output, even
    through a symbolic link, a relative path or a hard link."""
    from lsst_bfdrift.utils.errors import OutputExistsError
    from lsst_bfdrift.utils.io import check_output
    src, out = tmp_path / "in.fits", tmp_path / "out.fits"
    src.write_text("data")
    check_output(out, [src])  # a new file is fine
    out.write_text("old")
    with pytest.raises(OutputExistsError, match="--out .*out.fits exists .*--overwrite"):
        check_output(out, [src], what="--out")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        check_output(out, [src])
    check_output(out, [src], overwrite=True)
    (tmp_path / "link.fits").symlink_to(src)
    os.link(src, tmp_path / "hard.fits")
    for alias in (src, tmp_path / "link.fits", tmp_path / "hard.fits",
                  os.path.relpath(src)):
        with pytest.raises(OutputExistsError, match="one of the inputs"):
            check_output(alias, [src], overwrite=True)
    with pytest.raises(OutputExistsError, match="is a directory"):
        check_output(tmp_path, [], overwrite=True)


def test_atomic_output_applies_the_rule_and_names_the_output(tmp_path):
    from lsst_bfdrift.utils.errors import OutputExistsError
    src = tmp_path / "in.txt"
    src.write_text("keep")
    with pytest.raises(OutputExistsError, match="one of the inputs"):
        with atomic_output(src, inputs=[src]):
            pass
    assert src.read_text() == "keep"
    out = tmp_path / "out.txt"
    with pytest.raises(OSError, match="cannot write .*out.txt: No space left") as info:
        with atomic_output(out) as tmp:
            raise OSError(28, "No space left on device", tmp)  # e.g. a full disk
    assert ".tmp-" not in str(info.value) and info.value.errno == 28
    assert sorted(os.listdir(tmp_path)) == ["in.txt"]


def test_data_files_skip_temporaries(tmp_path):
    from lsst_bfdrift.utils.io import data_files
    for name in ("b.fits", "a.FITS", ".tmp-abc.fits", "notes.txt"):
        (tmp_path / name).write_text("x")
    (tmp_path / "d.fits").mkdir()
    assert data_files(tmp_path, (".fits",)) == [str(tmp_path / "a.FITS"),
                                                 str(tmp_path / "b.fits")]


def test_truncated_fits_is_named(tmp_path):
    """A truncated FITS gives an error naming the file and saying so (was
    numpy's 'cannot reshape array'), in every shared image loader."""
    import numpy as np
    from astropy.io import fits

    from lsst_bfdrift.correction.task import unpack_exposure
    from lsst_bfdrift.utils.errors import InputFileError
    from lsst_bfdrift.utils.io import read_image
    full = tmp_path / "full.fits"
    fits.PrimaryHDU(np.random.default_rng(3).normal(size=(64, 64))).writeto(full)
    cut = tmp_path / "cut.fits"
    cut.write_bytes(full.read_bytes()[:2880 + 3600])
    with pytest.warns(Warning, match="truncated"):
        with pytest.raises(InputFileError, match="cut.fits: truncated"):
            read_image(cut)
    with pytest.warns(Warning, match="truncated"):
        with pytest.raises(InputFileError, match="cut.fits: truncated"):
            unpack_exposure(str(cut), None)
    (tmp_path / "empty.fits").write_bytes(b"")
    with pytest.raises(InputFileError, match="empty.fits: not a readable FITS"):
        read_image(tmp_path / "empty.fits")
    with pytest.raises(FileNotFoundError, match="nope.fits"):
        read_image(tmp_path / "nope.fits")
