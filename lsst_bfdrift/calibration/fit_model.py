"""The model the calibration fits: its candidate parameters, numerics and start Jacobian.

:func:`~lsst_bfdrift.calibration.tuning.calibrate` fits the electrostatic
model's a_ij (:func:`model_acoeffs`: the linear area response of the
template, ``definition='alpha'`` of
:func:`~lsst_bfdrift.calibration.acoeff_model.electrostatic_acoeffs`, with
the numerical settings :data:`MODEL_SETTINGS`) over the free parameters it
chooses among :data:`CANDIDATES`, starting at :func:`default_start` (the
bundled template's sensor) from the derivatives :func:`start_jacobian`
gives: package data for the default start and candidates
(:func:`write_start_jacobian`), computed otherwise.
"""

import json

import numpy as np

from lsst_bfdrift.calibration.acoeff_model import electrostatic_acoeffs
from lsst_bfdrift.calibration.fitting import FitError
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.io import data_path, write_text

__all__ = ["CANDIDATES", "CHARGE", "CONVERGED_MODEL_SETTINGS", "MODEL_NUMERICS",
           "MODEL_SETTINGS", "START_JACOBIAN_FILE", "START_JACOBIAN_MAX_LAG", "default_start",
           "model_acoeffs", "start_jacobian", "write_start_jacobian"]

#: Candidate free parameters and their bounds: the dipole unit xi0 (e), the
#: buried-channel depth (um, sets the charge dipole), the collection height
#: (um), the clock-pair separation (um), the backside bias (V) and the bulk
#: doping (cm^-3), which together set where in the bulk the backdrop field
#: cancels the barriers' lateral field (the paper's footnote on the
#: clock-dipole knob), the clock-barrier and channel-stop strengths
#: (xi0), the lateral rms size of the collected charge cloud (um) and its
#: extra variance along the columns (um^2).
CANDIDATES = {"channel_depth": (0.05, 6.0), "xi0": (300.0, 3e4),
              "collection_height": (0.05, 6.0), "clock_separation": (0.1, 8.0),
              "v_bss": (-150.0, -10.0), "acceptor_density": (1e11, 1e13),
              "xi_ck": (0.5, 30.0), "xi_cs": (-60.0, -2.0), "charge_cloud": (0.0, 2.8),
              "charge_variance_parallel": (0.0, 8.0)}

#: Aggressor charge (e) of the model evaluations and of the template.
CHARGE = 1e4


def default_start():
    """Sensor parameters of the bundled default template (the fit's default start)."""
    meta = load_default_template().meta
    return SensorParameters.from_dict(meta["params"]) if "params" in meta else SensorParameters()


#: Numerical settings of :func:`model_acoeffs` (the fit's model a_ij):
#: samples per edge and their spacing for lags 0-1 (``near_*``) and beyond
#: (``far_*``), bisection tolerance (px) and aggressor charge (e). Their
#: polygons put the a_ij of lags 0-2 up to ~18-26 % (a10) from their converged
#: values (``benchmarks/calibration/model_convergence.py``).
MODEL_SETTINGS = {"near_samples": 16, "far_samples": 6, "near_spacing": "uniform",
                  "far_spacing": "tan", "tol": 2e-6, "charge": CHARGE}

#: Settings whose a_ij lie within ~1-2 % of their converged values at lags
#: 0-3 (samples dense at the corners), for 1.2-1.6x the time.
CONVERGED_MODEL_SETTINGS = {**MODEL_SETTINGS, "near_samples": 32, "far_samples": 12,
                            "near_spacing": "ends", "far_spacing": "ends"}

#: The fit's numerics by name (``bfdrift calibrate --model-numerics``).
MODEL_NUMERICS = {"fit": MODEL_SETTINGS, "converged": CONVERGED_MODEL_SETTINGS}


def model_acoeffs(params, max_lag, *, settings=None):
    """The model's a_ij (1/e) used by the fit: linear area response of the
    template at the settings' charge, lags 0..max_lag, [i serial, j parallel].

    ``settings``: numerical settings (default :data:`MODEL_SETTINGS`; see
    :data:`CONVERGED_MODEL_SETTINGS`)."""
    s = MODEL_SETTINGS if settings is None else _checked_settings(settings)
    L = int(max_lag)
    return electrostatic_acoeffs(params, max_lag=max(L, 1), charge=s["charge"], tol=s["tol"],
                                 near_samples=s["near_samples"], far_samples=s["far_samples"],
                                 near_spacing=s["near_spacing"], far_spacing=s["far_spacing"],
                                 definition="alpha")[:L + 1, :L + 1]


def _checked_settings(settings):
    if not isinstance(settings, dict) or set(settings) != set(MODEL_SETTINGS):
        raise InputError(f"model settings must be a dict with keys {sorted(MODEL_SETTINGS)}, "
                         f"got {settings!r}")
    return settings


#: Package data: the model's a_ij and their derivatives at :func:`default_start`
#: for every candidate (:func:`write_start_jacobian`).
START_JACOBIAN_FILE = "start_jacobian.json"

#: Largest lag stored in :data:`START_JACOBIAN_FILE` (the 21 x 21 template's).
START_JACOBIAN_MAX_LAG = 10


def _step(x, lo, hi):
    """Forward-difference step of a parameter at ``x`` within (lo, hi)."""
    h = 0.02 * max(abs(x), 1e-3 * (hi - lo))
    if x in (lo, hi):  # on a bound (e.g. a point charge): a secant inwards
        h = 0.1 * (hi - lo)
    if x + h >= hi:
        h = -h
    return h


def _compute_jacobian(model, x0, candidates):
    m0 = model(x0)
    if not np.all(np.isfinite(m0)):
        raise FitError("the model has no finite a_ij at the start parameters")
    J = np.empty(m0.shape + (len(candidates),))
    for k, (n, (lo, hi)) in enumerate(candidates.items()):
        h = _step(x0[n], lo, hi)
        J[..., k] = np.nan_to_num((model({**x0, n: x0[n] + h}) - m0) / h)
    return m0, J


def _shipped(start, candidates, max_lag, settings):
    """(m0, J) sliced from the package data, or None when they do not apply."""
    try:
        with open(data_path(START_JACOBIAN_FILE)) as fh:
            d = json.load(fh)
    except (OSError, ValueError):
        return None
    if (d.get("start") != json.loads(start.to_json()) or d.get("model") != settings
            or int(max_lag) > int(d.get("max_lag", -1))):
        return None
    stored = d.get("candidates", {})
    if any(n not in stored or list(stored[n]) != [float(v) for v in b]
           for n, b in candidates.items()):
        return None
    k = int(max_lag) + 1
    m0 = np.asarray(d["a0"], float)[:k, :k]
    J = np.stack([np.asarray(d["jacobian"][n], float)[:k, :k] for n in candidates], axis=-1)
    return m0, J


def start_jacobian(start, candidates, max_lag, *, model=None, settings=None):
    """The model's a_ij at ``start`` and their forward-difference derivatives.

    With the default start (:func:`default_start`) and candidates whose
    bounds are those of :data:`CANDIDATES`, the values come from the package
    data (:data:`START_JACOBIAN_FILE`, lags up to
    :data:`START_JACOBIAN_MAX_LAG`; written by :func:`write_start_jacobian`
    with the same model settings, so they equal a fresh computation);
    otherwise they are computed: one model evaluation per candidate plus
    one (about 0.6 s each at lag 9).

    Parameters
    ----------
    start : SensorParameters
        Where to differentiate.
    candidates : dict
        {name: (lo, hi)} of the parameters.
    max_lag : int
        Largest lag L.
    model : callable, optional
        ``model(values) -> a_ij`` for {name: value}; default
        :func:`model_acoeffs` of ``start`` with those values replaced.
    settings : dict, optional
        The numerical settings ``model`` uses (default
        :data:`MODEL_SETTINGS`): the package data apply only to theirs.

    Returns
    -------
    m0 : ndarray, shape (L + 1, L + 1)
        a_ij (1/e) at the start, [i serial, j parallel].
    J : ndarray, shape (L + 1, L + 1, n)
        d a_ij / d parameter, columns in the order of ``candidates``.
    source : str
        ``'package data'`` or ``'computed'``.
    """
    settings = MODEL_SETTINGS if settings is None else _checked_settings(settings)
    shipped = _shipped(start, candidates, max_lag, settings)
    if shipped is not None:
        return shipped + ("package data",)
    if model is None:
        def model(values):
            return model_acoeffs(start.replace(**values), max_lag, settings=settings)
    x0 = {n: float(getattr(start, n)) for n in candidates}
    return _compute_jacobian(model, x0, candidates) + ("computed",)


def write_start_jacobian(path, *, max_lag=START_JACOBIAN_MAX_LAG):
    """Compute the start Jacobian at :func:`default_start` for every candidate
    and write it as the package data file (JSON, atomically).

    Rerun (``python scripts/make_start_jacobian.py``) whenever the bundled
    template's parameters, :data:`CANDIDATES` or the model's a_ij change;
    until then :func:`start_jacobian` ignores the stale file and computes.
    """
    start = default_start()
    x0 = {n: float(getattr(start, n)) for n in CANDIDATES}

    def model(values):
        return model_acoeffs(start.replace(**values), max_lag)

    m0, J = _compute_jacobian(model, x0, CANDIDATES)
    d = {"note": "lsst_bfdrift.calibration.fit_model.write_start_jacobian: model a_ij (1/e, "
                 "[i serial, j parallel]) at default_start() and their forward differences",
         "start": json.loads(start.to_json()), "model": dict(MODEL_SETTINGS),
         "max_lag": int(max_lag),
         "candidates": {n: [float(v) for v in b] for n, b in CANDIDATES.items()},
         "steps": {n: _step(x0[n], *CANDIDATES[n]) for n in CANDIDATES},
         "a0": m0.tolist(), "jacobian": {n: J[..., k].tolist() for k, n in enumerate(CANDIDATES)}}
    write_text(path, json.dumps(d, indent=1) + "\n")
    return d
