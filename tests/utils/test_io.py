"""Tests of the file helpers (atomic output)."""

import json
import os
import re

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

def _dead_pid():
    """The PID of a process that has ended (a child waited for)."""
    import subprocess
    import sys
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_temporary_names_carry_pid_and_host(tmp_path):
    from lsst_bfdrift.utils.io import _host_tag, temporary_owner
    with atomic_output(tmp_path / "a.fits") as tmp:
        assert temporary_owner(tmp) == (os.getpid(), _host_tag())
        assert tmp.endswith(".fits")
    assert temporary_owner(tmp_path / "a.fits") is None
    assert temporary_owner(".tmp-killed.fits") is None


def test_stale_temporaries_are_removed_live_ones_kept(tmp_path):
    """A temporary file of a dead process is stale whatever its age; one of a
    running process (this one) is kept whatever its age; files whose owner
    cannot be checked (another host, the old name without a PID) go after
    max_age; other .tmp-* files and data are never touched."""
    import time

    from lsst_bfdrift.utils.io import _host_tag, is_stale_temporary, remove_stale_temporaries
    host = _host_tag()
    old = time.time() - 7200.0
    names = {
        f".tmp-{_dead_pid()}-{host}-abc_1234.fits": True,     # killed run
        f".tmp-{os.getpid()}-{host}-abc_1235.fits": False,    # a live writer
        f".tmp-{os.getpid()}-{host}-abc_1236.fits.old": False,  # live, and old
        ".tmp-12-otherhost-abc_1237.fits": False,             # another host, fresh
        ".tmp-13-otherhost-abc_1238.fits.old": True,          # another host, old
        ".tmp-abcd1234.fits": False,                          # old scheme, fresh
        ".tmp-abcd1235.fits.old": True,                       # old scheme, old
        ".tmp-killed.fits.old": False,                        # not our name
        "flat_1.fits.old": False,                             # data
    }
    for name in names:
        path = tmp_path / name.removesuffix(".old")
        path.write_bytes(b"partial")
        if name.endswith(".old"):
            os.utime(path, (old, old))
    (tmp_path / ".tmp-1-x-abcdefgh.d").mkdir()  # a directory is never removed
    expect = sorted(str(tmp_path / n.removesuffix(".old")) for n, gone in names.items() if gone)
    for name, gone in names.items():
        assert is_stale_temporary(tmp_path / name.removesuffix(".old")) is gone, name
    assert remove_stale_temporaries(tmp_path) == expect
    left = sorted(os.listdir(tmp_path))
    assert left == sorted([n.removesuffix(".old") for n, gone in names.items() if not gone]
                          + [".tmp-1-x-abcdefgh.d"])
    assert remove_stale_temporaries(tmp_path) == []
    assert remove_stale_temporaries(tmp_path / "missing") == []


def test_failing_fits_write_leaves_no_temporary(tmp_path, monkeypatch):
    """A FITS write that fails half-way (disk full) leaves no .tmp-* file and
    no output; the error names the output, not the temporary file."""
    import numpy as np
    from astropy.io import fits

    from lsst_bfdrift.correction.batch import correct_file
    src = tmp_path / "in.fits"
    hdu = fits.PrimaryHDU(np.random.default_rng(5).normal(1000.0, 30.0, (32, 32)))
    hdu.header["BUNIT"] = "electron"
    hdu.writeto(src)

    def full_disk(self, name, *args, **kwargs):
        with open(name, "wb") as fh:
            fh.write(b"SIMPLE  =                    T")  # a partial file
        raise OSError(28, "No space left on device", name)

    monkeypatch.setattr(fits.HDUList, "writeto", full_disk)
    with pytest.raises(OSError, match="cannot write .*out.fits: No space left"):
        correct_file(src, tmp_path / "out.fits")
    assert sorted(os.listdir(tmp_path)) == ["in.fits"]


def test_read_text_rows_headers_and_malformed_rows(tmp_path):
    """Issue 44 item 8: lines without numbers before the data are a header; a row
    mixing numbers and text is malformed, named by its line and field."""
    from lsst_bfdrift.utils.errors import InputFileError
    from lsst_bfdrift.utils.io import read_text_rows

    p = tmp_path / "t.txt"
    p.write_text("# comment\nmean variance\n\n1, 2\n3 4e1\n")
    assert read_text_rows(p, accepted="pairs") == [(4, [1.0, 2.0]), (5, [3.0, 40.0])]
    assert read_text_rows(p, accepted="pairs", limit=1) == [(4, [1.0, 2.0])]
    p.write_text("0 0 -1.333e-06 x\n")
    with pytest.raises(InputFileError, match=re.escape(
            f"{p}:1: field 4 ('x') of the row '0 0 -1.333e-06 x' is not a number (3 of its 4 "
            "fields are numbers, so it is a malformed row, not a header); accepted: rows")):
        read_text_rows(p, accepted="rows")
    p.write_bytes(b"1 2\n\xff\xfe\n")
    with pytest.raises(InputFileError, match="t.txt: not a text file"):
        read_text_rows(p, accepted="rows")
