"""One calibration, every band: a calibrated template carried to the other bands.

Flats taken in one band B calibrate the model (:func:`~lsst_bfdrift.calibration.tuning.calibrate`).
The model then says how the template changes with the depth at which each
band's photons convert (:func:`~lsst_bfdrift.templates.bands.build_band_templates`,
drift lines starting at the conversion depths of GalSim's silicon absorption
table over the band's LSST throughput). :func:`calibrated_band_templates`
gives band X the calibrated template plus the model's change from B to X,

``T_X = T_cal + (M_X - M_B)``,

with ``M`` the model's band templates at the calibrated parameters (the same
build settings as ``T_cal``). Band B keeps the calibrated template exactly;
the edge displacements are linear, so the areas change by the model's
difference to first order.

The calibration's uncertainty is carried as a relative one: a template off
by some fraction in band B is off by the same fraction in every band (the
field of the charge is the same; only the drift length changes). Each
band's stored uncertainty (``meta['calibration']['uncertainty']``, that
:func:`~lsst_bfdrift.templates.refine.draw_templates` and the Task's
``uncertainty_draws`` read) is the calibration's, scaled per lag by the
model's ratio ``r_ij = alpha_ij(M_X) / alpha_ij(M_B)`` of the linear area
responses; ``meta['calibration']['band']`` records a00 (1/e), its error
from that uncertainty and, where the fit's Jacobian is known, from the
parameter covariance alone.
"""

import copy

import numpy as np

from lsst_bfdrift.physics.depth import BANDS, normalize_band
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.bands import (MultiBandTemplate, band_key, build_band_templates,
                                          combine_templates)
from lsst_bfdrift.templates.refine import template_alpha
from lsst_bfdrift.templates.template import DistortionTemplate, TemplateSettings
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["calibrated_band_templates", "band_a00_table"]


def _lag_ratio(model_x, model_b, max_lag):
    """r[i, j] = alpha(M_X) / alpha(M_B) at lags i (serial), j (parallel) <= max_lag."""
    ax, ab = template_alpha(model_x), template_alpha(model_b)
    c = model_b.center
    k = min(int(max_lag), c) + 1
    num, den = ax[c:c + k, c:c + k].T, ab[c:c + k, c:c + k].T  # [j, i] -> [i, j]
    tiny = 1e-9 * abs(den[0, 0])
    return np.where(np.abs(den) > tiny, num / np.where(np.abs(den) > tiny, den, 1.0), 1.0)


def _scaled_uncertainty(unc, ratio):
    """The calibration uncertainty ``unc`` with every lag scaled by ``ratio`` [i, j]
    (parameter modes, edge shifts near the aggressor, by the a00 ratio)."""
    if not unc:
        return unc
    out = copy.deepcopy(unc)
    modes = out.get("parameter_modes")
    if modes:
        r00 = abs(float(np.asarray(ratio, float)[0, 0]))
        for key in ("corner_d", "vedge_d", "hedge_d"):
            modes[key] = (np.asarray(modes[key], float) * r00).tolist()
    if unc.get("kind") == "data":
        s = np.asarray(unc["sigma"], float)
        r = _fit(ratio, s.shape)
        out["sigma"] = np.where(np.isfinite(s), s * np.abs(r), np.nan).tolist()
    elif unc.get("kind") == "parameters":
        j = np.asarray(unc["jacobian"], float)
        out["jacobian"] = (j * _fit(ratio, j.shape[:2])[..., None]).tolist()
    else:
        raise InputError(f"unknown calibration uncertainty kind {unc.get('kind')!r}; "
                         "accepted: 'data' or 'parameters' (lsst_bfdrift.calibration.calibrate)")
    return out


def _fit(ratio, shape):
    """``ratio`` cut or padded (with 1) to ``shape``."""
    out = np.ones(shape)
    n0, n1 = min(shape[0], ratio.shape[0]), min(shape[1], ratio.shape[1])
    out[:n0, :n1] = ratio[:n0, :n1]
    return out


def _a00_errors(unc, jacobian, covariance):
    """(error of a00 from the stored uncertainty, error from the parameter covariance)."""
    stored = None
    if unc and unc.get("kind") == "data":
        s = float(np.asarray(unc["sigma"], float)[0, 0])
        stored = s if np.isfinite(s) else None
    elif unc and unc.get("kind") == "parameters":
        j = np.asarray(unc["jacobian"], float)[0, 0]
        stored = float(np.sqrt(j @ np.asarray(unc["covariance"], float) @ j))
    params = None
    if jacobian is not None and covariance is not None:
        j = np.asarray(jacobian, float)[0, 0]
        params = float(np.sqrt(j @ np.asarray(covariance, float) @ j))
    return stored, params


def calibrated_band_templates(template, band, *, bands=BANDS, sed=None, nodes=8, fit=None,
                              temperature=None, progress=False):
    """Templates for every band from a template calibrated on flats of one band.

    Parameters
    ----------
    template : DistortionTemplate
        The calibrated template (:func:`~lsst_bfdrift.calibration.tuning.calibrate`:
        its ``meta`` holds ``params``, ``settings`` and ``calibration``).
    band : str
        Band of the flats it was calibrated on ('u' .. 'y' or a physical
        filter such as 'r_57').
    bands : sequence of str or float, optional
        Bands (and/or wavelengths in nm) to write; default all six.
    sed : optional
        Spectrum of the light (:func:`~lsst_bfdrift.physics.depth.sed_photons`);
        None: flat in photons per nm (a flat field's lamp). The same for
        the flats' band and the others.
    nodes : int or array_like, optional
        Conversion heights of the model's band templates
        (:func:`~lsst_bfdrift.templates.bands.build_band_templates`; 8: 7
        builds at the template's settings).
    fit : ParameterFit, optional
        The calibration's fit (``CalibrationResult.fit``): its Jacobian gives
        each band's a00 error from the parameter covariance alone (recorded
        as ``a00_err_params``). Default: from the template's uncertainty
        when it is of kind 'parameters'.
    temperature : float, optional
        Temperature of the sensor (K) for the absorption lengths of every
        band, the flats' included (None: 300 K, the table's;
        :func:`~lsst_bfdrift.templates.bands.build_band_templates`).
    progress : bool or callable, optional
        Progress of the model builds (see ``build_band_templates``).

    Returns
    -------
    MultiBandTemplate
        One template per band (band keys), each with
        ``meta['calibration']['band']``: ``flats`` (B), ``a00`` (1/e),
        ``a00_err`` (from the scaled calibration uncertainty, None if a00 was
        not measured), ``a00_err_params`` (from the parameter covariance, or
        None), ``ratio`` (the model's r_ij) and ``transfer``.

    Raises
    ------
    InputError
        An unknown band, a template without calibration metadata, or model
        templates that do not match the calibrated one's layout.
    """
    if not isinstance(template, DistortionTemplate):
        raise InputTypeError(f"template must be a DistortionTemplate, got "
                             f"{type(template).__name__}")
    b = normalize_band(band)
    meta = template.meta
    missing = [k for k in ("params", "settings", "calibration") if not meta.get(k)]
    if missing:
        raise InputError(f"the template lacks {', '.join(missing)} in its metadata: a template "
                         "calibrated by lsst_bfdrift (bfdrift calibrate) is needed")
    keys = list(dict.fromkeys(band_key(x) for x in bands))
    if not keys:
        raise InputError("bands must name at least one band")
    params = SensorParameters.from_dict(meta["params"])
    settings = TemplateSettings.from_dict(dict(meta["settings"], conversion_height=None,
                                               aggressor_charge=template.charge))
    need = keys + ([b] if b not in keys else [])
    sources = [float(k[:-2]) if k.endswith("nm") else k for k in need]
    model = build_band_templates(params, sources, sed=sed, settings=settings, nodes=nodes,
                                 temperature=temperature, progress=progress)
    mb = model[b]
    if mb.size != template.size or mb.edge_samples != template.edge_samples or \
            not np.allclose(mb.fractions, template.fractions):
        raise InputError(f"the model's band templates ({mb.size} x {mb.size}, "
                         f"{mb.edge_samples} samples) do not match the calibrated template "
                         f"({template.size} x {template.size}, {template.edge_samples} samples)")
    cal = meta["calibration"]
    unc = cal.get("uncertainty")
    max_lag = int(cal.get("max_lag", 5))
    if fit is not None:
        jac, cov = np.asarray(fit.jacobian, float), np.asarray(fit.covariance, float)
    elif unc and unc.get("kind") == "parameters":
        jac, cov = np.asarray(unc["jacobian"], float), np.asarray(unc["covariance"], float)
    else:
        jac = cov = None
    out = {}
    for key in keys:
        ratio = _lag_ratio(model[key], mb, max_lag)
        m = copy.deepcopy(dict(meta))
        m["depth"] = model[key].meta["depth"]
        c = m["calibration"]
        c["uncertainty"] = _scaled_uncertainty(unc, ratio)
        stored, from_params = _a00_errors(
            c["uncertainty"], None if jac is None else jac * _fit(ratio, jac.shape[:2])[..., None],
            cov)
        tpl = template if key == b else combine_templates([template, model[key], mb],
                                                          [1.0, 1.0, -1.0], meta=m)
        if key == b:
            tpl = DistortionTemplate(template.corner_d, template.vedge_d, template.hedge_d,
                                     template.fractions, template.charge,
                                     vedge_t=template.vedge_t, hedge_t=template.hedge_t, meta=m)
        a00 = float(template_alpha(tpl)[tpl.center, tpl.center])
        c["band"] = {"flats": b, "band": key, "a00": a00, "a00_err": stored,
                     "a00_err_params": from_params, "ratio": ratio.tolist(),
                     "transfer": "T_cal + (M_band - M_flats): model band templates at the "
                                 "calibrated parameters; uncertainty scaled by the model's "
                                 "ratio of area responses per lag"}
        out[key] = tpl
    return MultiBandTemplate(out, meta={"calibration_band": b, "depth_response": "drift",
                                        "sed": "flat" if sed is None else str(sed)})


def band_a00_table(templates):
    """Per band: a00 (1/e) and its errors, as recorded by :func:`calibrated_band_templates`.

    Parameters
    ----------
    templates : MultiBandTemplate

    Returns
    -------
    dict
        band -> {'a00', 'a00_err', 'a00_err_params', 'ratio_a00', 'mean_height'}.
    """
    rows = {}
    for key in templates.bands:
        t = templates[key]
        info = (t.meta.get("calibration") or {}).get("band") or {}
        rows[key] = {"a00": info.get("a00"), "a00_err": info.get("a00_err"),
                     "a00_err_params": info.get("a00_err_params"),
                     "ratio_a00": (info.get("ratio") or [[None]])[0][0],
                     "mean_height": (t.meta.get("depth") or {}).get("mean_height")}
    return rows
