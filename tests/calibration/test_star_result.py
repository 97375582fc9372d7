"""Tests of lsst_bfdrift.calibration.star_result (independent reference: the
forward Gaussian update, precision^-2 = flats^-2 + fields x per-field
information, evaluated directly)."""

import numpy as np
import pytest

from lsst_bfdrift.calibration.star_result import fields_for_precision


def _stated(flats, per_field, n):
    """Precision the flats and n fields state (forward Gaussian update)."""
    return 1.0 / np.sqrt(1.0 / flats ** 2 + n * per_field)


@pytest.mark.parametrize("flats, joint, n_fields, goal", [
    (29.2, 8.7, 2, 3.0),     # GalSim lsst_itl_32, two fields (the held-out benchmark)
    (8.1, 4.1, 12, 3.0),     # GalSim ITL, twelve fields
    (18.2, 6.9, 1, 1.5),
    (300.0, 40.0, 3, 5.0),
])
def test_fields_for_precision_is_the_fewest_that_reach_the_goal(flats, joint, n_fields, goal):
    need = fields_for_precision(flats, joint, n_fields, goal)
    per_field = (1.0 / joint ** 2 - 1.0 / flats ** 2) / n_fields
    assert _stated(flats, per_field, need) <= goal * (1 + 1e-9)
    assert _stated(flats, per_field, need - 1) > goal
    # the fitted fields themselves give back the joint precision
    assert np.isclose(_stated(flats, per_field, n_fields), joint)


def test_fields_for_precision_when_met_or_not_measurable():
    assert fields_for_precision(2.5, 1.0, 4, 3.0) == 0          # the flats alone meet it
    assert fields_for_precision(6.0, 2.0, 4, 3.0) <= 4           # these fields meet it
    assert fields_for_precision(6.0, 6.0, 4, 3.0) is None        # the stars add nothing
    assert fields_for_precision(6.0, float("nan"), 4, 3.0) is None
    with pytest.raises(ValueError, match="must be > 0 and n_fields >= 1"):
        fields_for_precision(6.0, 2.0, 0, 3.0)
    with pytest.raises(ValueError, match="must be > 0"):
        fields_for_precision(6.0, 2.0, 2, -1.0)
