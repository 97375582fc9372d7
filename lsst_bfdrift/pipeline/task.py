"""BrighterFatterDriftPipelineTask: the correction as an LSST PipelineTask.

The PipelineTask only wires: it reads the exposure from the Butler, hands it
to its ``bf`` subtask (:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask`)
and writes the corrected exposure and the geometry maps back.

Run it with ``pipetask`` on a repository that knows the package's storage
classes (``butler_seed.yaml``)::

    pipetask run -b REPO -i INPUT_COLLECTION -o OUTPUT_COLLECTION -j 2 \\
        -p $(python -c "import lsst_bfdrift.pipeline as p; print(p.pipeline_path())") \\
        --register-dataset-types

In a full LSST stack with afw, set ``exposure_storage_class`` to ``ExposureF``:
the task accepts afw Exposures (``.image.array``, ``.mask.array``,
``.variance.array``, ``getMetadata()``) as they are.
"""

import dataclasses

import lsst.pex.config as pexConfig
import lsst.pipe.base as pipeBase
import lsst.pipe.base.connectionTypes as cT

from lsst_bfdrift.correction.task import BrighterFatterDriftTask

__all__ = ["BrighterFatterDriftConnections", "BrighterFatterDriftPipelineConfig",
           "BrighterFatterDriftPipelineTask", "MAP_NAMES", "data_id_band"]

_DIMENSIONS = ("instrument", "exposure", "detector")

#: Names of the geometry-map dataset's entries (Struct attribute -> map name).
MAP_NAMES = {"area": "area", "centroid_x": "centroid_x", "centroid_y": "centroid_y",
             "e1": "e1", "e2": "e2", "flux_moved": "flux_moved", "flags": "bfflags"}


class BrighterFatterDriftConnections(pipeBase.PipelineTaskConnections,
                                     dimensions=_DIMENSIONS):
    """One exposure and detector in; the corrected exposure and its maps out."""

    input_exposure = cT.Input(
        doc="post-ISR exposure (electrons), before the brighter-fatter correction",
        name="post_isr_image", storageClass="BfdriftExposure", dimensions=_DIMENSIONS)
    corrected_exposure = cT.Output(
        doc="the exposure corrected for the brighter-fatter effect; same layout, mask plane "
            "BF added", name="bf_corrected_image", storageClass="BfdriftExposure",
        dimensions=_DIMENSIONS)
    geometry_maps = cT.Output(
        doc="final pixel geometry (area, centroid_x/y in px, e1, e2), flux moved (e) and the "
            "correction's flag bits", name="bf_geometry_maps",
        storageClass="BfdriftGeometryMaps", dimensions=_DIMENSIONS)

    def __init__(self, *, config=None):
        super().__init__(config=config)
        if config is None:
            return
        storage = config.exposure_storage_class
        if storage != "BfdriftExposure":
            self.input_exposure = dataclasses.replace(self.input_exposure, storageClass=storage)
            self.corrected_exposure = dataclasses.replace(self.corrected_exposure,
                                                          storageClass=storage)
        if not config.bf.compute_geometry:
            del self.geometry_maps


class BrighterFatterDriftPipelineConfig(pipeBase.PipelineTaskConfig,
                                       pipelineConnections=BrighterFatterDriftConnections):
    """Config of :class:`BrighterFatterDriftPipelineTask`."""

    bf = pexConfig.ConfigurableField(
        target=BrighterFatterDriftTask,
        doc="the correction (template, method, masks, gain; see BrighterFatterDriftConfig)")
    exposure_storage_class = pexConfig.Field(
        doc="storage class of the input and corrected exposures: BfdriftExposure (FITS in "
            "the LSST Exposure layout, no afw needed; declared in butler_seed.yaml) or, in a "
            "full LSST stack, ExposureF", dtype=str, default="BfdriftExposure")


class BrighterFatterDriftPipelineTask(pipeBase.PipelineTask):
    """Correct the brighter-fatter effect of each exposure and detector of a Butler run."""

    ConfigClass = BrighterFatterDriftPipelineConfig
    _DefaultName = "brighterFatterDrift"

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.makeSubtask("bf")

    def runQuantum(self, butlerQC, inputRefs, outputRefs):
        """Read the exposure, correct it with its band's template, write the outputs.

        The band is the data ID's ``physical_filter`` (else ``band``), read
        by :func:`data_id_band`; with a multi-band template it must agree
        with the exposure's BAND/FILTER keyword and ``bf.band``.
        """
        inputs = butlerQC.get(inputRefs)
        outputs = self.run(**inputs, band=data_id_band(butlerQC.quantum.dataId))
        butlerQC.put(outputs, outputRefs)

    def run(self, input_exposure, *, band=None):
        """Correct one exposure.

        Parameters
        ----------
        input_exposure : MaskedExposure or afw Exposure
            Post-ISR exposure in electrons (or ADU with a gain). Never modified.
        band : str, optional
            Its band or physical filter (``runQuantum`` passes the data ID's),
            for a multi-band template (see
            :meth:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask.select_template`).

        Returns
        -------
        lsst.pipe.base.Struct
            ``corrected_exposure`` (same type and layout, BF mask plane added) and
            ``geometry_maps`` (dict of 2-d arrays, see :data:`MAP_NAMES`; None when
            ``bf.compute_geometry`` is off).
        """
        res = self.bf.run(input_exposure, band=band)
        maps = None
        if res.area is not None:
            maps = {name: getattr(res, attr) for attr, name in MAP_NAMES.items()}
            maps.update(iterations=int(res.iterations), converged=bool(res.converged))
        return pipeBase.Struct(corrected_exposure=res.exposure, geometry_maps=maps)


def data_id_band(data_id):
    """The physical filter (else band) of a Butler data ID, or None.

    An exposure's data ID implies its ``physical_filter`` and ``band``
    dimensions when it is expanded (as in ``runQuantum``); a data ID without
    them gives None (the exposure's header then says the band).
    """
    if data_id is None:
        return None
    for name in ("physical_filter", "band"):
        try:
            value = data_id[name]
        except (KeyError, LookupError, TypeError, AttributeError):
            continue
        if value:
            return str(value)
    return None
