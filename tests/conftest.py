"""Shared fixtures: small, fast templates built once per test session."""

import os

if "PYTEST_XDIST_WORKER" in os.environ:
    # one worker per core: GalSim's OpenMP threads on top of them oversubscribe
    # the cores (star drawing 8 times slower); set before GalSim is loaded
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    # likewise numba's parallel kernels: two workers of two threads each on two
    # cores made the numba-bound tests 35 % slower than one thread per worker
    os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import shutil
import tempfile

import numpy as np
import pytest
from hypothesis import settings

from tests._shared import SHARED_ENV

# Property-based tests (tests/test_fuzz.py): seeded and derandomized, so every run
# generates the same cases; BFDRIFT_HYPOTHESIS=extended runs ten times more.
settings.register_profile("ci", max_examples=100, derandomize=True, deadline=None,
                          database=None, print_blob=True)
settings.register_profile("extended", max_examples=1000, derandomize=True, deadline=None,
                          database=None, print_blob=True)
settings.load_profile(os.environ.get("BFDRIFT_HYPOTHESIS", "ci"))

from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import TemplateSettings, build_template


def pytest_configure(config):
    """On the controlling process: a directory for the data the xdist workers
    share (tests/_shared.py); the workers, started after it, inherit it."""
    if not hasattr(config, "workerinput") and SHARED_ENV not in os.environ:
        config._bfdrift_shared = tempfile.mkdtemp(prefix="bfdrift-tests-")
        os.environ[SHARED_ENV] = config._bfdrift_shared


def pytest_unconfigure(config):
    directory = getattr(config, "_bfdrift_shared", None)
    if directory:
        shutil.rmtree(directory, ignore_errors=True)
        os.environ.pop(SHARED_ENV, None)


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
