"""Reading a sensor's characterization data: every input kind of ``bfdrift calibrate``.

:func:`read_calibration_input` takes the files given to the command, finds
which of four kinds they are (:func:`detect_input_kind`) and returns one
:class:`CalibrationData`. Files of different kinds in one call are an error.
Nothing read is modified. Every error names the file, the problem and what
would be accepted.

Input kinds
-----------
``'flats'`` -- flat pairs as FITS images (:func:`read_flat_pairs`)
    Any number of files, each with ``EXPTIME`` (s) in the image HDU's header
    or the primary header. The image is the first 2-d HDU that is not named
    ``MASK``; an optional 2-d ``MASK`` HDU of the same shape marks bad pixels
    (non-zero); NaN/inf pixels are masked and counted. Files are grouped by
    ``EXPTIME`` (relative tolerance ``exptime_rtol``) into levels; within a
    level, consecutive files in sorted file-name order form pairs, and an odd
    file out is dropped (and reported). A level holding a single flat is an
    error (its partner is missing or has a different ``EXPTIME``) unless
    ``drop_single``. Each pair's covariances come from
    :func:`~lsst_bfdrift.ptc.covariances.pair_covariances`. All flats must
    have one shape and one ``BUNIT``/``GAIN``. ``BUNIT`` 'adu' (also 'ADU',
    'count', 'DN') or absent: signals in ADU, gain from ``GAIN`` (e/ADU) if
    present, else unknown; ``BUNIT`` 'electron' (also 'e', 'e-'): signals in
    electrons, gain 1. Points past the PTC turn-off
    (:func:`~lsst_bfdrift.ptc.covariances.ptc_turnoff`: saturation, the
    variance falls more than ``turnoff_drop`` below its running maximum) are
    dropped and reported; at least ``min_levels`` distinct levels must remain.
    A pair whose difference has no variance
    (:func:`~lsst_bfdrift.ptc.covariances.identical_flats`) is judged before
    the turn-off is sought: one exposure twice (e.g. a copied file) is
    excluded and reported as such, never read as saturation; two constant
    images are past the turn-off (saturation) when brighter than every
    other pair, else excluded and reported.
``'ptc'`` -- a PTC text file (:func:`read_ptc_file`)
    The eotest two-column format (mean ADU, variance ADU^2 per line, ``#``
    comments; read by :func:`~lsst_bfdrift.ptc.covariances.read_ptc_text`;
    a third column is refused, not dropped unread).
    Points past the turn-off are dropped and reported as for flats.
``'amatrix'`` -- a table of area coefficients a_ij (:func:`read_amatrix_file`)
    Either the text format ``i j value sigma`` (one lag per line, header
    lines without numbers allowed, a row with a field that is not a number
    refused naming its line; a00 alone is accepted; the file does not
    declare which axis is serial, so it is oriented from the data by
    :func:`~lsst_bfdrift.ptc.acoeffs.read_acoeff_table`, as
    everywhere in the package), or an ECSV table (``# %ECSV`` first line)
    with integer columns ``i`` (serial lag), ``j`` (parallel lag) and float
    columns ``a``, ``a_err`` (per electron; a unit, if given, must convert to
    1 / electron). Lags must be non-negative integers filling the square
    0..L x 0..L, errors positive, and a00 present. Whether a00 was measured
    or set by the area sum rule is decided by
    :func:`~lsst_bfdrift.ptc.acoeffs.sum_rule_check`.
``'cp_pipe'`` -- the PTC dataset FITS of LSST's cp_pipe
    Read by :func:`~lsst_bfdrift.ptc.cp_pipe.read_cp_pipe_ptc` (its
    module documents the layout read).

Conventions: a-matrices are indexed ``a[i, j]`` with i the serial and j the
parallel lag, per electron; covariances ``cov[k, di, dj]`` likewise, in the
signal's unit squared.
"""

import math
import os
import warnings

import numpy as np
import astropy.units as u
from astropy.io import fits
from astropy.table import Table

from lsst_bfdrift.ptc.acoeffs import (AcoeffTable, acoeff_square, assign_axes, read_acoeff_table,
                                      sum_rule_check)
from lsst_bfdrift.ptc.cp_pipe import read_cp_pipe_ptc
from lsst_bfdrift.ptc.data import INPUT_KINDS, CalibrationData, describe_paths, require_levels
from lsst_bfdrift.ptc.covariances import (identical_flats, pair_covariances, ptc_turnoff,
                                          read_ptc_text)
from lsst_bfdrift.images.electrons import image_unit
from lsst_bfdrift.utils.errors import InputError, InputFileError, InputNotFoundError
from lsst_bfdrift.utils.io import hdu_pixels, not_fits_reason, open_fits, read_text_rows

__all__ = ["FITS_SUFFIXES", "ExposureLevelWarning", "exptime_level_problem",
           "detect_input_kind", "read_calibration_input", "read_flat_pairs", "read_ptc_file",
           "read_amatrix_file"]


# --------------------------------------------------------------------------- detection

#: Endings of file names taken as FITS: such a file that is not FITS is refused
#: as such, not read as a text table.
FITS_SUFFIXES = (".fits", ".fit", ".fts", ".fits.gz", ".fits.fz", ".fz")


def _is_fits(path):
    """Starts like a FITS file (or a compressed one, which astropy opens)."""
    return not_fits_reason(path) is None


#: What a text input may be, for the messages of the readers.
_TEXT_KINDS = ("a PTC (2 columns: mean ADU, variance ADU^2), an a-matrix (4 columns: i j value "
               "sigma) or an ECSV a-matrix (# %ECSV) with columns i, j, a, a_err")


def _first_data_row(path):
    """(first line, number of numeric fields of the first row of numbers).

    Header lines (no number in them) are skipped; a row mixing numbers and
    other fields is an error naming its line
    (:func:`~lsst_bfdrift.utils.io.read_text_rows`), never a header.
    """
    try:
        with open(path, encoding="utf-8") as fh:
            first = next((s for s in (line.strip() for line in fh) if s), None)
    except UnicodeDecodeError:
        raise InputError(f"{path}: neither FITS nor text; accepted inputs are FITS flats, a "
                         "cp_pipe PTC dataset FITS, a PTC text file (mean, variance) or an "
                         "a-matrix table (text 'i j value sigma' or ECSV)") from None
    if first is not None and first.startswith("# %ECSV"):
        return first, 0
    rows = read_text_rows(path, accepted=_TEXT_KINDS, limit=1)
    return first, (len(rows[0][1]) if rows else 0)


def detect_input_kind(path):
    """Kind of one input file: 'flats', 'ptc', 'amatrix' or 'cp_pipe'.

    FITS files with a 2-d image HDU are flats; FITS files with a binary
    table and no image are taken as a cp_pipe PTC dataset (checked when
    read). Text files starting with ``# %ECSV`` are a-matrix tables; other
    text files are told apart by the number of numeric columns (2: PTC, 4:
    a-matrix).

    Parameters
    ----------
    path : str or path-like

    Returns
    -------
    str
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputNotFoundError(f"{path}: no such file")
    if os.path.isdir(path):
        raise InputError(f"{path}: is a directory; give the files themselves (e.g. "
                         f"{os.path.join(path, '*.fits')})")
    if _is_fits(path):
        with open_fits(path) as hdul:
            image = any(h.is_image and h.header.get("NAXIS", 0) == 2 for h in hdul)
            table = any(isinstance(h, fits.BinTableHDU) for h in hdul)
        if image:
            return "flats"
        if table:
            return "cp_pipe"
        raise InputError(f"{path}: FITS file with neither a 2-d image HDU (a flat) nor a binary "
                         "table (a cp_pipe PTC dataset); one of those is accepted")
    if path.lower().endswith(FITS_SUFFIXES):
        # named as FITS: say so rather than read it as a table of numbers
        raise InputFileError(f"{path}: {not_fits_reason(path)}; "
                             "accepted: FITS flats or a cp_pipe PTC dataset FITS (or, named "
                             "otherwise, a PTC text file or an a-matrix table)", path)
    first, ncol = _first_data_row(path)
    if first is not None and first.startswith("# %ECSV"):
        return "amatrix"
    if ncol == 2:
        return "ptc"
    if ncol == 4:
        return "amatrix"
    raise InputError(f"{path}: text file with {ncol} numeric columns; accepted are 2 columns "
                     "(a PTC: mean ADU, variance ADU^2) or 4 columns (an a-matrix: i j value "
                     "sigma), or an ECSV table (# %ECSV) with columns i, j, a, a_err")


def read_calibration_input(paths, *, max_lag=8, amp=None, exptime_rtol=1e-3, turnoff_drop=0.05,
                           min_levels=3, drop_single=False, nsig=5.0, min_pixels=1000,
                           progress=None):
    """Read the inputs of ``bfdrift calibrate``: flats, a PTC, an a-matrix or a cp_pipe PTC.

    Parameters
    ----------
    paths : str, path-like or sequence of them
        The input files, all of one kind (see the module documentation).
        Flats: any number of FITS files; other kinds: exactly one file.
    max_lag : int, optional
        Largest covariance lag measured from flats; a-matrices and cp_pipe
        covariances with larger lags are truncated to it (noted).
    amp : str, optional
        cp_pipe: the amplifier to read (default: see :func:`read_cp_pipe_ptc`).
    exptime_rtol : float, optional
        Flats: relative tolerance of equal ``EXPTIME``.
    turnoff_drop : float, optional
        Flats and PTC files: relative fall of the variance below its running
        maximum that marks the turn-off.
    min_levels : int, optional
        Flats and PTC files: fewest distinct signal levels accepted after the
        turn-off cut.
    drop_single : bool, optional
        Flats: drop (and report) a level holding a single flat instead of
        raising.
    nsig, min_pixels
        Flats: passed to :func:`~lsst_bfdrift.ptc.covariances.pair_covariances`.
    progress : callable, optional
        Flats: called as ``progress(done, total)`` as the files are read
        (:func:`read_flat_pairs`).

    Returns
    -------
    CalibrationData

    Warns
    -----
    ExposureLevelWarning
        Flats whose levels are not proportional to their ``EXPTIME``
        (:func:`exptime_level_problem`), said as soon as the levels are
        measured.

    Raises
    ------
    FileNotFoundError
        A path does not exist.
    ValueError
        Unrecognised or bad input, or files of several kinds.
    """
    if isinstance(paths, (str, bytes)) or hasattr(paths, "__fspath__"):
        paths = [paths]
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise InputError("no input files given; accepted: FITS flats, a PTC text file, an "
                         "a-matrix table or a cp_pipe PTC dataset FITS")
    if len(set(paths)) != len(paths):
        dup = sorted({p for p in paths if paths.count(p) > 1})
        raise InputError(f"{dup[0]}: given more than once; each file may appear once")
    kinds = {p: detect_input_kind(p) for p in paths}
    found = sorted(set(kinds.values()), key=INPUT_KINDS.index)
    if len(found) > 1:
        listing = "; ".join(f"{p}: {k}" for p, k in kinds.items())
        raise InputError(f"inputs of different kinds in one call ({', '.join(found)}): "
                         f"{listing}; give files of one kind only (flats, ptc, amatrix or "
                         "cp_pipe)")
    kind = found[0]
    if amp is not None and kind != "cp_pipe":
        raise InputError(f"{paths[0]}: amp={amp!r} given, but the input is {kind}; amp selects "
                         "an amplifier of a cp_pipe PTC dataset only")
    if kind == "flats":
        return read_flat_pairs(paths, max_lag=max_lag, exptime_rtol=exptime_rtol,
                               turnoff_drop=turnoff_drop, min_levels=min_levels,
                               drop_single=drop_single, nsig=nsig, min_pixels=min_pixels,
                               progress=progress)
    if len(paths) > 1:
        raise InputError(f"{paths[1]}: only one {kind} file can be read at a time, got "
                         f"{len(paths)} ({', '.join(paths)})")
    if kind == "ptc":
        return read_ptc_file(paths[0], turnoff_drop=turnoff_drop, min_levels=min_levels)
    if kind == "amatrix":
        return read_amatrix_file(paths[0], max_lag=max_lag)
    return read_cp_pipe_ptc(paths[0], amp=amp, max_lag=max_lag, min_levels=min_levels)


# --------------------------------------------------------------------------- flats

class ExposureLevelWarning(UserWarning):
    """Flat levels not proportional to their exposure times (``EXPTIME``): a
    mislabelled file, a wrong keyword, or a bias not subtracted."""


def exptime_level_problem(exptime, mu, files, *, rtol=0.1):
    """What is wrong when flat levels are not proportional to ``EXPTIME``; None if they are.

    The signal rate ``mu / exptime`` of every pair should be the lamp's, the
    same for all: a pair more than ``rtol`` from the median rate (the lower
    median: one pair's own rate) is named.
    (A shutter delay of a few per cent of the shortest exposure stays within
    10 %; flats past the turn-off should be left out by the caller.)

    Parameters
    ----------
    exptime, mu : array_like, shape (n,)
        Exposure time (s) and mean level of each pair.
    files : sequence of sequence of str
        The files of each pair.
    rtol : float, optional
        Largest relative departure of a pair's rate from the median rate.

    Returns
    -------
    str or None
        A sentence naming the pairs out of line, with every level and
        ``EXPTIME``.
    """
    t = np.asarray(exptime, float)
    m = np.asarray(mu, float)
    ok = (t > 0) & np.isfinite(m)
    if ok.sum() < 2:
        return None
    rate = m / np.where(ok, t, np.nan)
    med = float(np.sort(rate[ok])[(int(ok.sum()) - 1) // 2])  # a pair's own rate
    if not med > 0:
        return None
    off = ok & (np.abs(rate / med - 1.0) > rtol)
    if not off.any():
        return None
    order = np.argsort(t)

    def name(k):
        return ", ".join(os.path.basename(f) for f in files[k])

    listing = "; ".join(f"{name(k)}: EXPTIME {t[k]:g} s, level {m[k]:.6g} "
                        f"({rate[k]:.4g} per s){' <-' if off[k] else ''}" for k in order)
    return (f"flat levels are not proportional to EXPTIME: {int(off.sum())} of {int(ok.sum())} "
            f"pair(s) are more than {rtol:.0%} from the median rate {med:.4g} per s "
            f"(marked <-): {listing}. Check the EXPTIME keywords (the pairs are grouped by "
            "them) and that the flats are bias-subtracted; the calibration goes on with the "
            "measured levels")


def _header_value(headers, key):
    for h in headers:
        if key in h:
            return h[key]
    return None


def _flat_header(path):
    """Header facts of one flat FITS (no pixel data read)."""
    with open_fits(path) as hdul:
        image = next((k for k, h in enumerate(hdul) if h.is_image and h.header.get("NAXIS") == 2
                      and str(h.header.get("EXTNAME", "")).upper() != "MASK"), None)
        if image is None:
            raise InputError(f"{path}: no 2-d image HDU (other than MASK); a flat needs one")
        hdr = hdul[image].header
        headers = [hdr, hdul[0].header]
        shape = (int(hdr["NAXIS2"]), int(hdr["NAXIS1"]))
        mask = next((k for k, h in enumerate(hdul)
                     if str(h.header.get("EXTNAME", "")).upper() == "MASK"), None)
        if mask is not None:
            mh = hdul[mask].header
            mshape = (mh.get("NAXIS2"), mh.get("NAXIS1")) if mh.get("NAXIS") == 2 else None
            if not hdul[mask].is_image or mshape != shape:
                raise InputError(f"{path}: MASK HDU has shape {mshape}, the image {shape}; the "
                                 "mask must be a 2-d image of the image's shape (non-zero = bad)")
        exptime = _header_value(headers, "EXPTIME")
        gain = _header_value(headers, "GAIN")
        bunit = _header_value(headers, "BUNIT")
    if exptime is None:
        raise InputError(f"{path}: no EXPTIME keyword; a flat needs its exposure time (s) as "
                         "EXPTIME in the image HDU's header or the primary header")
    try:
        exptime = float(exptime)
    except (TypeError, ValueError):
        raise InputError(f"{path}: EXPTIME = {exptime!r} is not a number; accepted: the exposure "
                         "time in seconds") from None
    if not math.isfinite(exptime):
        raise InputError(f"{path}: EXPTIME = {exptime} is not finite; accepted: the exposure "
                         "time in seconds")
    # the package's one unit rule: a stated BUNIT, else a GAIN means ADU, else ADU with
    # an unknown gain (measured from the flats)
    unit = image_unit(bunit, header_gain=gain, from_file=True, source=path)
    units, gain = unit.unit, (None if unit.unit == "electron" else unit.gain)
    return {"path": path, "hdu": image, "mask_hdu": mask, "shape": shape, "exptime": exptime,
            "gain": gain, "units": units, "bunit": bunit, "unit_note": unit.note}


def _flat_pixels(info):
    """(image, bad-pixel mask, pixels masked by MASK, non-finite pixels)."""
    with open_fits(info["path"]) as hdul:
        data = hdu_pixels(hdul[info["hdu"]], info["path"])
        given = (np.zeros(data.shape, bool) if info["mask_hdu"] is None
                 else hdu_pixels(hdul[info["mask_hdu"]], info["path"]) != 0)
    nonfinite = ~np.isfinite(data)
    return data, given | nonfinite, int(given.sum()), int((nonfinite & ~given).sum())


def _group_levels(infos, rtol):
    """Lists of infos with equal EXPTIME (within rtol), by increasing time."""
    levels = []
    for info in sorted(infos, key=lambda d: d["exptime"]):
        if levels and abs(info["exptime"] - levels[-1][0]["exptime"]) <= (
                rtol * abs(levels[-1][0]["exptime"])):
            levels[-1].append(info)
        else:
            levels.append([info])
    return levels


def _check_one_kind(infos):
    """All flats of one shape, one unit and one gain (or none), or an error naming two."""
    first = infos[0]
    for info in infos[1:]:
        if info["shape"] != first["shape"]:
            raise InputError(f"{info['path']}: image shape {info['shape']} differs from "
                             f"{first['path']} {first['shape']}; all flats must have one shape "
                             "(the same amplifier or sensor region)")
        if info["units"] != first["units"]:
            raise InputError(f"{info['path']}: BUNIT {info['bunit']!r} differs from "
                             f"{first['path']} {first['bunit']!r}; all flats must be in one unit")
        g0, g1 = first["gain"], info["gain"]
        if (g0 is None) != (g1 is None) or (g0 is not None and abs(g1 - g0) > 1e-6 * g0):
            raise InputError(f"{info['path']}: GAIN = {g1} differs from {first['path']} "
                             f"GAIN = {g0}; all flats must share one gain (or none)")


def _pair_levels(levels, exptime_rtol, drop_single, dropped):
    """(level index, flat, flat) pairs in file-name order within each level; a flat
    alone at its level is an error (or, with ``drop_single``, dropped), an odd one
    out dropped, each with its reason appended to ``dropped``."""
    pairs = []
    for k, level in enumerate(levels):
        level = sorted(level, key=lambda d: d["path"])
        if len(level) == 1:
            only = level[0]
            others = [lv[0] for lv in levels if lv is not levels[k]]
            if others:
                near = min(others, key=lambda d: abs(d["exptime"] - only["exptime"]))
                rel = abs(near["exptime"] - only["exptime"]) / only["exptime"]
                hint = (f" (nearest other level: EXPTIME = {near['exptime']:g} s in "
                        f"{near['path']}, relative difference {rel:.2g} > exptime_rtol="
                        f"{exptime_rtol:g})")
            else:
                hint = ""
            msg = (f"{only['path']}: the only flat at EXPTIME = {only['exptime']:g} s{hint}; "
                   "each level needs a pair of flats with equal EXPTIME")
            if not drop_single:
                raise InputError(msg + " (add its partner, or pass drop_single=True to drop it)")
            dropped.append({"files": [only["path"]], "exptime": only["exptime"],
                            "reason": "the only flat at its EXPTIME (no partner)"})
            continue
        for m in range(0, len(level) - 1, 2):
            pairs.append((k, level[m], level[m + 1]))
        if len(level) % 2:
            odd = level[-1]
            dropped.append({"files": [odd["path"]], "exptime": odd["exptime"],
                            "reason": f"odd file out: {len(level)} flats at EXPTIME = "
                                      f"{odd['exptime']:g} s, paired in file-name order"})
    return pairs


def read_flat_pairs(paths, *, max_lag=8, exptime_rtol=1e-3, turnoff_drop=0.05, min_levels=3,
                    drop_single=False, nsig=5.0, min_pixels=1000, progress=None):
    """Covariances of flat pairs read from FITS files.

    See the module documentation (kind ``'flats'``) for the file format,
    grouping and pairing rules; the options are those of
    :func:`read_calibration_input`.

    Parameters
    ----------
    paths : sequence of str or path-like
        FITS flats, bias-subtracted (ADU or electrons).
    progress : callable, optional
        Called as ``progress(done, total)``: a step per file whose header is
        read, then a step per flat whose pixels are read (with its pair's
        covariances), from ``progress(0, total)`` on.

    Returns
    -------
    CalibrationData
        ``kind`` 'flats'; one PTC point per pair used.

    Warns
    -----
    ExposureLevelWarning
        The levels of the pairs below the turn-off are not proportional to
        their ``EXPTIME`` (:func:`exptime_level_problem`); it is also added
        to the notes.
    """
    paths = [os.fspath(p) for p in paths]
    if len(paths) < 2:
        name = paths[0] if paths else "(no file)"
        raise InputError(f"{name}: only one flat given; a photon transfer curve needs pairs of "
                         f"flats (two FITS files with equal EXPTIME) at >= {min_levels} "
                         "exposure levels")
    done, total = 0, 2 * len(paths)

    def step(n=1):
        nonlocal done
        done += n
        if progress is not None:
            progress(done, total)

    step(0)
    infos = []
    for p in paths:
        infos.append(_flat_header(p))
        step()
    first = infos[0]
    _check_one_kind(infos)
    notes, dropped = [], []
    for info in infos:
        if not info["exptime"] > 0:
            dropped.append({"files": [info["path"]], "exptime": info["exptime"],
                            "reason": f"EXPTIME = {info['exptime']} s is not positive (a bias "
                                      "or dark, not a flat)"})
    usable = [i for i in infos if i["exptime"] > 0]
    levels = _group_levels(usable, exptime_rtol)
    pairs = _pair_levels(levels, exptime_rtol, drop_single, dropped)
    files = describe_paths(paths)
    require_levels(len({k for k, _, _ in pairs}), min_levels, "with a pair of flats", files,
                    dropped)
    total = len(paths) + 2 * len(pairs)  # the flats left out need no pixels read
    step(0)
    rows, constant, ncopies = [], [], 0
    for _, f1, f2 in pairs:
        d1, m1, g1, n1 = _flat_pixels(f1)
        d2, m2, g2, n2 = _flat_pixels(f2)
        # a zero difference variance is judged before the turn-off: it is not a fall of
        # the variance, and must not drop every brighter pair as past a turn-off
        same = identical_flats(d1, d2, mask=m1 | m2)
        entry = {"files": [f1["path"], f2["path"]],
                 "exptime": 0.5 * (f1["exptime"] + f2["exptime"])}
        if same is not None:
            step(2)
        if same is not None and same[0] == "copies":
            ncopies += 1
            dropped.append(entry | {"reason": f"{same[1]}; pair excluded"})
            continue
        if same is not None:  # both constant: saturation if brighter than every other pair
            good = ~(m1 | m2)
            constant.append(entry | {"mu": 0.5 * float(d1[good].mean() + d2[good].mean()),
                                     "var": 0.0, "reason": same[1]})
            continue
        try:
            pc = pair_covariances(d1, d2, max_lag=max_lag, mask=m1 | m2, nsig=nsig,
                                  min_pixels=min_pixels)
        except ValueError as err:
            raise InputError(f"flat pair {f1['path']}, {f2['path']}: {err}") from None
        del d1, d2
        step(2)
        rows.append({"files": [f1["path"], f2["path"]],
                     "exptime": 0.5 * (f1["exptime"] + f2["exptime"]), "mu": pc.mu,
                     "var": float(pc.cov[0, 0]), "nan_pixels": n1 + n2,
                     "mask_pixels": g1 + g2, "nmasked": pc.nmasked, "_pc": pc})
        if n1 + n2:
            notes.append(f"{f1['path']}, {f2['path']}: {n1 + n2} NaN/inf pixel(s) masked")
    if ncopies:
        notes.append(f"{ncopies} pair(s) of one exposure twice (zero difference variance) "
                     "excluded: see the dropped pairs")
    rows.sort(key=lambda r: r["mu"])
    mu = np.array([r["mu"] for r in rows])
    var = np.array([r["var"] for r in rows])
    turnoff = ptc_turnoff(mu, var, drop=turnoff_drop)
    top = float(mu.max()) if mu.size else -np.inf
    if any(c["mu"] > top for c in constant):  # saturated: the turn-off is below them
        turnoff = min(turnoff, top)
    used = []
    for r in rows:
        if r["mu"] > turnoff:
            dropped.append({k: v for k, v in r.items() if k != "_pc"}
                           | {"reason": f"past the PTC turn-off at {turnoff:.6g} "
                                        f"{first['units']} (the variance falls more than "
                                        f"{turnoff_drop:.0%} below its running maximum: "
                                        "saturation)"})
        else:
            used.append(r)
    for c in constant:
        if c["mu"] > top:
            c["reason"] = (f"past the PTC turn-off at {turnoff:.6g} {first['units']}: "
                           f"{c['reason']}")
        else:
            c["reason"] = (f"{c['reason']}; below brighter pairs, so not saturation: pair "
                           "excluded")
        dropped.append(c)
    nlev = len(_group_levels([{"exptime": r["exptime"]} for r in used], exptime_rtol))
    require_levels(nlev, min_levels, "remain below the PTC turn-off", files, dropped)
    problem = exptime_level_problem([r["exptime"] for r in used], [r["mu"] for r in used],
                                    [r["files"] for r in used])
    if problem is not None:  # said now, before any fit
        warnings.warn(problem, ExposureLevelWarning, stacklevel=2)
        notes.append(problem)
    units = first["units"]
    if units == "electron":
        gain, source = 1.0, "BUNIT = 'electron': signals in electrons"
    elif first["gain"] is not None:
        gain, source = first["gain"], "GAIN keyword (e/ADU)"
    else:
        gain, source = None, "unknown: no GAIN keyword; signals kept in ADU"
        notes.append("no GAIN keyword: signals and covariances in ADU, gain to be fitted")
    notes.append(first["unit_note"])  # the unit rule's own sentence, as every command says it
    return CalibrationData(
        kind="flats", files=paths, mu=np.array([r["mu"] for r in used]),
        var=np.array([r["var"] for r in used]),
        cov=np.array([r["_pc"].cov for r in used]), npix=np.array([r["_pc"].npix for r in used]),
        exptime=np.array([r["exptime"] for r in used]), units=units, gain=gain,
        gain_source=source, turnoff=turnoff,
        pairs_used=[{k: v for k, v in r.items() if k != "_pc"} for r in used],
        pairs_dropped=dropped, notes=notes,
        meta={"max_lag": int(max_lag), "exptime_rtol": exptime_rtol,
              "shape": list(first["shape"])})


# --------------------------------------------------------------------------- PTC text

def read_ptc_file(path, *, turnoff_drop=0.05, min_levels=3):
    """A two-column PTC text file (eotest format: mean ADU, variance ADU^2).

    Parameters
    ----------
    path : str or path-like
    turnoff_drop, min_levels
        As in :func:`read_calibration_input`.

    Returns
    -------
    CalibrationData
        ``kind`` 'ptc'; ``mu``, ``var`` below the turn-off, no covariances.
    """
    path = os.fspath(path)
    try:
        mu, var = read_ptc_text(path)
    except ValueError as err:
        msg = str(err)
        raise InputError(msg if msg.startswith(path) else f"{path}: {msg}; accepted: lines of "
                         "two numbers (mean ADU, variance ADU^2), '#' comments") from None
    bad = ~(np.isfinite(mu) & np.isfinite(var) & (mu > 0) & (var > 0))
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise InputError(f"{path}: {int(bad.sum())} PTC point(s) not finite and positive, e.g. "
                         f"mean {mu[k]!r}, variance {var[k]!r}; accepted: positive means (ADU) "
                         "and variances (ADU^2)")
    turnoff = ptc_turnoff(mu, var, drop=turnoff_drop)
    keep = mu <= turnoff
    used = [{"index": k, "mu": float(m), "var": float(v)}
            for k, (m, v) in enumerate(zip(mu, var)) if keep[k]]
    dropped = [{"index": k, "mu": float(m), "var": float(v),
                "reason": f"past the PTC turn-off at {turnoff:.6g} ADU (the variance falls more "
                          f"than {turnoff_drop:.0%} below its running maximum: saturation)"}
               for k, (m, v) in enumerate(zip(mu, var)) if not keep[k]]
    require_levels(int(keep.sum()), min_levels, "remain below the PTC turn-off", path, dropped)
    return CalibrationData(kind="ptc", files=[path], mu=mu[keep], var=var[keep], units="adu",
                           gain_source="unknown: a PTC file gives no gain (to be fitted)",
                           turnoff=turnoff, pairs_used=used, pairs_dropped=dropped,
                           notes=["PTC file: points sorted by mean; no covariances beyond "
                                  "the variance"])


# --------------------------------------------------------------------------- a-matrix

def _ecsv_rows(path):
    try:
        t = Table.read(path, format="ascii.ecsv")
    except Exception as err:  # noqa: BLE001 - any parse failure is a bad file
        raise InputError(f"{path}: not a readable ECSV table ({err}); accepted: ECSV with "
                         "columns i, j, a, a_err") from None
    missing = [c for c in ("i", "j", "a", "a_err") if c not in t.colnames]
    if missing:
        raise InputError(f"{path}: ECSV table lacks column(s) {missing} (found {t.colnames}); "
                         "accepted: columns i (serial lag), j (parallel lag), a, a_err "
                         "(per electron)")
    out = []
    for c in ("i", "j", "a", "a_err"):
        col = t[c]
        if getattr(col, "mask", None) is not None and np.any(col.mask):
            raise InputError(f"{path}: column {c} has missing values; every row needs i, j, a, "
                             "a_err")
        if col.dtype.kind not in "biuf":
            raise InputError(f"{path}: column {c} is not numeric (dtype {col.dtype}); accepted: "
                             "integer lags i, j and float a, a_err")
        if c in ("a", "a_err") and col.unit is not None:
            try:
                vals = (np.asarray(col, float) * col.unit).to_value(1 / u.electron)
            except u.UnitConversionError:
                raise InputError(f"{path}: column {c} has unit {col.unit}; accepted: per "
                                 "electron (1 / electron) or no unit") from None
        else:
            vals = np.asarray(col, float)
        out.append(vals)
    return tuple(out), t.meta


def read_amatrix_file(path, *, max_lag=None):
    """An a-matrix table: text ``i j value sigma`` or ECSV ``i, j, a, a_err``.

    Parameters
    ----------
    path : str or path-like
    max_lag : int, optional
        Truncate to lags <= max_lag (noted).

    Returns
    -------
    CalibrationData
        ``kind`` 'amatrix'; ``a``, ``a_sigma`` [serial, parallel] per electron.
    """
    path = os.fspath(path)
    first, _ = _first_data_row(path)
    notes = []
    if first is not None and first.startswith("# %ECSV"):
        (i, j, a, s), tmeta = _ecsv_rows(path)
        A, S = acoeff_square(path, i, j, a, s)
        table = AcoeffTable(A, S, source=path)
        table.axis_note = "ECSV columns i (serial), j (parallel) taken as given"
        if A.shape[0] > 1 and A[1, 0] > A[0, 1]:
            notes.append(f"a[1,0] = {A[1, 0]:.3g} (serial) exceeds a[0,1] = {A[0, 1]:.3g} "
                         "(parallel), unlike every measured LSST sensor: check the i/j columns")
        fmt = "ecsv"
    else:
        # the file declares no axes: oriented from the data, as read_acoeff_table(orient=True)
        table = assign_axes(read_acoeff_table(path, orient=False))
        fmt = "text"
    ok, rule = sum_rule_check(table)
    table.exclude_a00 = ok
    notes.append(table.axis_note)
    notes.append(rule)
    if max_lag is not None and table.max_lag > int(max_lag):
        notes.append(f"table has lags up to {table.max_lag}, truncated to max_lag={int(max_lag)}")
        table = table.truncated(max_lag)
    return CalibrationData(kind="amatrix", files=[path], a=table.a, a_sigma=table.sigma,
                           a00_measured=not table.exclude_a00,
                           gain_source="unknown: an a-matrix table gives no gain", notes=notes,
                           meta={"format": fmt, "axis_note": table.axis_note,
                                 "sum_rule": rule})


# --------------------------------------------------------------------------- cp_pipe


