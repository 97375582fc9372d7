"""Tests of lsst_bfdrift.physics.features: edge roll-off and midline."""

import numpy as np
import pytest
from numpy.testing import assert_allclose

from lsst_bfdrift.physics.features import edge_rolloff, midline
from lsst_bfdrift.validation.paper_figures import paper_parameters


@pytest.fixture(scope="module")
def edge():
    return edge_rolloff(paper_parameters(), xi_guard=(-3.0, 0.0, 3.0), n_columns=16,
                        edge_samples=4, tol=3e-4)


def test_edge_rolloff_profile(edge):
    for g in (-3.0, 0.0, 3.0):
        s = edge[edge["setting"] == g]
        area = np.asarray(s["area"])
        assert area[0] < 0.95 and abs(area[-1] - 1) < 0.02  # rolls off to ~1 px^2
        # monotonic recovery inwards (beyond ~8 columns the steps fall below the
        # bisection tolerance of this quick test)
        assert np.all(np.diff(area[1:9]) > 0)
        assert np.all(np.diff(area[1:]) > -1e-3)
        assert s["dx"][0] > 0.1  # outer pixels shifted inwards (astrometric error)
    # a guard dipole pointing into the array (negative drain bias) helps the
    # outermost column most
    a0 = {g: edge[edge["setting"] == g]["area"][0] for g in (-3.0, 0.0, 3.0)}
    assert a0[3.0] > a0[0.0] > a0[-3.0]


def test_midline_symmetry_and_conservation():
    t = midline(paper_parameters(), v_bss=(-70.0, -40.0), n_rows=14, edge_samples=8, tol=1e-4)
    deficit = {}
    for v in (-70.0, -40.0):
        s = t[t["setting"] == v]
        area = np.asarray(s["area"])
        # mirror symmetric about the bloom stop (row boundary 0)
        assert_allclose(area, area[::-1], atol=2e-3)
        assert_allclose(np.asarray(s["dy"]), -np.asarray(s["dy"])[::-1], atol=2e-3)
        # the two rows beside the implant (rows -1 and 0) lose area, their
        # neighbours gain
        assert area[13] < 0.9 and area[14] < 0.9 and area[12] > 1.0
        # boundaries are only rearranged: the total change over the strip vanishes
        assert abs(np.sum(area - 1)) < 0.05 * np.sum(np.abs(area - 1))
        deficit[v] = 1 - area[13]
    # a weaker backside bias lets the implant redistribute more
    assert deficit[-40.0] > deficit[-70.0]
