"""Tests of lsst_bfdrift.utils.progress (a consistency check of the printed lines)."""

import io

from lsst_bfdrift.utils.progress import ProgressBar


def test_lines_every_decile_with_an_eta():
    out = io.StringIO()
    with ProgressBar(20, "work", stream=out) as bar:
        for _ in range(20):
            bar(1)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("work   5.0%") or lines[0].startswith("work  10.0%")
    assert all("ETA" in line for line in lines[:-2])  # while running
    assert lines[-1].startswith("work 100.0%") and "ETA" not in lines[-1]
    assert len(lines) <= 12


def test_disabled_is_silent():
    out = io.StringIO()
    with ProgressBar(5, "quiet", stream=out, enabled=False) as bar:
        bar(5)
    assert out.getvalue() == ""
