"""Reader of the PTC dataset FITS that LSST's cp_pipe writes.

Layout learned from ``python/lsst/ip/isr/ptcDataset.py``
(``PhotonTransferCurveDataset.toTable`` / ``fromTable``, schema version
2.6, ip_isr commit d2a69bfd) and ``python/lsst/ip/isr/calibType.py``
(``IsrCalib.writeFits``) of lsst/ip_isr, and from
``python/lsst/cp/pipe/ptc/cpPtcExtract.py``, ``cpPtcSolve.py`` and
``utils.py`` of lsst/cp_pipe (commit f029a3f2) for the index order;
no code was taken from them. What is read:

* HDU 0: empty primary HDU (ignored). HDU 1: a binary table, one row per
  amplifier. Its header holds the calibration metadata: ``OBSTYPE`` =
  'PTC' (required), ``PTC_SCHEMA`` = 'Gen3 Photon Transfer Curve',
  ``PTC_VERSION`` (e.g. 2.6), ``PTC_FIT_TYPE``, ``CALIBCLS`` =
  'lsst.ip.isr.ptcDataset.PhotonTransferCurveDataset' (long keys are
  HIERARCH cards). Further HDUs are ignored.
* Columns read (required): ``AMPLIFIER_NAME`` (str), ``PTC_FIT_TYPE``
  (str: 'EXPAPPROXIMATION', 'FULLCOVARIANCE', 'FULLCOVARIANCE_NO_B',
  older 'POLYNOMIAL'), ``COV_MATRIX_SIDE`` (int M: covariances are
  M x M, lags 0..M-1), ``RAW_MEANS`` (n, ADU), ``RAW_VARS`` (n, ADU^2),
  ``EXP_ID_MASK`` (n, bool: True = used by cp_pipe), ``GAIN``,
  ``GAIN_ERR`` (e/ADU), ``NOISE`` (electron from version 1.9 on),
  ``PTC_TURNOFF`` (ADU, version >= 1.1), ``PTC_FIT_PARS`` /
  ``PTC_FIT_PARS_ERROR`` (for EXPAPPROXIMATION: a00 (1/e), gain, noise^2;
  NaN for full-covariance fits), ``A_MATRIX`` (raveled K x K, 1/e),
  ``COVARIANCES`` (raveled n x M x M, ADU^2), ``BAD_AMPS`` (str array,
  the same in every row). Optional: ``COV_MATRIX_SIDE_FULL_COV_FIT`` (K,
  version >= 1.5; else K = M), ``COVARIANCES_SQRT_WEIGHTS`` (raveled
  n x M x M: 1/sigma of each covariance, 1/ADU^2; 0 where unmeasured), ``RAW_EXP_TIMES``
  (n, s), ``NPIXEL_COVARIANCES`` (one int per amplifier, version >= 2.4,
  recorded in ``meta``). Per-amplifier arrays are fixed-width or
  variable-length columns.
* Index order: cp_pipe fills ``cov[k, i, j]`` with ``i`` the lag along
  x and ``j`` along y (``makeCovArray`` from ``(dx, dy)`` tuples; the
  plots call ``cov[:, 1, 0]`` the nearest *serial* neighbour), and fits
  ``A_MATRIX`` on the same array. x is the serial direction of an LSST
  amplifier image, so cp_pipe's ``[i, j]`` is already this package's
  [serial, parallel]: nothing is transposed.
* The a-matrix is filled only by the FULLCOVARIANCE fits, and the file
  stores no errors for it (``a_sigma`` is None). An EXPAPPROXIMATION fit
  gives a00 with its error (``PTC_FIT_PARS[0]``), returned as a 1 x 1
  a-matrix.
* An amplifier is chosen by ``amp``; ``amp=None`` takes the only good
  amplifier (not in ``BAD_AMPS``), or averages the good amplifiers'
  a-matrices with inverse-variance weights when every one has errors,
  and otherwise asks to choose. PTC points with ``EXP_ID_MASK`` False or
  above ``PTC_TURNOFF`` are dropped and reported.
"""

import math
import os

import numpy as np
from astropy.io import fits

from lsst_bfdrift.ptc.data import CalibrationData, require_levels, truncate_lags
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.io import open_fits

__all__ = ["CP_PIPE_COLUMNS", "read_cp_pipe_ptc"]


#: Columns a cp_pipe PTC dataset table must have to be read here.
CP_PIPE_COLUMNS = ("AMPLIFIER_NAME", "PTC_FIT_TYPE", "COV_MATRIX_SIDE", "RAW_MEANS", "RAW_VARS",
                   "EXP_ID_MASK", "GAIN", "GAIN_ERR", "NOISE", "PTC_TURNOFF", "PTC_FIT_PARS",
                   "PTC_FIT_PARS_ERROR", "A_MATRIX", "COVARIANCES", "BAD_AMPS")


_CP_EXPECTED = ("a cp_pipe PTC dataset (lsst.ip.isr PhotonTransferCurveDataset, schema 'Gen3 "
                "Photon Transfer Curve'): HDU 1 a binary table with one row per amplifier, "
                "OBSTYPE = 'PTC' in its header")


def _cell(data, col, row):
    v = data[col][row]
    return np.asarray(v)


def _bad_amps(data):
    col = data["BAD_AMPS"]
    if np.asarray(col).size == 0:
        return []
    out = set()
    for row in range(len(data)):
        for v in np.atleast_1d(np.asarray(col[row])).ravel():
            v = v.decode() if isinstance(v, bytes) else str(v)
            if v.strip():
                out.add(v.strip())
    return sorted(out)


def _cp_amp(path, data, row, version):
    """One amplifier's row as a dict of arrays (checked shapes)."""
    name = str(_cell(data, "AMPLIFIER_NAME", row)).strip()
    fit_type = str(_cell(data, "PTC_FIT_TYPE", row)).strip()
    side = int(_cell(data, "COV_MATRIX_SIDE", row))
    side_fit = (int(_cell(data, "COV_MATRIX_SIDE_FULL_COV_FIT", row))
                if "COV_MATRIX_SIDE_FULL_COV_FIT" in data.names else side)
    mu = _cell(data, "RAW_MEANS", row).astype(float).ravel()
    n = mu.size
    var = _cell(data, "RAW_VARS", row).astype(float).ravel()
    mask = _cell(data, "EXP_ID_MASK", row).astype(bool).ravel()
    for col, arr in (("RAW_VARS", var), ("EXP_ID_MASK", mask)):
        if arr.size != n:
            raise InputError(f"{path}: amplifier {name}: column {col} has {arr.size} entries, "
                             f"RAW_MEANS {n}; {_CP_EXPECTED} with one entry per flat pair")
    exptime = (_cell(data, "RAW_EXP_TIMES", row).astype(float).ravel()
               if "RAW_EXP_TIMES" in data.names else None)
    if exptime is not None and exptime.size != n:
        exptime = None
    cov = _cell(data, "COVARIANCES", row).astype(float).ravel()
    if cov.size not in (0, n * side * side):
        raise InputError(f"{path}: amplifier {name}: COVARIANCES has {cov.size} values, expected "
                         f"{n} x {side} x {side} = {n * side * side} (RAW_MEANS x "
                         "COV_MATRIX_SIDE^2)")
    cov = cov.reshape(n, side, side) if cov.size else None
    cov_sigma = None
    if cov is not None and "COVARIANCES_SQRT_WEIGHTS" in data.names:
        w = _cell(data, "COVARIANCES_SQRT_WEIGHTS", row).astype(float).ravel()
        if w.size == cov.size:
            with np.errstate(divide="ignore"):
                cov_sigma = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), np.nan).reshape(
                    cov.shape)
    amat = _cell(data, "A_MATRIX", row).astype(float).ravel()
    a = a_sigma = None
    if fit_type.startswith("FULLCOVARIANCE"):
        if amat.size != side_fit * side_fit:
            raise InputError(f"{path}: amplifier {name}: A_MATRIX has {amat.size} values, "
                             f"expected {side_fit} x {side_fit} (COV_MATRIX_SIDE_FULL_COV_FIT^2)")
        if np.all(np.isfinite(amat)):
            a = amat.reshape(side_fit, side_fit)
    elif fit_type.startswith("EXPAPPROXIMATION"):
        pars = _cell(data, "PTC_FIT_PARS", row).astype(float).ravel()
        errs = _cell(data, "PTC_FIT_PARS_ERROR", row).astype(float).ravel()
        if pars.size and np.isfinite(pars[0]):
            a = np.array([[pars[0]]])
            if errs.size and np.isfinite(errs[0]) and errs[0] > 0:
                a_sigma = np.array([[errs[0]]])
    info = {"fit_type": fit_type, "gain": float(_cell(data, "GAIN", row)),
            "gain_err": float(_cell(data, "GAIN_ERR", row)),
            "noise": float(_cell(data, "NOISE", row)),
            "noise_units": "electron" if (version is None or version >= 1.9) else
            ("electron^2" if fit_type.startswith("FULLCOVARIANCE") else "electron"),
            "turnoff": float(_cell(data, "PTC_TURNOFF", row)), "cov_matrix_side": side,
            "cov_matrix_side_full_cov_fit": side_fit}
    if "NPIXEL_COVARIANCES" in data.names:
        info["npixel_covariances"] = int(_cell(data, "NPIXEL_COVARIANCES", row))
    return name, {"mu": mu, "var": var, "mask": mask, "exptime": exptime, "cov": cov,
                  "cov_sigma": cov_sigma, "a": a, "a_sigma": a_sigma, "info": info}


def read_cp_pipe_ptc(path, *, amp=None, max_lag=None, min_levels=3):
    """Read the PTC dataset FITS written by LSST's cp_pipe.

    The layout read, and the index order, are described in the module
    documentation (kind ``'cp_pipe'``).

    Parameters
    ----------
    path : str or path-like
    amp : str, optional
        Amplifier name (``AMPLIFIER_NAME``). None: the only good amplifier,
        or the inverse-variance average of the good amplifiers' a-matrices
        when all carry errors; otherwise an error asks to choose.
    max_lag : int, optional
        Truncate the a-matrix and covariances to lags <= max_lag (noted).
    min_levels : int, optional
        Fewest PTC points kept when the dataset has no a-matrix.

    Returns
    -------
    CalibrationData
        ``kind`` 'cp_pipe'.
    """
    path = os.fspath(path)
    with open_fits(path) as hdul:
        if len(hdul) < 2 or not isinstance(hdul[1], fits.BinTableHDU):
            found = "no HDU 1" if len(hdul) < 2 else f"HDU 1 is {type(hdul[1]).__name__}"
            raise InputError(f"{path}: not {_CP_EXPECTED}; found {found}")
        hdr = hdul[1].header
        obstype = hdr.get("OBSTYPE", hdul[0].header.get("OBSTYPE"))
        calibcls = hdr.get("CALIBCLS")
        if obstype != "PTC":
            raise InputError(f"{path}: not {_CP_EXPECTED}; found OBSTYPE = {obstype!r}"
                             + (f", CALIBCLS = {calibcls!r}" if calibcls else ""))
        data = hdul[1].data
        names = list(data.names) if data is not None else []
        missing = [c for c in CP_PIPE_COLUMNS if c not in names]
        if missing:
            raise InputError(f"{path}: not {_CP_EXPECTED} with columns {list(CP_PIPE_COLUMNS)}; "
                             f"missing {missing} (found {names})")
        if len(data) == 0:
            raise InputError(f"{path}: the PTC table has no amplifier rows; {_CP_EXPECTED}")
        version = hdr.get("PTC_VERSION")
        version = float(version) if version is not None else None
        bad_amps = _bad_amps(data)
        amps = dict(_cp_amp(path, data, row, version) for row in range(len(data)))
    meta = {"PTC_VERSION": version, "PTC_SCHEMA": hdr.get("PTC_SCHEMA"),
            "PTC_FIT_TYPE": hdr.get("PTC_FIT_TYPE"), "CALIBCLS": calibcls,
            "axis_note": "cp_pipe [i, j] = [dx, dy] = [serial, parallel]: not transposed"}
    notes = []
    if version is None:
        notes.append("no PTC_VERSION in the table header: read as the current schema")
    if calibcls is not None and "PhotonTransferCurveDataset" not in str(calibcls):
        notes.append(f"CALIBCLS = {calibcls!r}, not PhotonTransferCurveDataset; read by OBSTYPE")
    good = [n for n in amps if n not in bad_amps]
    if amp is not None:
        if amp not in amps:
            raise InputError(f"{path}: no amplifier {amp!r}; the file holds {list(amps)}")
        if amp in bad_amps:
            raise InputError(f"{path}: amplifier {amp!r} is in badAmps {bad_amps}; choose one of "
                             f"{good}")
        chosen = [amp]
    elif not good:
        raise InputError(f"{path}: every amplifier is in badAmps {bad_amps}; nothing to read")
    elif len(good) == 1:
        chosen = good
    else:
        with_err = [n for n in good if amps[n]["a_sigma"] is not None]
        shapes = {amps[n]["a"].shape for n in with_err}
        if len(with_err) != len(good) or len(shapes) != 1:
            raise InputError(
                f"{path}: {len(good)} good amplifiers {good} (badAmps {bad_amps}) and their "
                f"a-matrices carry no errors ({amps[good[0]]['info']['fit_type']} fit), so they "
                "cannot be averaged with inverse-variance weights; choose one with amp='NAME'")
        chosen = good
    per_amp = {n: amps[n]["info"] for n in amps}
    if len(chosen) > 1:
        w = np.array([1.0 / amps[n]["a_sigma"] ** 2 for n in chosen])
        a = np.sum(w * np.array([amps[n]["a"] for n in chosen]), axis=0) / w.sum(axis=0)
        a_sigma = 1.0 / np.sqrt(w.sum(axis=0))
        notes.append(f"a-matrix: inverse-variance average of {len(chosen)} good amplifiers "
                     f"{chosen}; PTC points and gain are per amplifier (see amps)")
        out = CalibrationData(kind="cp_pipe", files=[path], a=a, a_sigma=a_sigma,
                              a00_measured=True, units="adu",
                              gain_source="per amplifier (see amps): not averaged",
                              amp="average of " + ", ".join(chosen), amps=per_amp,
                              bad_amps=bad_amps, notes=notes, meta=meta)
        return truncate_lags(out, max_lag)
    name = chosen[0]
    d = amps[name]
    info = d["info"]
    turnoff = info["turnoff"]
    keep = d["mask"] & np.isfinite(d["mu"]) & np.isfinite(d["var"])
    reasons = np.where(~d["mask"], "rejected by cp_pipe (EXP_ID_MASK False)",
                       np.where(keep, "", "non-finite mean or variance"))
    if math.isfinite(turnoff):
        past = keep & (d["mu"] > turnoff)
        reasons = np.where(past, f"past cp_pipe's PTC turn-off at {turnoff:.6g} ADU", reasons)
        keep &= ~past
    used, dropped = [], []
    for k in range(d["mu"].size):
        e = {"index": k, "mu": float(d["mu"][k]), "var": float(d["var"][k])}
        if d["exptime"] is not None:
            e["exptime"] = float(d["exptime"][k])
        if keep[k]:
            used.append(e)
        else:
            dropped.append(e | {"reason": str(reasons[k])})
    if d["a"] is None:
        notes.append(f"amplifier {name}: no a-matrix ({info['fit_type']} fit"
                     + (", A_MATRIX not filled)" if info["fit_type"].startswith("FULL") else ")"))
        require_levels(int(keep.sum()), min_levels, "kept", f"{path} amplifier {name}", dropped)
    elif d["a_sigma"] is None:
        notes.append("the cp_pipe PTC dataset stores no a-matrix errors (a_sigma None)")
    order = np.argsort(d["mu"][keep], kind="stable")
    sel = np.flatnonzero(keep)[order]

    def pick(x):
        return None if x is None else x[sel]

    a00_measured = None
    if d["a"] is not None:
        a00_measured = True
    gain = info["gain"] if math.isfinite(info["gain"]) and info["gain"] > 0 else None
    out = CalibrationData(
        kind="cp_pipe", files=[path], a=d["a"], a_sigma=d["a_sigma"], a00_measured=a00_measured,
        mu=d["mu"][sel], var=d["var"][sel], cov=pick(d["cov"]), cov_sigma=pick(d["cov_sigma"]),
        exptime=pick(d["exptime"]), units="adu", gain=gain,
        gain_err=info["gain_err"] if gain is not None else None,
        gain_source=f"cp_pipe {info['fit_type']} fit (GAIN column, e/ADU)" if gain else
        "unknown: GAIN is not a positive number", turnoff=turnoff,
        pairs_used=[used[i] for i in order], pairs_dropped=dropped, amp=name, amps=per_amp,
        bad_amps=bad_amps, notes=notes, meta=meta)
    return truncate_lags(out, max_lag)
