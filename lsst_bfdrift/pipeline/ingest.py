"""Put FITS exposures into a Butler repository, ready for ``pipetask run``.

:func:`put_exposures` is what ``bfdrift butler-put`` runs: on a repository
made with the package's seed config (``butler create REPO --seed-config
...``), it records the instrument, detectors and exposures the data IDs
name (when the repository does not know them yet), registers the input
dataset type of the pipeline (``post_isr_image``: dimensions instrument,
exposure, detector; storage class ``BfdriftExposure``) and puts each file,
read as :func:`~lsst_bfdrift.images.exposure.read_exposure` reads it, into
a run collection. ``pipetask run -b REPO -i RUN ...`` then finds them.

This is a minimal registration for files that come without an LSST
instrument package (``butler ingest-raws`` needs one): the dimension
records hold the data ID and what the headers say (``FILTER``,
``DATE-OBS``), nothing more. A repository of a real instrument already has
its records; they are used as they are.
"""

import datetime
import os
import re

from lsst.daf.butler import Butler, ButlerConfig, DatasetType
from lsst.daf.butler.registry import ConflictingDefinitionError

from lsst_bfdrift.images.exposure import read_exposure
from lsst_bfdrift.pipeline.task import BrighterFatterDriftConnections
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.io import open_fits

__all__ = ["INPUT_DATASET_TYPE", "DATA_ID_KEYS", "parse_data_id", "header_data_id",
           "put_exposures"]

#: The pipeline's input dataset type (its ``input_exposure`` connection).
INPUT_DATASET_TYPE = BrighterFatterDriftConnections.input_exposure.name

#: Header keywords read for each key of the data ID, in order of preference.
DATA_ID_KEYS = {"exposure": ("EXPOSURE", "EXPID", "EXPNUM"),
                "detector": ("DETECTOR", "CCDNUM", "DETNUM")}

#: Largest ids an instrument recorded here accepts (the registry's checks).
_ID_MAX = {"detector_max": 10000, "exposure_max": 10**12, "visit_max": 10**12}


def parse_data_id(text):
    """A data ID written as ``exposure=12,detector=3``.

    Parameters
    ----------
    text : str

    Returns
    -------
    dict of str to int
        ``exposure`` and ``detector`` (both required).

    Raises
    ------
    InputError
        Another key, a value that is not an integer, or a key missing.
    """
    out = {}
    for part in filter(None, (p.strip() for p in str(text).split(","))):
        key, sep, value = part.partition("=")
        key = key.strip()
        if not sep or key not in DATA_ID_KEYS:
            raise InputError(f"--data-id {text!r}: {part!r} is not KEY=VALUE with KEY one of "
                             f"{', '.join(DATA_ID_KEYS)}; e.g. exposure=12,detector=3")
        try:
            out[key] = int(value)
        except ValueError:
            raise InputError(f"--data-id {text!r}: {key}={value.strip()!r} is not an "
                             "integer") from None
    missing = [k for k in DATA_ID_KEYS if k not in out]
    if missing:
        raise InputError(f"--data-id {text!r}: no {' and no '.join(missing)}; a data ID "
                         "names both, e.g. exposure=12,detector=3")
    return out


def _integer(value):
    """An integer id from a header value (12, '12', 'e000012'), or None."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    m = re.search(r"(\d+)\s*$", str(value))
    return int(m.group(1)) if m else None


def header_data_id(path):
    """The data ID the headers of a FITS file give, and what else they say.

    Parameters
    ----------
    path : str

    Returns
    -------
    data_id : dict
        ``exposure`` and ``detector`` (int) from the first of
        :data:`DATA_ID_KEYS` present in any HDU's header.
    facts : dict
        ``filter`` (``FILTER`` or ``BAND``), ``date_obs`` (``DATE-OBS``),
        ``obs_id`` (``OBSID``) when present.

    Raises
    ------
    InputError
        An id the headers do not give, naming the keywords looked for.
    """
    headers = []
    with open_fits(path) as hdul:
        headers = [h.header for h in hdul]

    def first(keys):
        for key in keys:
            for h in headers:
                if key in h and h[key] not in (None, ""):
                    return h[key]
        return None

    data_id = {}
    for name, keys in DATA_ID_KEYS.items():
        value = _integer(first(keys))
        if value is None:
            raise InputError(f"{path}: no {name} id in its headers (looked for "
                             f"{', '.join(keys)}); give it with --data-id "
                             "exposure=N,detector=M, one per file in order")
        data_id[name] = value
    facts = {"filter": first(("FILTER", "BAND")), "date_obs": first(("DATE-OBS",)),
             "obs_id": first(("OBSID",))}
    return data_id, {k: v for k, v in facts.items() if v is not None}


def _day_obs(date_obs):
    """YYYYMMDD of a DATE-OBS value, or None."""
    try:
        return int(datetime.datetime.fromisoformat(str(date_obs).replace("Z", "")).strftime(
            "%Y%m%d"))
    except ValueError:
        return None


def _sync(registry, element, record):
    """Insert a dimension record unless it exists (an equal one is fine)."""
    try:
        registry.syncDimensionData(element, record)
    except ConflictingDefinitionError as exc:
        which = ", ".join(f"{k}={record[k]!r}" for k in ("instrument", "id", "name")
                          if k in record)
        raise InputError(f"the repository holds another {element} record for {which} ({exc}); "
                         "use its data IDs, or another instrument name") from None


def put_exposures(repo, files, *, run, instrument, data_ids=None,
                  dataset_type=INPUT_DATASET_TYPE, storage_class="BfdriftExposure",
                  physical_filter=None, progress=None):
    """Put FITS exposures into a run collection of a Butler repository.

    Parameters
    ----------
    repo : str
        The repository (made with the package's seed config, which declares
        the storage class ``BfdriftExposure``).
    files : sequence of str
        FITS exposures in electrons (the pipeline's input): the LSST
        Exposure layout, CCDData or a plain image
        (:func:`~lsst_bfdrift.images.exposure.read_exposure`).
    run : str
        The run collection they go into (created if missing): ``pipetask run
        -i RUN``.
    instrument : str
        Instrument name of the data IDs; recorded if the repository does not
        know it.
    data_ids : sequence of dict, optional
        One ``{"exposure": N, "detector": M}`` per file, in order; default:
        from each file's headers (:func:`header_data_id`).
    dataset_type : str, optional
        The dataset type (default the pipeline's input, ``post_isr_image``);
        registered with dimensions instrument, exposure, detector if missing.
    storage_class : str, optional
        Its storage class.
    physical_filter : str, optional
        Filter of the exposures recorded here (default: each file's
        ``FILTER``, else ``unknown``).
    progress : callable, optional
        Called as ``progress(done, total)`` after each file.

    Returns
    -------
    list of dict
        Per file: ``file``, ``data_id``, ``dataset_type``, ``run``, ``uri``.

    Raises
    ------
    InputError
        A file that cannot be read as an exposure, a data ID missing or
        given twice, a repository without the storage class (not made with
        the seed config), a dataset type of another definition, or a data
        ID already in the run.
    """
    files = [os.fspath(f) for f in files]
    if not files:
        raise InputError("no files given; accepted: FITS exposures in electrons")
    if data_ids is not None and len(data_ids) != len(files):
        raise InputError(f"{len(data_ids)} --data-id for {len(files)} files; give one per file, "
                         "in order, or none (the headers' EXPOSURE/EXPID and DETECTOR/CCDNUM)")
    entries = []
    for k, path in enumerate(files):
        did, facts = header_data_id(path) if data_ids is None else (dict(data_ids[k]), {})
        if data_ids is not None:
            facts = _facts(path)
        entries.append((path, did, facts, read_exposure(path)))
    seen = {}
    for path, did, _, _ in entries:
        key = (did["exposure"], did["detector"])
        if key in seen:
            raise InputError(f"{path} and {seen[key]}: the same data ID exposure={key[0]}, "
                             f"detector={key[1]}; each file needs its own")
        seen[key] = path
    formatters = ButlerConfig(repo).get(("datastore", "formatters")) or {}
    if storage_class not in formatters:  # before any record is written
        raise InputError(f"{repo}: the repository does not know the storage class "
                         f"{storage_class!r}; create it with the package's seed config (butler "
                         "create REPO --seed-config $(python -c \"import lsst_bfdrift.pipeline "
                         "as p; print(p.seed_config_path())\"))")
    butler = Butler.from_config(repo, writeable=True, run=run)
    reg = butler.registry
    dets = sorted({d["detector"] for _, d, _, _ in entries})
    _sync(reg, "instrument", {"name": instrument, "class_name": "none", **_ID_MAX})
    for d in dets:
        _sync(reg, "detector", {"instrument": instrument, "id": d, "full_name": f"D{d:04d}"})
    for path, did, facts, _ in entries:
        band = str(physical_filter or facts.get("filter") or "unknown")
        _sync(reg, "physical_filter", {"instrument": instrument, "name": band, "band": band})
        day = _day_obs(facts.get("date_obs")) or 19700101
        _sync(reg, "day_obs", {"instrument": instrument, "id": day})
        group = f"{instrument}_{did['exposure']}"
        _sync(reg, "group", {"instrument": instrument, "name": group})
        _sync(reg, "exposure", {"instrument": instrument, "id": did["exposure"],
                                "obs_id": str(facts.get("obs_id") or group),
                                "physical_filter": band, "group": group, "day_obs": day})
    dims = BrighterFatterDriftConnections.input_exposure.dimensions
    try:
        reg.registerDatasetType(DatasetType(dataset_type, dims, storage_class,
                                            universe=butler.dimensions))
    except ConflictingDefinitionError as exc:
        raise InputError(f"{repo}: dataset type {dataset_type!r} exists with another "
                         f"definition ({exc}); the pipeline reads {dataset_type!r} with "
                         f"dimensions {', '.join(dims)} and storage class {storage_class}; give "
                         "another --dataset-type") from None
    out = []
    for k, (path, did, _, exposure) in enumerate(entries):
        try:
            ref = butler.put(exposure, dataset_type, instrument=instrument, **did)
        except ConflictingDefinitionError:
            raise InputError(f"{path}: {dataset_type} {did} is already in run {run!r}; "
                             "use another run, or remove that dataset (butler "
                             "remove-runs / prune-datasets)") from None
        out.append({"file": os.path.abspath(path), "data_id": {"instrument": instrument, **did},
                    "dataset_type": dataset_type, "run": run,
                    "uri": str(butler.getURI(ref))})
        if progress is not None:
            progress(k + 1, len(entries))
    return out


def _facts(path):
    """What the headers say besides the ids (filter, date, obs id)."""
    try:
        return header_data_id(path)[1]
    except InputError:  # the ids were given; the headers need not hold them
        facts = {}
        with open_fits(path) as hdul:
            for h in hdul:
                for key, name in (("FILTER", "filter"), ("DATE-OBS", "date_obs"),
                                  ("OBSID", "obs_id")):
                    if key in h.header and name not in facts:
                        facts[name] = h.header[key]
        return facts
