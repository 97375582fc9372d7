"""LSST middleware route: a PipelineTask that runs under ``pipetask`` on a Butler.

Takes a post-ISR exposure (electrons) from a Butler repository and gives the
corrected exposure and the final pixel geometry maps, with
:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask` doing the work
as a subtask. Needs the ``[lsst]`` extra (``lsst-pipe-base``,
``lsst-daf-butler``, ``lsst-ctrl-mpexec``); the rest of the package does not.

* :mod:`~lsst_bfdrift.pipeline.task`: connections, config and the PipelineTask;
* :mod:`~lsst_bfdrift.pipeline.formatters`: Butler formatters of the storage
  classes ``BfdriftExposure`` (the LSST Exposure FITS layout, without afw)
  and ``BfdriftGeometryMaps``;
* :mod:`~lsst_bfdrift.pipeline.ingest`: FITS exposures put into a run
  collection with their data IDs (``bfdrift butler-put``);
* ``butler_seed.yaml``: the storage classes and formatters for
  ``butler create --seed-config``; ``bfdrift.yaml``: a pipeline using the task.
"""

import os

try:
    import lsst.pipe.base  # noqa: F401
except ImportError as exc:  # pragma: no cover - the core install
    raise ImportError("lsst_bfdrift.pipeline needs the LSST middleware: "
                      "pip install 'lsst_bfdrift[lsst]'") from exc

from lsst_bfdrift.pipeline.task import *  # noqa: F401,F403,E402
from lsst_bfdrift.pipeline.ingest import put_exposures  # noqa: E402

__all__ = ["BrighterFatterDriftPipelineTask", "BrighterFatterDriftPipelineConfig",
           "BrighterFatterDriftConnections", "pipeline_path", "seed_config_path",
           "put_exposures"]


def pipeline_path():
    """Path of the bundled pipeline YAML (``bfdrift.yaml``)."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "bfdrift.yaml")


def seed_config_path():
    """Path of the Butler seed config declaring the package's storage classes."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "butler_seed.yaml")
