"""Shared fixtures: small, fast templates built once per test session."""

import numpy as np
import pytest

from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import TemplateSettings, build_template


@pytest.fixture(scope="session")
def small_settings():
    """5 x 5 neighbourhood, 3 samples per edge, 1e-3 px: a few seconds to build."""
    return TemplateSettings(size=5, edge_samples=3, tol=1e-3, workers=2)


@pytest.fixture(scope="session")
def small_template(small_settings):
    """Template of the default (symmetric) model."""
    return build_template(SensorParameters.paper(), small_settings)


@pytest.fixture
def rng():
    return np.random.default_rng(20151)
