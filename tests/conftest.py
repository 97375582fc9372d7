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
import subprocess
import sys
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
    share (tests/_shared.py); the workers, started after it, inherit it. With
    workers, the numba kernels are compiled first, once, by the workloads of
    tests/_warm.py side by side (``BFDRIFT_TEST_WARM=0`` skips it)."""
    if hasattr(config, "workerinput"):
        return
    if SHARED_ENV not in os.environ:
        config._bfdrift_shared = tempfile.mkdtemp(prefix="bfdrift-tests-")
        os.environ[SHARED_ENV] = config._bfdrift_shared
    if getattr(config.option, "numprocesses", None) and \
            os.environ.get("BFDRIFT_TEST_WARM", "1") != "0":
        _warm_numba(str(config.rootpath))


def _warm_numba(root):
    """Run tests/_warm.py's parts side by side; a part that fails only costs its
    kernels' compilation in the workers, as without the warm-up (said on stderr)."""
    from tests._warm import PARTS

    procs = {p: subprocess.Popen([sys.executable, "-m", "tests._warm", p], cwd=root,
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
             for p in PARTS}
    for part, proc in procs.items():
        _, err = proc.communicate()
        if proc.returncode:
            sys.stderr.write(f"tests/_warm.py {part} failed (kernels compile in the "
                             f"workers instead): {err.strip().splitlines()[-1:]}\n")


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
