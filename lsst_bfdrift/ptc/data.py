"""The characterization data of one sensor (amplifier), whatever file it came from.

:class:`CalibrationData` is what :func:`~lsst_bfdrift.ptc.inputs.read_calibration_input`
returns. Conventions: a-matrices are indexed ``a[i, j]`` with i the serial
and j the parallel lag, per electron; covariances ``cov[k, di, dj]``
likewise, in the signal's unit squared.
"""

import dataclasses
import math
import os

import numpy as np

from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.utils.errors import InputError

__all__ = ["CalibrationData", "INPUT_KINDS", "require_levels", "truncate_lags",
           "describe_paths"]


#: The input kinds, in the order of :data:`CalibrationData.kind`.
INPUT_KINDS = ("flats", "ptc", "amatrix", "cp_pipe")


@dataclasses.dataclass
class CalibrationData:
    """A sensor's characterization data, as read by :func:`read_calibration_input`.

    Attributes
    ----------
    kind : str
        'flats', 'ptc', 'amatrix' or 'cp_pipe'.
    files : list of str
        The files read.
    a, a_sigma : ndarray, shape (L + 1, L + 1), or None
        Area coefficients a_ij and 1-sigma errors (per electron), indexed
        [i serial, j parallel]; ``a_sigma`` None when the source gives none.
    a00_measured : bool or None
        Whether ``a[0, 0]`` is a measurement (False: set by the area sum
        rule); None without an a-matrix.
    mu, var : ndarray, shape (n,), or None
        PTC points kept (past the turn-off and rejected points are left out):
        mean signal (``units``) and variance (``units`` squared), sorted by ``mu``.
    cov : ndarray, shape (n, M, M), or None
        Covariances ``cov[k, di, dj]`` (``units`` squared) of the same points.
    cov_sigma : ndarray, shape (n, M, M), or None
        Their errors, when the source gives them (cp_pipe weights).
    npix : ndarray of int, shape (n, M, M), or None
        Pixel pairs behind each covariance (flats).
    exptime : ndarray, shape (n,), or None
        Exposure time of each point (s).
    units : str
        'adu' or 'electron': unit of ``mu``.
    gain, gain_err : float or None
        Gain (electron per ``units``) and its error, when known.
    gain_source : str
        Where the gain came from (or why it is unknown).
    turnoff : float or None
        PTC turn-off signal (``units``); inf when none was found.
    pairs_used, pairs_dropped : list of dict
        One entry per flat pair (``'flats'``) or per PTC point (``'ptc'``,
        ``'cp_pipe'``): files or index, exposure time, ``mu``, ``var``;
        dropped entries carry a ``'reason'``. Files dropped before pairing
        (odd file out) have ``'files'`` of length 1.
    amp : str or None
        Amplifier read (cp_pipe); 'average of ...' when several were averaged.
    amps : dict
        Per amplifier (cp_pipe): gain, noise, turn-off, fit type.
    bad_amps : list of str
        cp_pipe's ``badAmps``.
    notes : list of str
        Everything worth telling the user (units assumed, axis orientation,
        truncation, ...).
    meta : dict
        Source metadata (cp_pipe version and fit type, a-matrix axis note).
    """

    kind: str
    files: list
    a: np.ndarray = None
    a_sigma: np.ndarray = None
    a00_measured: bool = None
    mu: np.ndarray = None
    var: np.ndarray = None
    cov: np.ndarray = None
    cov_sigma: np.ndarray = None
    npix: np.ndarray = None
    exptime: np.ndarray = None
    units: str = "adu"
    gain: float = None
    gain_err: float = None
    gain_source: str = ""
    turnoff: float = None
    pairs_used: list = dataclasses.field(default_factory=list)
    pairs_dropped: list = dataclasses.field(default_factory=list)
    amp: str = None
    amps: dict = dataclasses.field(default_factory=dict)
    bad_amps: list = dataclasses.field(default_factory=list)
    notes: list = dataclasses.field(default_factory=list)
    meta: dict = dataclasses.field(default_factory=dict)

    @property
    def max_lag(self):
        """Largest lag of the a-matrix, else of the covariances; None without either."""
        if self.a is not None:
            return self.a.shape[0] - 1
        if self.cov is not None:
            return self.cov.shape[1] - 1
        return None

    @property
    def n_levels(self):
        """Number of distinct exposure levels kept (points when times are unknown)."""
        if self.mu is None:
            return 0
        if self.exptime is None:
            return int(self.mu.size)
        return int(np.unique(self.exptime).size)

    def acoeff_table(self):
        """The a-matrix as an :class:`~lsst_bfdrift.ptc.acoeffs.AcoeffTable`.

        Raises
        ------
        ValueError
            Without an a-matrix or without its errors.
        """
        src = ", ".join(self.files)
        if self.a is None:
            raise InputError(f"{src}: no a-matrix was read (kind {self.kind!r})")
        if self.a_sigma is None:
            raise InputError(f"{src}: the a-matrix has no errors; an AcoeffTable needs "
                             "positive 1-sigma errors for every lag")
        return AcoeffTable(self.a, self.a_sigma, source=src,
                           axis_note=str(self.meta.get("axis_note", "")),
                           exclude_a00=not self.a00_measured)

    def summary(self):
        """JSON-ready dict (no NaN: non-finite numbers become None)."""
        return _jsonable({
            "kind": self.kind, "files": list(self.files), "units": self.units,
            "gain": self.gain, "gain_err": self.gain_err, "gain_source": self.gain_source,
            "turnoff": self.turnoff, "max_lag": self.max_lag, "n_levels": self.n_levels,
            "n_points": 0 if self.mu is None else int(self.mu.size),
            "mu": self.mu, "var": self.var, "exptime": self.exptime,
            "a": self.a, "a_sigma": self.a_sigma, "a00_measured": self.a00_measured,
            "pairs_used": self.pairs_used, "pairs_dropped": self.pairs_dropped,
            "amp": self.amp, "amps": self.amps, "bad_amps": self.bad_amps,
            "notes": self.notes, "meta": self.meta})


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if x is None or isinstance(x, str):
        return x
    return str(x)


def describe_paths(paths, *, limit=4):
    """Files named for a message: all of a few; the directory and the count of many.

    Parameters
    ----------
    paths : sequence of str
    limit : int, optional
        Most paths named one by one.

    Returns
    -------
    str
        ``'a.fits, b.fits'``; ``'flats/ (80 files)'`` when more than ``limit``
        share a directory; ``'flats/a.fits ... (80 files in 3 directories)'``
        otherwise.
    """
    paths = [os.fspath(p) for p in paths]
    if len(paths) <= limit:
        return ", ".join(paths)
    dirs = sorted({os.path.dirname(p) or "." for p in paths})
    if len(dirs) == 1:
        return f"{os.path.join(dirs[0], '')} ({len(paths)} files)"
    return f"{paths[0]} ... ({len(paths)} files in {len(dirs)} directories)"


def _dropped_summary(dropped, limit=4):
    """The dropped pairs or points, grouped by reason; a few named, the rest counted."""
    groups = {}
    for d in dropped:
        # reasons that name a level or value differ only in it: group by the text before
        reason = d["reason"]
        key = reason.split(":")[0] if "files" in d else reason
        groups.setdefault(key, []).append(d)
    parts = []
    for key, items in groups.items():
        if len(items) <= 2:
            for d in items:
                what = describe_paths(d["files"]) if "files" in d else f"point {d['index']}"
                parts.append(f"dropped {what}: {d['reason']}")
            continue
        files = [f for d in items for f in d.get("files", [])]
        what = (describe_paths(files, limit=limit) if files
                else f"points {', '.join(str(d['index']) for d in items[:limit])}"
                + (" ..." if len(items) > limit else ""))
        parts.append(f"dropped {len(items)} for the same reason ({what}): {items[0]['reason']}"
                     + (" (first of them)" if len(items) > 1 else ""))
    return "".join(f"; {p}" for p in parts)


def require_levels(nlev, min_levels, what, files, dropped):
    """Refuse a PTC with fewer than ``min_levels`` signal levels ``what``, naming the
    files (:func:`describe_paths`) and why points were dropped (grouped by
    reason, a few named)."""
    if nlev >= min_levels:
        return
    raise InputError(f"{files}: {nlev} distinct signal level(s) {what}, fewer than "
                     f"min_levels={min_levels}; a photon transfer curve needs at least "
                     f"{min_levels} levels below the turn-off{_dropped_summary(dropped)}")


def truncate_lags(out, max_lag):
    if max_lag is None:
        return out
    k = int(max_lag) + 1
    if out.a is not None and out.a.shape[0] > k:
        out.notes.append(f"a-matrix lags up to {out.a.shape[0] - 1} truncated to "
                         f"max_lag={int(max_lag)}")
        out.a = out.a[:k, :k]
        out.a_sigma = None if out.a_sigma is None else out.a_sigma[:k, :k]
    if out.cov is not None and out.cov.shape[1] > k:
        out.notes.append(f"covariances up to lag {out.cov.shape[1] - 1} truncated to "
                         f"max_lag={int(max_lag)}")
        out.cov = out.cov[:, :k, :k]
        out.cov_sigma = None if out.cov_sigma is None else out.cov_sigma[:, :k, :k]
    return out
