"""LSST's brighter-fatter calibration products, read and written.

Two products of LSST's calibration pipeline (cp_pipe) feed ip_isr's
corrections:

``electroBfDistortionMatrix`` (OBSTYPE ``BF_DISTORTION_MATRIX``, versions 1.0 and 1.1)
    The ASTIER23 product: the measured a-matrix and its errors, the fitted
    electrostatic model (Astier & Regnault 2023) with its parameters, and the
    per-edge boundary shifts ``aN``, ``aS``, ``aE``, ``aW`` per electron
    (arrays [i serial, j parallel]), optionally per filter (version 1.1).
``bfk`` (BrighterFatterKernel, versions 1.0 and 1.1)
    The COULTON18 product: brighter-fatter kernels per amplifier and per
    detector ([y, x], per electron; the Laplacian of a kernel is the
    a-matrix).

Both are IsrCalib FITS files: an empty primary HDU and binary tables whose
header holds the calibration's metadata (``OBSTYPE``, ``<OBSTYPE>_SCHEMA``,
``<OBSTYPE>_VERSION``, ...), one row per amplifier (``bfk``) or a single row
(``electroBfDistortionMatrix``), arrays flattened. The layout was taken from
ip_isr's public schema (the column names of ``toTable``); the files
:func:`write_distortion_matrix` and :func:`write_bfk` write are the ones
ip_isr's ``readFits`` reads, and those it writes are read here. Each
product gives a :class:`~lsst_bfdrift.templates.template.DistortionTemplate`
(:meth:`DistortionMatrix.template`, :meth:`BfKernel.template`), so that a
user can bring a DP2 (or DP1) product and correct or compare with it.
"""

import dataclasses
import os
import warnings

import numpy as np
from astropy.io import fits
from astropy.table import Table

from lsst_bfdrift.correction.solvers import area_coefficients, coulton18_kernel
from lsst_bfdrift.templates.edge_shifts import (template_edge_shifts, template_from_edge_shifts,
                                                template_from_kernel)
from lsst_bfdrift.utils.errors import InputError, InputFileError
from lsst_bfdrift.utils.io import atomic_output, check_output, open_fits

__all__ = ["DistortionMatrix", "BfKernel", "read_distortion_matrix", "write_distortion_matrix",
           "read_bfk", "write_bfk", "template_products", "DISTORTION_OBSTYPE", "BFK_OBSTYPE",
           "READ_VERSIONS"]

#: OBSTYPE of an electroBfDistortionMatrix.
DISTORTION_OBSTYPE = "BF_DISTORTION_MATRIX"
#: OBSTYPE of a brighter-fatter kernel.
BFK_OBSTYPE = "bfk"
#: Schema versions read, by OBSTYPE; the version written is the last.
READ_VERSIONS = {DISTORTION_OBSTYPE: (1.0, 1.1), BFK_OBSTYPE: (1.0, 1.1)}
_SCHEMA = {DISTORTION_OBSTYPE: "ELectrostatic brighter-fatter pixel distortion model",
           BFK_OBSTYPE: "Brighter-fatter kernel"}
_CLASS = {DISTORTION_OBSTYPE: "lsst.ip.isr.electrostaticBrighterFatter."
                              "ElectrostaticBrighterFatterDistortionMatrix",
          BFK_OBSTYPE: "lsst.ip.isr.brighterFatterKernel.BrighterFatterKernel"}


def _float(value):
    """A table value as float (a masked one, as astropy reads a NaN, is NaN)."""
    return float(np.ma.filled(np.ma.asarray(value, dtype=float), np.nan))


def _text(values):
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.atleast_1d(values)]


def _read_tables(path, obstype, what):
    """The tables of an IsrCalib FITS file, checked to be ``obstype`` of a version read."""
    path = os.fspath(path)
    with open_fits(path) as hdul:
        tables = [k for k, h in enumerate(hdul) if isinstance(h, fits.BinTableHDU)]
        if not tables:
            raise InputFileError(f"{path}: no binary table HDU; an LSST {what} is an IsrCalib "
                                 "FITS file (an empty primary and tables)", path)
    out = [Table.read(path, hdu=k) for k in tables]
    meta = out[0].meta
    found = meta.get("OBSTYPE")
    if found != obstype:
        raise InputFileError(f"{path}: OBSTYPE = {found!r}; an LSST {what} has OBSTYPE "
                             f"{obstype!r}", path)
    key = f"{obstype}_VERSION"
    version = meta.get(key)
    try:
        version = float(version)
    except (TypeError, ValueError):
        raise InputFileError(f"{path}: {key} = {version!r} is not a schema version; this "
                             f"lsst_bfdrift reads versions {READ_VERSIONS[obstype]}",
                             path) from None
    if version not in READ_VERSIONS[obstype]:
        raise InputFileError(f"{path}: {what} schema version {version:g}; this lsst_bfdrift "
                             f"reads versions {', '.join(f'{v:g}' for v in READ_VERSIONS[obstype])}",
                             path)
    return out, dict(meta), version


def _write_tables(path, tables, obstype, *, overwrite, inputs=()):
    check_output(path, inputs, overwrite=overwrite)
    version = READ_VERSIONS[obstype][-1]
    for t in tables:
        t.meta.update({"OBSTYPE": obstype, f"{obstype}_SCHEMA": _SCHEMA[obstype],
                       f"{obstype}_VERSION": version, "CALIBCLS": _CLASS[obstype]})
    hdus = [fits.PrimaryHDU()]
    with warnings.catch_warnings():  # long metadata keys become HIERARCH cards, as in ip_isr's
        warnings.simplefilter("ignore", fits.verify.VerifyWarning)
        hdus += [fits.table_to_hdu(t) for t in tables]
    with atomic_output(path, overwrite=overwrite, inputs=inputs) as tmp:
        fits.HDUList(hdus).writeto(tmp)


@dataclasses.dataclass
class DistortionMatrix:
    """An electroBfDistortionMatrix: LSST's ASTIER23 calibration.

    Attributes
    ----------
    a_matrix, a_sigma : ndarray, shape (R, R)
        The measured a_ij and their errors (per electron), [i serial, j
        parallel], R = ``input_range``.
    a_model : ndarray, shape (F, F)
        The fitted model's a_ij, F = ``fit_range``.
    shifts : tuple of ndarray, shape (F, F)
        ``aN``, ``aS``, ``aE``, ``aW``: outward edge shifts per electron.
    fit_params, fit_errors : dict
        Parameter name -> value and error.
    free_params : list of str
    chi2, reduced_chi2 : float
    covariance : ndarray
        Of the free parameters.
    used : ndarray of bool, shape (R, R)
        Lags in the fit.
    gain : dict
        Amplifier name -> gain (e/ADU).
    bad_amps : list of str
    normalization : list of float
        Multiplicative and additive normalisation of the model.
    filters : dict
        Physical filter -> its four shift arrays (version 1.1; may be empty).
    meta : dict
        The file's metadata.
    """

    a_matrix: np.ndarray
    a_sigma: np.ndarray
    a_model: np.ndarray
    shifts: tuple
    fit_params: dict = dataclasses.field(default_factory=dict)
    fit_errors: dict = dataclasses.field(default_factory=dict)
    free_params: list = dataclasses.field(default_factory=list)
    chi2: float = np.nan
    reduced_chi2: float = np.nan
    covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    used: np.ndarray = None
    gain: dict = dataclasses.field(default_factory=dict)
    bad_amps: list = dataclasses.field(default_factory=list)
    normalization: list = dataclasses.field(default_factory=lambda: [1.0, 0.0])
    filters: dict = dataclasses.field(default_factory=dict)
    meta: dict = dataclasses.field(default_factory=dict)

    @property
    def fit_range(self):
        """Side of the shift arrays."""
        return self.shifts[0].shape[0]

    def template(self, *, band=None, size=None, edge_samples=8, charge=1e4):
        """The template whose edges move by these shifts (per filter with ``band``).

        Parameters
        ----------
        band : str, optional
            A physical filter of ``filters``; default the filter-independent
            shifts.
        size, edge_samples, charge
            See :func:`~lsst_bfdrift.templates.edge_shifts.template_from_edge_shifts`.
        """
        if band is None:
            shifts = self.shifts
        elif band in self.filters:
            shifts = self.filters[band]
        else:
            raise InputError(f"filter {band!r} is not in this distortion matrix; it has "
                             f"{sorted(self.filters) or 'none'}")
        meta = {"source": "LSST electroBfDistortionMatrix (ASTIER23)",
                "method": "astier23", "band": band}
        return template_from_edge_shifts(*shifts, size=size, edge_samples=edge_samples,
                                         charge=charge, meta=meta)


def read_distortion_matrix(path):
    """Read an electroBfDistortionMatrix FITS file (versions 1.0 and 1.1).

    Raises
    ------
    InputFileError
        Not an IsrCalib FITS file, another OBSTYPE, or another schema version
        (the message names the file, what was found and what is read).
    """
    tables, meta, version = _read_tables(path, DISTORTION_OBSTYPE, "electroBfDistortionMatrix")
    r = tables[0][0]
    try:
        n_in, n_fit = int(r["INPUT_RANGE"]), int(r["FIT_RANGE"])

        def arr(name, n):
            return np.asarray(r[name], dtype=float).reshape(n, n)

        names = _text(r["FIT_PARAM_NAMES"])
        free = _text(r["FREE_FIT_PARAM_NAMES"])
        shifts = tuple(arr(k, n_fit) for k in ("A_N", "A_S", "A_E", "A_W"))
        filters = {}
        if version >= 1.1:
            bands = _text(r["AVAILABLE_FILTERS"]) if len(r["AVAILABLE_FILTERS"]) else []
            for k, band in enumerate(bands):
                filters[band] = tuple(np.asarray(r[c][k], dtype=float).reshape(n_fit, n_fit)
                                      for c in ("A_N_BY_FILTER", "A_S_BY_FILTER",
                                                "A_E_BY_FILTER", "A_W_BY_FILTER"))
        amps = _text(r["AMPNAMES"]) if len(r["AMPNAMES"]) else []
        cov = np.asarray(r["FIT_PARAM_COV_MATRIX"], dtype=float)
        return DistortionMatrix(
            a_matrix=arr("A_MATRIX", n_in), a_sigma=arr("A_MATRIX_SIGMA", n_in),
            a_model=arr("A_MATRIX_MODEL", n_fit), shifts=shifts,
            fit_params=dict(zip(names, (float(v) for v in r["FIT_PARAMS"]))),
            fit_errors=dict(zip(names, (float(v) for v in r["FIT_PARAM_ERRORS"]))),
            free_params=free, chi2=float(r["FIT_CHI2"]),
            reduced_chi2=float(r["FIT_REDUCED_CHI2"]),
            covariance=cov.reshape(len(free), len(free)) if cov.size == len(free) ** 2
            else cov, used=arr("USED_PIXELS", n_in).astype(bool),
            gain=dict(zip(amps, (_float(g) for g in np.atleast_1d(r["GAIN"])))),
            bad_amps=_text(r["BAD_AMPS"]) if len(r["BAD_AMPS"]) else [],
            normalization=[float(v) for v in r["MODEL_NORMALIZATION"]], filters=filters,
            meta=meta)
    except (KeyError, ValueError, IndexError) as exc:
        raise InputFileError(f"{os.fspath(path)}: not a readable electroBfDistortionMatrix "
                             f"version {version:g} ({exc})", os.fspath(path)) from exc


def write_distortion_matrix(path, matrix, *, overwrite=False, inputs=()):
    """Write ``matrix`` as an electroBfDistortionMatrix FITS file (version 1.1),
    atomically; an existing file only with ``overwrite``."""
    m = matrix
    n_fit = m.fit_range
    names = list(m.fit_params)
    filters = list(m.filters)
    row = {
        "AMPNAMES": list(m.gain) or ["detector"],
        "INPUT_RANGE": m.a_matrix.shape[0], "FIT_RANGE": n_fit,
        "BAD_AMPS": list(m.bad_amps),
        "GAIN": [float(g) for g in m.gain.values()] or [np.nan],
        "A_MATRIX": m.a_matrix.ravel(), "A_MATRIX_SIGMA": m.a_sigma.ravel(),
        "A_MATRIX_MODEL": m.a_model.ravel(),
        "A_MATRIX_SUM": float(np.nansum(m.a_matrix)),
        "A_MATRIX_MODEL_SUM": float(np.nansum(m.a_model)),
        "MODEL_NORMALIZATION": [float(v) for v in m.normalization],
        "USED_PIXELS": (np.ones(m.a_matrix.shape, bool) if m.used is None else m.used).ravel(),
        "FIT_PARAM_NAMES": names, "FREE_FIT_PARAM_NAMES": list(m.free_params),
        "FIT_PARAMS": [float(m.fit_params[k]) for k in names],
        "FIT_PARAM_ERRORS": [float(m.fit_errors.get(k, np.nan)) for k in names],
        "FIT_CHI2": float(m.chi2), "FIT_REDUCED_CHI2": float(m.reduced_chi2),
        "FIT_PARAM_COV_MATRIX": np.asarray(m.covariance, float).ravel(),
        "ATH": m.a_model.ravel(), "ATH_MINUS_BETA": m.a_model.ravel(),
        "A_N": m.shifts[0].ravel(), "A_S": m.shifts[1].ravel(),
        "A_E": m.shifts[2].ravel(), "A_W": m.shifts[3].ravel(),
        "AVAILABLE_FILTERS": filters,
        "A_MATRIX_MODEL_BY_FILTER": [m.a_model.ravel() for _ in filters],
        "ATH_BY_FILTER": [m.a_model.ravel() for _ in filters],
        "ATH_MINUS_BETA_BY_FILTER": [m.a_model.ravel() for _ in filters],
    }
    for k, col in enumerate(("A_N_BY_FILTER", "A_S_BY_FILTER", "A_E_BY_FILTER",
                             "A_W_BY_FILTER")):
        row[col] = [m.filters[b][k].ravel() for b in filters]
    table = Table([row])
    table.meta = {k: v for k, v in m.meta.items() if k not in ("OBSTYPE",)}
    table.meta.update({"INPUT_RANGE": m.a_matrix.shape[0], "FIT_RANGE": n_fit})
    _write_tables(path, [table], DISTORTION_OBSTYPE, overwrite=overwrite, inputs=inputs)


@dataclasses.dataclass
class BfKernel:
    """A brighter-fatter kernel (LSST's ``bfk``): the COULTON18 calibration.

    Attributes
    ----------
    kernel : ndarray, shape (N, N)
        The detector's kernel ([y, x], per electron): the detector kernel of
        the file, else the mean of its valid amplifiers' kernels.
    amp_kernels : dict
        Amplifier -> kernel.
    valid : dict
        Amplifier -> whether its kernel is valid.
    gain : dict
        Amplifier -> gain (e/ADU).
    level : str
        ``'AMP'`` or ``'DETECTOR'``.
    meta : dict
    """

    kernel: np.ndarray
    amp_kernels: dict = dataclasses.field(default_factory=dict)
    valid: dict = dataclasses.field(default_factory=dict)
    gain: dict = dataclasses.field(default_factory=dict)
    level: str = "DETECTOR"
    meta: dict = dataclasses.field(default_factory=dict)

    def template(self, *, edge_samples=8, charge=1e4):
        """The template whose edges move by the kernel's gradient
        (:func:`~lsst_bfdrift.templates.edge_shifts.template_from_kernel`)."""
        return template_from_kernel(self.kernel, edge_samples=edge_samples, charge=charge,
                                    meta={"source": "LSST bfk (COULTON18)",
                                          "method": "coulton18"})


def read_bfk(path):
    """Read a brighter-fatter kernel FITS file (``bfk``, versions 1.0 and 1.1).

    Raises
    ------
    InputFileError
        Not an IsrCalib FITS file, another OBSTYPE or schema version, or no
        valid kernel in it.
    """
    tables, meta, version = _read_tables(path, BFK_OBSTYPE, "brighter-fatter kernel (bfk)")
    path = os.fspath(path)
    shape = (int(meta.get("KERNEL_DX", 0)), int(meta.get("KERNEL_DY", 0)))
    try:
        amps = tables[0]
        amp_kernels, valid, gain = {}, {}, {}
        for row in amps:
            name = _text(row["AMPLIFIER"])[0]
            amp_kernels[name] = np.ma.filled(np.ma.asarray(row["KERNEL"], dtype=float),
                                             np.nan).reshape(shape)
            valid[name] = bool(row["VALID"])
            gain[name] = _float(row["GAIN"])
        det = None
        if len(tables) > 1 and len(tables[1]):
            det = np.asarray(tables[1][0]["KERNEL"], dtype=float).reshape(shape)
    except (KeyError, ValueError, IndexError) as exc:
        raise InputFileError(f"{path}: not a readable bfk version {version:g} ({exc})",
                             path) from exc
    if det is None:
        good = [k for n, k in amp_kernels.items() if valid.get(n) and np.all(np.isfinite(k))]
        if not good:
            raise InputFileError(f"{path}: no detector kernel and no valid amplifier kernel",
                                 path)
        det = np.mean(good, axis=0)
    return BfKernel(kernel=det, amp_kernels=amp_kernels, valid=valid, gain=gain,
                    level=str(meta.get("LEVEL", "AMP")), meta=meta)


def write_bfk(path, kernel, *, detector="detector", gain=None, overwrite=False, inputs=()):
    """Write ``kernel`` ([y, x], per electron, odd square) as a ``bfk`` FITS file
    (version 1.1, level DETECTOR, one amplifier row holding the same kernel),
    atomically; an existing file only with ``overwrite``."""
    k = np.asarray(kernel, dtype=float)
    if k.ndim != 2 or k.shape[0] != k.shape[1] or k.shape[0] % 2 != 1:
        raise InputError(f"kernel must be a square array of odd size, got {k.shape}")
    amp = Table([{"AMPLIFIER": detector, "EXP_ID_MASK": [True], "RAW_MEANS": [np.nan],
                  "RAW_VARIANCES": [np.nan], "RAW_XCORRS": [np.nan],
                  "GAIN": np.nan if gain is None else float(gain), "NOISE": np.nan,
                  "MEAN_XCORRS": np.zeros(k.size), "KERNEL": k.ravel(), "VALID": True}])
    det = Table([{"DETECTOR": detector, "KERNEL": k.ravel()}])
    meta = {"LEVEL": "DETECTOR", "KERNEL_DX": k.shape[0], "KERNEL_DY": k.shape[1]}
    amp.meta.update(meta)
    det.meta.update(meta)
    _write_tables(path, [amp, det], BFK_OBSTYPE, overwrite=overwrite, inputs=inputs)


def template_products(template, *, max_lag=None):
    """The kernel and edge shifts of a template, as LSST's products hold them:
    (kernel [y, x] of the template's size, (aN, aS, aE, aW) to ``max_lag``)."""
    return coulton18_kernel(area_coefficients(template)), template_edge_shifts(template,
                                                                                 max_lag)
