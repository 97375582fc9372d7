"""The Examples sections of the public docstrings run and give what they show.

Consistency of the documentation with the code (each example states an
independent fact too: the unit square's moments, flux conservation, GalSim's
Gaussian size, the exact polygon moments).
"""

import doctest
import importlib

import pytest

MODULES = ["lsst_bfdrift.physics.drift", "lsst_bfdrift.physics.polygons",
           "lsst_bfdrift.physics.depth",
           "lsst_bfdrift.templates.template", "lsst_bfdrift.templates.galsim_io",
           "lsst_bfdrift.geometry.superpose",
           "lsst_bfdrift.geometry.linear", "lsst_bfdrift.correction.task",
           "lsst_bfdrift.catalogs.catalog", "lsst_bfdrift.ptc.acoeffs"]


@pytest.mark.parametrize("name", MODULES)
def test_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
                             report=True)
    assert result.attempted > 0, f"{name} has no examples"
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples of {name} failed"
