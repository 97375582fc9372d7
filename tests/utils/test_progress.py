"""Tests of lsst_bfdrift.utils.progress (a consistency check of the printed lines)."""

import io

import pytest

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


def test_stages_share_one_bar_by_weight():
    """StageProgress: the bar stands at the stages done plus the fraction of
    the current one, labelled with it; it never goes back, and stages that
    are not weighted are ignored."""
    from lsst_bfdrift.utils.progress import StageProgress
    out = io.StringIO()
    with StageProgress({"read": 1, "maps": 8, "skipped": 0, "write": 1}, "a.fits",
                       stream=out) as progress:
        progress("read", 1.0)
        assert progress.bar.done == 100
        progress("maps", 0.5)
        assert progress.bar.done == 500 and progress.bar.label == "a.fits: maps"
        progress("maps", 0.25)  # never back
        progress("skipped", 1.0)
        progress("unknown", 1.0)
        assert progress.bar.done == 500 and progress.bar.label == "a.fits: maps"
        progress("write", 0.0)
        assert progress.bar.done == 900
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("a.fits: read  10.0%")
    assert lines[1].startswith("a.fits: maps  50.0%")
    assert lines[2].startswith("a.fits: write  90.0%")
    assert lines[-1].startswith("a.fits: done 100.0%")
    quiet = io.StringIO()
    with StageProgress({"read": 1}, "b", stream=quiet, enabled=False) as progress:
        progress("read", 1.0)
    assert quiet.getvalue() == ""


def test_terminal_redraw_blanks_a_longer_previous_line():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    out = Tty()
    with ProgressBar(2, "a much longer label", stream=out) as bar:
        bar(1)
        bar.label = "short"
    first, last = out.getvalue().split("\r")[1:3]
    assert len(last.rstrip("\n")) >= len(first) and last.startswith("short [")


def test_stage_weights_follow_the_tasks_order():
    """bfdrift correct's stages are weighted in the order the Task reports
    them: the linear maps (from the correction's first pass) after the
    correction, the exact maps before it."""
    from lsst_bfdrift.correction.batch import stage_weights
    assert list(stage_weights()) == ["read", "correct", "maps", "write"]
    assert list(stage_weights({"geometry_method": "exact"})) == ["read", "maps", "correct",
                                                                  "write"]
    w = stage_weights({"compute_geometry": False})
    assert w["maps"] == 0.0 and w["correct"] > 0


def test_stage_weights_are_the_measured_seconds():
    """The weights are benchmarks/performance/stage_timings_results.json's medians."""
    import json
    import os

    from lsst_bfdrift.correction.batch import STAGE_SECONDS, stage_weights
    path = os.path.join(os.path.dirname(__file__), "..", "..", "benchmarks",
                        "performance", "stage_timings_results.json")
    with open(path) as fh:
        med = json.load(fh)["medians"]
    for mode, name in (("none", "no maps"), ("linear", "default"), ("exact", "exact maps")):
        for stage, sec in med[name].items():
            assert STAGE_SECONDS[mode][stage] == pytest.approx(sec, abs=0.005), (mode, stage)
    assert stage_weights() == STAGE_SECONDS["linear"]
    assert stage_weights({"geometry_method": "exact"}) == STAGE_SECONDS["exact"]


def test_a_failed_job_ends_failed_not_done():
    """Issue 43 item 3: a job that failed ends labelled 'failed' where it stood,
    not 'done 100.0%', and says so even when it stopped within a decile."""
    from lsst_bfdrift.utils.progress import StageProgress
    s = io.StringIO()
    with StageProgress({"read": 1, "work": 9}, "job", stream=s) as stages:
        stages("read", 0.0)
        stages.fail()
    text = s.getvalue()
    assert "done" not in text and "100.0%" not in text
    assert text.splitlines()[-1].startswith("job: failed   0.0%")
    s = io.StringIO()
    with ProgressBar(10, "bar", stream=s) as bar:
        bar(3)
        bar.fail()
    assert s.getvalue().splitlines()[-1].startswith("bar  30.0%") and "ETA" not in \
        s.getvalue().splitlines()[-1]


def test_activity_says_what_runs_at_its_first_step_and_how_long_it_took():
    """Issue 43 item 1: work of unknown length (an iterative fit) says its label at
    its first step, and at the end its time and step count; no step: silent."""
    from lsst_bfdrift.utils.progress import Activity
    out = io.StringIO()
    with Activity("ptc: covariance model fit", unit="model evaluations", stream=out) as act:
        assert out.getvalue() == ""
        for _ in range(5):
            act()
    lines = out.getvalue().splitlines()
    assert lines[0] == "ptc: covariance model fit ..."
    assert lines[-1].startswith("ptc: covariance model fit: done in ")
    assert lines[-1].endswith("(5 model evaluations)")
    quiet = io.StringIO()
    with Activity("nothing", stream=quiet):
        pass
    assert quiet.getvalue() == ""


def test_a_log_gets_a_line_per_stage_and_after_a_silent_stretch(monkeypatch):
    """A new stage is said when it starts, and a slow stretch within a decile
    still gets a line after `every` seconds."""
    from lsst_bfdrift.utils import progress as pmod
    from lsst_bfdrift.utils.progress import StageProgress
    clock = [0.0]
    monkeypatch.setattr(pmod.time, "perf_counter", lambda: clock[0])
    out = io.StringIO()
    with StageProgress({"fit": 1, "build": 1}, "calibrate", stream=out) as stages:
        stages("fit", 0.0)
        clock[0] = 30.0
        stages("fit", 0.02)  # within the first decile, 30 s later
        stages("build", 0.0)
    lines = out.getvalue().splitlines()
    assert lines[0].startswith("calibrate: fit   0.0%")
    assert lines[1].startswith("calibrate: fit   1.0%")
    assert lines[2].startswith("calibrate: build  50.0%")
