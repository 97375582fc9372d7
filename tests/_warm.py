"""Compile the package's numba kernels once, before the pytest-xdist workers start.

``python -m tests._warm PART`` runs a small workload that calls the kernels of
one part of the package, so that numba writes them to its on-disk cache
(``cache=True``); ``tests/conftest.py`` runs the parts side by side on the
controlling process. Without it every worker (and every subprocess a test
starts: ``pipetask -j 2``, the README's command lines) compiles the same
kernels itself on a fresh install. A kernel this workload misses is compiled
where it is first called, as before: the warm-up changes no test's result.
"""

import os
import sys

__all__ = ["PARTS", "warm"]

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("NUMBA_NUM_THREADS", "1")  # the workers' setting (tests/conftest.py)


def _image():
    import numpy as np

    rng = np.random.default_rng(1)
    y, x = np.mgrid[:96, :96]
    img = 800.0 + 2e5 * np.exp(-((x - 40.3) ** 2 + (y - 51.7) ** 2) / 4.5)
    return rng.normal(img, np.sqrt(img)), rng.normal(5e4, 220.0, (96, 96))


def _geometry():
    import numpy as np

    from lsst_bfdrift import BrighterFatterDriftTask

    star, flat = _image()
    BrighterFatterDriftTask().run(star)  # the default: drift with the geometry maps
    BrighterFatterDriftTask().run(flat)
    sparse = np.full((320, 320), 800.0)  # one star on a wide sky: the maps' windows
    sparse[150:246, 100:196] = star
    BrighterFatterDriftTask().run(sparse)


def _correction_and_physics():
    from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    from lsst_bfdrift.physics.sensor import SensorParameters
    from lsst_bfdrift.templates.galsim_io import galsim_effective_moves
    from lsst_bfdrift.templates.template import TemplateSettings, build_template

    star, flat = _image()
    cfg = BrighterFatterDriftConfig(compute_geometry=False)
    BrighterFatterDriftTask(config=cfg).run(star)
    BrighterFatterDriftTask(config=cfg).run(flat)
    build_template(SensorParameters.paper(), TemplateSettings(size=3, edge_samples=2, tol=1e-2))
    galsim_effective_moves("lsst_itl_50_8", cells=200, engine="rules")
    _photons()


def _photons():
    import numpy as np

    from lsst_bfdrift.simulation.stars import StarSimulation
    from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
    from lsst_bfdrift.templates.template import load_default_template

    rng = np.random.default_rng(2)
    x, y = rng.normal(15.3, 1.5, (2, 3000))
    StarSimulation(load_default_template(), stamp_size=31, update_every=1000).add(x, y)
    StarSimulation(import_galsim_sensor("lsst_itl_50_8"), stamp_size=31, update_every=1000,
                   layout="galsim", seed=3).add(x, y)


#: The workloads, by name: run side by side, one process each.
PARTS = {"geometry": _geometry, "correction": _correction_and_physics}


def warm(part):
    """Run the workload ``part`` of :data:`PARTS`."""
    PARTS[part]()


if __name__ == "__main__":
    warm(sys.argv[1])
