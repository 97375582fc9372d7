"""Tests of lsst_bfdrift.validation.paper_figures and bfdrift reproduce."""

import json

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.cli.main import main
from lsst_bfdrift.validation.paper_figures import (PAPER, neighbour_recovery, paper_parameters,
                                    radial_fits, radial_profile)
from lsst_bfdrift.templates.template import TemplateSettings, build_template


def test_neighbour_recovery_and_profile(small_template):
    a = small_template.moments().area
    c = small_template.center
    ref = (a[c - 1:c + 2, c - 1:c + 2].sum() - a[c, c] - 8) / (1 - a[c, c])
    assert neighbour_recovery(small_template) == pytest.approx(ref)
    r2, dlna, p_r, e_r = radial_profile(small_template)
    assert r2.size == small_template.size ** 2 - 1 and r2.min() == 1
    # nearest neighbours grow, on the side facing the shrinking aggressor, so
    # their centroids move towards it (p_r < 0)
    near = r2 == 1
    assert np.all(dlna[near] > 0) and np.all(p_r[near] < 0)
    # a pure power law gives back its exponent
    assert radial_fits(small_template, r2_range=(1, 8))["slope_area"] < 0


def test_calibrated_parameters_reproduce_the_papers_areas():
    s = build_template(paper_parameters(),
                       TemplateSettings(size=3, edge_samples=32, tol=1e-4,
                                        workers=1)).summary()
    for k in ("A00", "A01", "A10"):
        assert s[k] == pytest.approx(PAPER[k], abs=3e-4)
    assert s["A11"] == pytest.approx(PAPER["A11"], abs=5e-4)
    assert 2.6 < s["ratio_01_10"] < 3.1


def test_cli_quick(capsys, tmp_path):
    code = main(["reproduce", "--quick", "--json", "--quiet", "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert code == 0, err
    n = json.loads(out)
    for key in ("A00", "A01", "A10", "A11", "ratio_01_10", "slope_area", "slope_shift",
                "slope_ellipticity", "neighbour_recovery"):
        assert set(n[key]) == {"paper", "package"}
    assert n["xi0_si"] > 0 and n["channel_depth_um"] > 0
    assert np.shape(n["ratio_scan"]["ratio_01_10"]) == (2, 2)
    for f in ("ratio_scan.png", "radial.png", "template.png", "reproduce.json",
              "paper_template.fits", "recovery.png", "edge_rolloff.png",
              "edge_rolloff_contours.png", "midline.png", "midline_contours.png",
              "tearing_contours.png", "tearing_profile.png", "tearing_onset.png", "bamboo.png",
              "bamboo_contours.png", "prnu.png"):
        assert (tmp_path / f).exists()
    feats = n["features"]
    for key in ("edge_rolloff", "midline", "tearing_onset", "bamboo", "prnu"):
        assert feats[key]
    # the unweakened stop is the regular grid; the removed one distorts
    assert feats["tearing_onset"]["f=0"]["max_abs_dA"] < 1e-3
    assert feats["tearing_onset"]["f=1"]["max_abs_dA"] > 0.1
    # clock jitter leaves no structure along the serial axis, channel stops
    # none along the parallel axis
    assert feats["prnu"]["jitter"]["D1_serial"] == 0.0
    assert feats["prnu"]["channel_stop"]["D1_parallel"] == 0.0
    assert_allclose(n["A00"]["package"], PAPER["A00"], atol=2e-3)
