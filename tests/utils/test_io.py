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
