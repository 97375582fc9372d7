"""What an effect added by the diagnosis means for the BF calibration and for stars.

When :func:`~lsst_bfdrift.diagnosis.effects_fit.diagnose` adds an effect, the
base model's electrostatic parameters are fitted again beside it, and the
brighter-fatter a_ij they give move. :func:`template_change` takes the base
a_ij of the base model alone (the calibration a user would have made without
the diagnosis) and those of the final model, calibrates a template from each
(:func:`~lsst_bfdrift.calibration.tuning.calibrate`), and asks
:func:`star_consequence` what correcting stars with the first would leave if
the second is right.

:func:`star_consequence` draws noise-free stars (a pixel-integrated Gaussian)
through one template with the package's forward model
(:func:`~lsst_bfdrift.correction.solvers.recorded_image`), corrects them with
another (:func:`~lsst_bfdrift.correction.solvers.correct_image`) and gives the
size-flux and e1-flux slopes left as fractions of the uncorrected slopes. It
is the package's own model on both sides: an estimate of the consequence, not
a measurement on independent stars (``benchmarks/calibration/calibrate_sensor.py`` is
that).
"""

import numpy as np
from scipy.special import erf

from lsst_bfdrift.calibration import tuning
from lsst_bfdrift.diagnosis.effects_fit import base_acoeffs, scaled_basis
from lsst_bfdrift.ptc.acoeffs import AcoeffTable
from lsst_bfdrift.ptc.covariances import least_squares_line
from lsst_bfdrift.correction.settings import REFERENCE
from lsst_bfdrift.correction.solvers import correct_image, recorded_image
from lsst_bfdrift.simulation.stars import image_moments
from lsst_bfdrift.templates.swept import SweptAreas
from lsst_bfdrift.utils.errors import InputError

__all__ = ["star_consequence", "template_change", "CONSEQUENCE_FLUXES"]

#: Star fluxes (e) of :func:`star_consequence`: 1e4 to 1.5e6 e, as the
#: calibrate benchmark's stars.
CONSEQUENCE_FLUXES = tuple(np.geomspace(1e4, 1.5e6, 8))


def _gaussian_stamp(size, sigma, offset):
    """Pixel-integrated unit Gaussian of ``sigma`` px centred ``offset`` (x, y)
    px from the stamp's central pixel."""
    c = size // 2
    edges = np.arange(size + 1) - c - 0.5
    s2 = np.sqrt(2.0) * sigma
    gx = np.diff(0.5 * erf((edges - offset[0]) / s2))
    gy = np.diff(0.5 * erf((edges - offset[1]) / s2))
    return np.outer(gy, gx)


def _moments(img):
    m = image_moments(img)  # unweighted: noise-free stamps
    return m["T"], m["e1"]


def _slope(f, v):
    return float(least_squares_line(f, v)[0])


def star_consequence(true_template, used_template, *, fwhm=3.5, fluxes=CONSEQUENCE_FLUXES,
                     stamp=41, offset=(0.3, 0.2), order=3, density="fv4"):
    """Slopes left when stars recorded through ``true_template`` are corrected
    with ``used_template``.

    Parameters
    ----------
    true_template, used_template : DistortionTemplate
        The sensor's template and the one the correction uses.
    fwhm : float, optional
        Star FWHM (px; 3.5 px is 0.7" at 0.2"/px).
    fluxes : sequence of float, optional
        Star fluxes (e).
    stamp : int, optional
        Stamp size (px).
    offset : tuple of float, optional
        Star centre from the central pixel's centre (x, y), px.
    order : int, optional
        Terms of the forward series and of the correction.
    density : {'mean2', 'cubic4', 'fv4'}, optional
        Edge flux density.

    Returns
    -------
    dict
        ``size_left`` and ``e1_left``: the size (ixx + iyy) and e1 slopes
        against flux after the correction, as fractions of the uncorrected
        ones (0: fully corrected; > 0 under-, < 0 over-corrected);
        ``size_slope`` and ``e1_slope`` (per e; uncorrected and corrected).
    """
    fluxes = np.asarray(fluxes, float)
    if fluxes.size < 2 or np.any(~np.isfinite(fluxes)) or np.any(fluxes <= 0):
        raise InputError(f"fluxes must be at least two positive values, got {fluxes.tolist()}")
    if not fwhm > 0:
        raise InputError(f"fwhm must be positive (px), got {fwhm}")
    unit = _gaussian_stamp(int(stamp), fwhm / 2.3548200450309493, offset)
    swept = SweptAreas(true_template, unit.shape)
    rows = []
    for f in fluxes:
        truth = f * unit
        rec = recorded_image(truth, swept, order=order, density=density)
        cor = correct_image(rec, used_template, **REFERENCE.solver_kwargs(
            order=order, density=density, rtol=1e-10, max_iter=30), check_range=False)[0]
        rows.append([*_moments(truth), *_moments(rec), *_moments(cor)])
    r = np.array(rows)
    out = {}
    for k, name in enumerate(("size", "e1")):
        raw = _slope(fluxes, r[:, 2 + k] - r[:, k])
        left = _slope(fluxes, r[:, 4 + k] - r[:, k])
        out[f"{name}_slope"] = {"uncorrected": raw, "corrected": left}
        out[f"{name}_left"] = left / raw if raw != 0 else float("nan")
    out.update(fwhm_px=float(fwhm), fluxes=fluxes.tolist())
    return out


def template_change(diagnosis, basis, *, max_lag=None, threshold=1.0, calibrate_kw=None,
                    star_kw=None):
    """What the added effects change in the BF calibration and in star corrections.

    Parameters
    ----------
    diagnosis : dict
        ``Diagnosis.as_dict()`` of a table or flats diagnosis.
    basis : LinearBasis
        The basis given to the diagnosis (its ``base_scales`` are added).
    max_lag : int, optional
        Lags compared and calibrated (default: those of the basis, at most 3).
    threshold : float, optional
        The templates are calibrated (about a minute) only when some a_ij
        moved by more than ``threshold`` of its error.
    calibrate_kw : dict, optional
        Options of :func:`~lsst_bfdrift.calibration.tuning.calibrate`
        (default ``allow_poor_fit=True``).
    star_kw : dict, optional
        Options of :func:`star_consequence`.

    Returns
    -------
    dict
        ``available`` (False with a ``reason`` when nothing can be said);
        ``shift`` (per lag 'i,j': a before, a after, error, shift in
        sigma), ``largest_shift`` (sigma), ``changed`` (above
        ``threshold``); when changed: ``templates`` (per side the calibrated
        a00, a01, a10 and chi2/dof) and ``stars``: the slopes left when
        correcting with the template calibrated without the effects, if the
        final model is right (:func:`star_consequence`).
    """
    steps = diagnosis.get("steps") or []
    if diagnosis.get("kind") not in ("table", "flats") or basis is None:
        return {"available": False,
                "reason": "needs an electrostatic basis (a-matrix table or flat pairs input)"}
    if len(steps) < 2:
        return {"available": False, "reason": "no effect was added"}
    basis = scaled_basis(basis, diagnosis.get("base_scales"))
    L = min(basis.max_lag, 3) if max_lag is None else int(max_lag)
    a0, s0 = base_acoeffs(steps[0], basis, L)
    a1, s1 = base_acoeffs(steps[-1], basis, L)
    sig = np.maximum(s1, 1e-300)
    pull = (a1 - a0) / sig
    shift = {f"{i},{j}": {"before": float(a0[i, j]), "after": float(a1[i, j]),
                          "error": float(s1[i, j]), "sigma": float(pull[i, j])}
             for i in range(L + 1) for j in range(L + 1)}
    worst = np.unravel_index(np.argmax(np.abs(pull)), pull.shape)
    out = {"available": True, "shift": shift, "largest_shift": float(pull[worst]),
           "largest_shift_lag": [int(worst[0]), int(worst[1])],
           "changed": bool(np.abs(pull).max() > threshold), "threshold": float(threshold)}
    if not out["changed"]:
        return out
    # the templates' uncertainty is not used here: no parameter modes
    kw = {"allow_poor_fit": True, "modes": False, **(calibrate_kw or {})}
    results = {}
    for side, a, s in (("without effects", a0, s0), ("with effects", a1, s1)):
        # tuning.calibrate looked up at the call (tests replace it: about a minute a side)
        res = tuning.calibrate(AcoeffTable(a, np.maximum(s, 1e-3 * np.abs(a) + 1e-12),
                                           source=f"diagnosis base model, {side}"), **kw)
        results[side] = res
        t = res.template_acoeffs
        out.setdefault("templates", {})[side] = {
            "a00": None if t is None else float(t[0, 0]),
            "a01": None if t is None else float(t[0, 1]),
            "a10": None if t is None else float(t[1, 0]),
            "chi2_dof": float(res.fit.chi2_dof)}
    before, after = results["without effects"].template, results["with effects"].template
    if before is not None and after is not None:
        out["stars"] = star_consequence(after, before, **(star_kw or {}))
    return out
