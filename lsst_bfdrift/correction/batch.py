"""Correct many FITS files: serially or on a dask cluster.

Every file is handled by :func:`correct_file` (one
:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask` run, output written
atomically). :func:`correct_files` maps it over a list of (input, output)
pairs, either in this process or on a dask ``distributed`` cluster (a
``LocalCluster`` started here, or any scheduler address). A file that fails
gives an error entry for that file only; the others are still corrected.
dask is an optional dependency (``pip install lsst_bfdrift[dask]``).
"""

import contextlib
import functools
import json
import os
import sys
import threading

import numba
import numpy as np
from astropy.io import fits

from lsst_bfdrift.correction.steps import FLAG_BLOCKED, FLAG_EDGE
from lsst_bfdrift.correction.task import (BrighterFatterDriftConfig, BrighterFatterDriftTask,
                                          stage_order)
from lsst_bfdrift.images.exposure import read_exposure, write_exposure
from lsst_bfdrift.utils.io import check_output
from lsst_bfdrift.utils.config import config_from_dict
from lsst_bfdrift.utils.progress import ProgressBar, StageProgress
from lsst_bfdrift.utils.errors import BfdriftError, InputError

__all__ = ["correct_file", "correct_files", "output_pairs", "stage_weights", "error_text",
           "STAGE_SECONDS"]


def output_pairs(inputs, out_dir):
    """(input, out_dir/basename(input)) pairs; refuses duplicate output names."""
    pairs = [(os.fspath(f), os.path.join(os.fspath(out_dir), os.path.basename(os.fspath(f))))
             for f in inputs]
    names = [dst for _, dst in pairs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"several inputs would write the same output: {dup}")
    return pairs


#: Seconds per stage of :func:`correct_file` on a 4096 x 4096 field with 400
#: stars, without maps, with the linear maps and with the exact ones (2 shared
#: cores; ``python benchmarks/performance/stage_timings.py``,
#: ``benchmarks/performance/stage_timings_results.txt``). Each stage runs from the previous
#: stage's end: ``correct`` (or ``maps`` for the exact ones) includes the Task's
#: input checks, ``correct`` with the linear maps their first-order part.
STAGE_SECONDS = {
    "none": {"read": 0.05, "correct": 1.44, "maps": 0.0, "write": 0.43},
    "linear": {"read": 0.05, "correct": 2.46, "maps": 0.72, "write": 2.10},
    "exact": {"read": 0.06, "correct": 0.91, "maps": 9.33, "write": 2.08},
}


def stage_weights(config=None):
    """Shares of one file's time in each stage of :func:`correct_file`.

    The measured seconds of :data:`STAGE_SECONDS` for the configuration's
    maps (none, linear or exact). The stages come in the order they run
    (:func:`~lsst_bfdrift.correction.task.stage_order`): the exact maps
    before the correction, the linear ones after it (from its first pass).

    Parameters
    ----------
    config : BrighterFatterDriftConfig or dict, optional

    Returns
    -------
    dict of str to float
        ``read``, then ``maps`` and ``correct`` in the Task's order (``maps``
        0 without ``compute_geometry``), then ``write``: weights for a
        :class:`~lsst_bfdrift.utils.progress.StageProgress` (which takes the
        stages in the dict's order).
    """
    cfg = json.loads(_config_json(config))
    defaults = BrighterFatterDriftConfig()
    geometry = cfg.get("compute_geometry", defaults.compute_geometry)
    exact = cfg.get("geometry_method", defaults.geometry_method) == "exact"
    run = STAGE_SECONDS["none" if not geometry else "exact" if exact else "linear"]
    order = stage_order(cfg)
    weights = {"read": run["read"]}
    weights.update((stage, run[stage]) for stage in order)
    weights.update((stage, run[stage]) for stage in ("correct", "maps") if stage not in order)
    weights["write"] = run["write"]
    return weights


@functools.lru_cache(maxsize=4)
def _task(config_json):
    """One Task per configuration and process (the template is loaded once)."""
    cfg = config_from_dict(BrighterFatterDriftConfig, json.loads(config_json))
    return BrighterFatterDriftTask(config=cfg)


def _config_json(config):
    if config is None:
        config = BrighterFatterDriftConfig()
    if isinstance(config, BrighterFatterDriftConfig):
        config = config.toDict()
    config_from_dict(BrighterFatterDriftConfig, dict(config)).validate()  # before any work
    return json.dumps(config, sort_keys=True)


def correct_file(src, dst, config=None, *, overwrite=False, progress=None):
    """Correct one FITS file and write the result atomically, in the input's layout.

    Parameters
    ----------
    src, dst : str or path
        Input image and output file. The output keeps every HDU and header of
        the input (:func:`~lsst_bfdrift.images.exposure.write_exposure`): the
        image is corrected in place (same HDU, dtype and compression), an
        LSST ``MASK`` gains the ``BF`` plane (declared by its ``MP_BF`` card)
        for the pixels the correction flagged, ``VARIANCE`` is kept; then
        ``FLUX_MOVED`` (e), ``BFFLAGS`` and, with ``config.compute_geometry``,
        the geometry maps are appended, each with ``BUNIT`` and a description.
    config : BrighterFatterDriftConfig or dict, optional
        Task configuration (default: the defaults).
    overwrite : bool, optional
        Replace an existing ``dst``; otherwise an existing file is an error.
    progress : callable, optional
        Called as ``progress(stage, fraction)`` for the stages ``'read'``,
        ``'maps'`` and ``'correct'`` (see
        :meth:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask.run`) and
        ``'write'``, e.g. a :class:`~lsst_bfdrift.utils.progress.StageProgress`
        with :func:`stage_weights`. It does not change the result.

    Returns
    -------
    dict
        ``input``, ``output``, ``iterations``, ``converged``, ``layout``,
        ``warnings`` (what looked wrong with the input, see
        :func:`~lsst_bfdrift.correction.checks.input_warnings`),
        ``flux_moved_sum`` and ``flux_moved_abs_sum`` (e).
    """
    def report(stage, fraction):
        if progress is not None:
            progress(stage, fraction)

    src, dst = os.fspath(src), os.fspath(dst)
    check_output(dst, [src], overwrite=overwrite, hint="--overwrite")
    report("read", 0.0)
    exposure = read_exposure(src)
    report("read", 1.0)
    res = _task(_config_json(config)).run(exposure, progress=progress)
    extra = [_described(fits.ImageHDU(res.flux_moved.astype(np.float32), name="FLUX_MOVED"),
                        "electron", "flux moved into each pixel by the correction (sums to "
                        "zero)"),
             _flags_hdu(res.flags)]
    if res.area is not None:
        for name, unit, what in (("area", "pixel2", "final pixel area (px^2)"),
                                 ("centroid_x", "pixel", "centroid shift along x (px)"),
                                 ("centroid_y", "pixel", "centroid shift along y (px)"),
                                 ("e1", "", "pixel ellipticity e1"),
                                 ("e2", "", "pixel ellipticity e2")):
            # the area keeps float64: it is 1 plus a signal that can be below
            # float32's resolution at 1 (6e-8); the other maps are small numbers
            data = getattr(res, name).astype(np.float64 if name == "area" else np.float32,
                                             copy=False)
            extra.append(_described(fits.ImageHDU(data, name=name.upper()), unit, what))
    report("write", 0.0)
    write_exposure(dst, res.exposure, extra_hdus=extra, overwrite=overwrite, inputs=[src])
    report("write", 1.0)
    return {"input": src, "output": dst, "iterations": int(res.iterations),
            "converged": bool(res.converged), "layout": exposure.layout,
            "warnings": list(res.warnings),
            "flux_moved_abs_sum": float(np.abs(res.flux_moved).sum()),
            "flux_moved_sum": float(res.flux_moved.sum())}


def _described(hdu, unit, what):
    """``hdu`` with BUNIT and its description (``BFDESC``, long strings continued)."""
    if unit:
        hdu.header["BUNIT"] = unit
    hdu.header["BFDESC"] = what
    return hdu


def _flags_hdu(flags):
    """The BFFLAGS extension: its bits declared as mask planes, afw's way (``MP_`` bit
    number, ``MPD_`` description)."""
    hdu = _described(fits.ImageHDU(flags.astype(np.int16), name="BFFLAGS"), "",
                     f"bit planes of the correction: value {FLAG_BLOCKED} blocked (masked, "
                     f"saturated or non-finite: no flux exchanged), value {FLAG_EDGE} within "
                     "the template's reach of the image border (aggressors missing)")
    for name, value, doc in (("BLOCKED", FLAG_BLOCKED, "masked, saturated or non-finite: no "
                              "flux exchanged"),
                             ("EDGE", FLAG_EDGE, "within the template's reach of the border")):
        bit = int(value).bit_length() - 1
        hdu.header[f"HIERARCH MP_{name}"] = bit
        hdu.header[f"HIERARCH MPD_{name}"] = doc
    return hdu


_NUMBA_LOCK = threading.Lock()


def _numba_guard():
    """A lock unless numba's threading layer is thread-safe (omp, tbb).

    numba's fallback 'workqueue' layer must not launch parallel kernels from
    several threads at once (dask workers as threads); before the first
    parallel kernel has run the layer is unknown, so that run is locked too.
    """
    try:
        layer = numba.threading_layer()
    except ValueError:  # no parallel kernel has run yet
        layer = "unknown"
    return _NUMBA_LOCK if layer in ("workqueue", "unknown") else contextlib.nullcontext()


def _stderr_is_tty():
    return bool(getattr(sys.stderr, "isatty", lambda: False)())


def _safe(src, dst, config_json, overwrite, progress=None):
    """:func:`correct_file` with the error turned into a result entry."""
    try:
        with _numba_guard():
            out = correct_file(src, dst, json.loads(config_json), overwrite=overwrite,
                               progress=progress)
        out["error"] = None
        return out
    except Exception as exc:  # noqa: BLE001 - reported per file, the others go on
        return {"input": os.fspath(src), "output": os.fspath(dst), "iterations": None,
                "converged": False, "warnings": [], "error": error_text(exc)}


def error_text(exc):
    """The ``error`` of a failed file's result: the message of the package's
    errors (which name the file and the problem), ``'ExceptionType: message'``
    for any other exception.

    Parameters
    ----------
    exc : BaseException

    Returns
    -------
    str
    """
    return str(exc) if isinstance(exc, BfdriftError) else f"{type(exc).__name__}: {exc}"


def correct_files(pairs, config=None, *, scheduler=None, overwrite=False, n_workers=2,
                  threads_per_worker=1, processes=False, progress=False):
    """Correct many files, serially or on a dask cluster.

    Parameters
    ----------
    pairs : sequence of (str, str)
        (input, output) paths (:func:`output_pairs`).
    config : BrighterFatterDriftConfig or dict, optional
        Task configuration, the same for every file.
    scheduler : str, optional
        None: serial, in this process. ``'local'``: a dask ``LocalCluster``
        started here (``n_workers``, ``threads_per_worker``, ``processes``).
        Anything else: the address of a running dask distributed scheduler
        (e.g. ``tcp://host:8786``).
    overwrite : bool, optional
        Replace existing outputs (otherwise each such file is an error).
    n_workers, threads_per_worker, processes
        LocalCluster settings (ignored otherwise); threads by default, as
        ``bfdrift correct`` (the compiled kernels release the GIL).
    progress : bool, optional
        Progress on stderr. Run in this process, one file, or any number
        when stderr is a terminal: a bar per file through its stages (read,
        correct and maps in the Task's order, write; :func:`stage_weights`),
        labelled with the file (and ``k/n``); otherwise (a cluster, or
        several files logged to a file) a bar of the files finished.

    Returns
    -------
    list of dict
        One per pair, in the input order: the :func:`correct_file` summary and
        ``error`` (None, or the message of a failed file, :func:`error_text`).
    """
    pairs = [(os.fspath(a), os.fspath(b)) for a, b in pairs]
    cfg = _config_json(config)
    results = [None] * len(pairs)
    if scheduler is None and progress and (len(pairs) == 1 or _stderr_is_tty()):
        weights = stage_weights(json.loads(cfg))
        for k, (src, dst) in enumerate(pairs):
            label = "correct " + (f"{k + 1}/{len(pairs)} " if len(pairs) > 1 else "") + \
                os.path.basename(src)
            with StageProgress(weights, label) as stages:
                results[k] = _safe(src, dst, cfg, overwrite, progress=stages)
                if results[k]["error"]:
                    stages.fail()  # "failed", not "done 100 %"
        return results
    with ProgressBar(len(pairs), "correct", enabled=progress) as bar:
        if scheduler is None:
            for k, (src, dst) in enumerate(pairs):
                results[k] = _safe(src, dst, cfg, overwrite)
                bar(1)
            return results
        try:  # distributed: optional (the [dask] extra), starts workers
            from distributed import Client, LocalCluster, as_completed
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise ImportError("the dask scheduler needs dask[distributed]: "
                              "pip install 'lsst_bfdrift[dask]'") from exc
        cluster = None
        if scheduler == "local":
            cluster = LocalCluster(n_workers=int(n_workers),
                                   threads_per_worker=int(threads_per_worker),
                                   processes=bool(processes), dashboard_address=":0")
            client = Client(cluster)
        else:
            client = Client(scheduler)
        try:
            # absolute paths: workers may run in another directory (issue 19 row 8);
            # results keep the paths as given
            futures = {client.submit(_safe, os.path.abspath(src), os.path.abspath(dst), cfg,
                                     overwrite, pure=False): k
                       for k, (src, dst) in enumerate(pairs)}
            for fut in as_completed(futures):
                k = futures[fut]
                try:
                    results[k] = dict(fut.result(), input=pairs[k][0], output=pairs[k][1])
                except Exception as exc:  # noqa: BLE001 - e.g. a worker died
                    src, dst = pairs[k]
                    results[k] = {"input": src, "output": dst, "iterations": None,
                                  "converged": False, "warnings": [],
                                  "error": error_text(exc)}
                bar(1)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    return results
