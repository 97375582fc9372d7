"""Reproduce the numbers of Rasmussen 2015 with the calibrated model.

The calibrated parameters come from ``benchmarks/calibration/calibrate_paper.py`` (fit of
xi0, channel depth and clock-pair separation to the paper's A00..A11, with
collection 1 um above the gates; see ``docs/calibration.rst``).
"""

import os

import numpy as np

from lsst_bfdrift.physics.features import edge_rolloff, midline
from lsst_bfdrift.physics.patterns import (bamboo, bamboo_summary, prnu, tearing_onset,
                                           tearing_summary)
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import TemplateSettings, build_template

__all__ = ["PAPER", "paper_parameters", "radial_profile", "radial_fits",
           "neighbour_recovery", "ratio_scan", "reproduce", "fixed_patterns",
           "feature_summary", "write_figures"]

#: The paper's numbers (section 4.1; fiducial template for a 1e4 e aggressor).
PAPER = {"A00": 0.9033, "A01": 1.0077, "A10": 1.0027, "A11": 1.0033, "ratio_01_10": 2.86,
         "slope_area": -1.288, "slope_shift": -1.033, "slope_ellipticity": -1.410,
         "neighbour_recovery": 0.35}

#: Fitted by benchmarks/calibration/calibrate_paper.py (values +- 1 sigma: 8299 +- 130 e,
#: 4.203 +- 0.025 um, 2.62 +- 0.10 um).
_CALIBRATED = {"xi0": 8299.2, "channel_depth": 4.2026, "clock_separation": 2.6164,
               "collection_height": 1.0}


def paper_parameters(**changes):
    """SensorParameters calibrated to the paper's template (plus ``changes``)."""
    return SensorParameters.paper(**{**_CALIBRATED, **changes})


def radial_profile(template):
    """Per pixel of the template: r^2, d ln A, radial shift p_r, radial ellipticity e_r.

    p_r is the centroid shift along the direction away from the aggressor
    (px); e_r = (I_rr - I_tt) / (I_xx + I_yy) = e1 cos 2phi + e2 sin 2phi.
    The aggressor itself is excluded.
    """
    m = template.moments()
    c = template.center
    jj, ii = np.mgrid[-c:c + 1, -c:c + 1]
    r2 = (ii**2 + jj**2).astype(float)
    phi = np.arctan2(jj, ii)
    p_r = (m.x - ii) * np.cos(phi) + (m.y - jj) * np.sin(phi)
    e_r = m.e1 * np.cos(2 * phi) + m.e2 * np.sin(2 * phi)
    keep = r2 > 0
    return r2[keep], np.log(m.area[keep]), p_r[keep], e_r[keep]


def _loglog_slope(r2, y):
    ok = np.abs(y) > 0
    return float(np.polyfit(np.log(r2[ok]), np.log(np.abs(y[ok])), 1)[0])


def radial_fits(template, *, r2_range=(4, 25)):
    """Slopes of ln|d ln A|, ln|ln(1 - p_r)| and ln|ln(1 - e_r)| against ln r^2."""
    r2, dlna, p_r, e_r = radial_profile(template)
    sel = (r2 >= r2_range[0]) & (r2 <= r2_range[1])
    return {"slope_area": _loglog_slope(r2[sel], dlna[sel]),
            "slope_shift": _loglog_slope(r2[sel], np.log1p(-p_r[sel])),
            "slope_ellipticity": _loglog_slope(r2[sel], np.log1p(-e_r[sel]))}


def neighbour_recovery(template):
    """Fraction of the aggressor's area loss taken up by its 8 neighbours."""
    a = template.moments().area
    c = template.center
    block = a[c - 1:c + 2, c - 1:c + 2]
    return float((block.sum() - block[1, 1] - 8.0) / (1.0 - block[1, 1]))


def ratio_scan(v_bss=(-80.0, -65.0, -50.0, -35.0, -20.0), xi_ck=(3.0, 4.0, 5.0, 6.0, 7.0),
               *, settings=None, progress=None):
    """d ln A01 / d ln A10 against V_BSS for several clock dipole strengths."""
    st = settings or TemplateSettings(size=3, edge_samples=32, tol=1e-4, workers=1)
    out = np.empty((len(xi_ck), len(v_bss)))
    for a, ck in enumerate(xi_ck):
        for b, v in enumerate(v_bss):
            out[a, b] = build_template(paper_parameters(xi_ck=ck, v_bss=v), st) \
                .summary()["ratio_01_10"]
            if progress is not None:
                progress(1)
    return np.asarray(v_bss, float), np.asarray(xi_ck, float), out


def reproduce(*, size=31, edge_samples=32, v_bss=(-80.0, -65.0, -50.0, -35.0, -20.0),
              xi_ck=(3.0, 4.0, 5.0, 6.0, 7.0), quick_features=False, progress=None,
              tables=None):
    """All numbers: paper value next to package value, plus the inputs.

    Parameters
    ----------
    size, edge_samples : int, optional
        Template size and samples per edge.
    v_bss, xi_ck : sequence of float, optional
        Grid of the ratio scan (V, xi0).
    quick_features : bool, optional
        Coarse fixed-pattern features (tests).
    progress : callable, optional
        Called with 1 after each scan point and feature.
    tables : dict, optional
        Filled with the :func:`fixed_patterns` results (for figures).

    Returns
    -------
    numbers : dict
        ``{key: {"paper": x, "package": y}}``, ``xi0_si``, ``channel_depth_um``
        and the fixed-pattern ``features``.
    template : DistortionTemplate
        The calibrated template (``size`` x ``size``).
    scan : tuple
        :func:`ratio_scan` output.
    """
    p = paper_parameters()
    # tolerance 1e-4 px, as when `bfdrift reproduce`'s published results were made
    # (TemplateSettings' default became 1e-5 px with issue 43)
    tpl = build_template(p, TemplateSettings(size=size, edge_samples=edge_samples, tol=1e-4))
    s = tpl.summary()
    pkg = {k: s[k] for k in ("A00", "A01", "A10", "A11", "ratio_01_10")}
    pkg.update(radial_fits(tpl))
    pkg["neighbour_recovery"] = neighbour_recovery(tpl)
    numbers = {k: {"paper": PAPER[k], "package": pkg[k]} for k in PAPER}
    r2, dlna, _, _ = radial_profile(tpl)
    sel = (r2 >= 4) & (r2 <= 25)
    fit = np.polyfit(np.log(r2[sel]), np.log(np.abs(dlna[sel])), 1)
    far = r2 >= 100
    if np.any(far):
        pred = np.exp(np.polyval(fit, np.log(r2[far])))
        numbers["falloff_beyond_10px"] = {
            "paper": "faster than r^-2",
            "package": {"mean_abs_dlnA_r_ge_10": float(np.mean(np.abs(dlna[far]))),
                        "power_law_extrapolation": float(np.mean(pred)),
                        "r2_slope": float(fit[0])}}
    numbers["xi0_si"] = p.xi0
    numbers["channel_depth_um"] = p.channel_depth
    numbers["clock_separation_um"] = p.clock_separation
    numbers["collection_height_um"] = p.z_collect
    scan = ratio_scan(v_bss, xi_ck, progress=progress)
    found = fixed_patterns(p, quick=quick_features, progress=progress)
    if tables is not None:
        tables.update(found)
    numbers["features"] = feature_summary(p, tables=found)
    return numbers, tpl, scan


def fixed_patterns(params, *, quick=False, progress=None):
    """Every fixed-pattern feature of section 4.2 for ``params``.

    Returns
    -------
    dict
        ``edge_rolloff``, ``midline`` (:mod:`~lsst_bfdrift.physics.features`
        tables), ``tearing``, ``bamboo`` (:mod:`~lsst_bfdrift.physics.patterns`
        tables) and ``prnu`` (:func:`~lsst_bfdrift.physics.patterns.prnu` result).
    """
    if quick:
        kw = dict(edge_samples=4, tol=3e-4)
        jobs = {
            "edge_rolloff": lambda: edge_rolloff(params, xi_guard=(0.0,), n_columns=3, **kw),
            "midline": lambda: midline(params, v_bss=(-50.0,), n_rows=2, **kw),
            "tearing": lambda: tearing_onset(params, weakening=(0.0, 1.0), i_range=(-1, 1),
                                             j_range=(0, 1), **kw),
            "bamboo": lambda: bamboo(params, amplitudes=(1.0,), period=4, n_periods=1, **kw),
            "prnu": lambda: prnu(params, shape=(3, 3), max_lag=2, kernel_half_width=2,
                                 kernel_tol=3e-4, **kw)}
    else:
        jobs = {"edge_rolloff": lambda: edge_rolloff(params),
                "midline": lambda: midline(params),
                "tearing": lambda: tearing_onset(params),
                "bamboo": lambda: bamboo(params),
                "prnu": lambda: prnu(params)}
    out = {}
    for name, job in jobs.items():
        out[name] = job()
        if progress is not None:
            progress(1)
    return out


def _clean(obj):
    """NaN -> None, numpy scalars -> float, recursively (for JSON)."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (float, np.floating)):
        return None if not np.isfinite(obj) else float(obj)
    return obj


def feature_summary(params, *, edge=None, mid=None, tables=None):
    """Key numbers of the fixed-pattern features.

    Parameters
    ----------
    params : SensorParameters
        Model used when a table is not given.
    edge, mid : astropy.table.Table, optional
        Edge roll-off and midline tables (computed if not given).
    tables : dict, optional
        :func:`fixed_patterns` output; with it, tearing, bamboo and PRNU
        numbers are added.
    """
    tables = {} if tables is None else tables
    edge = tables.get("edge_rolloff", edge)
    mid = tables.get("midline", mid)
    edge = edge_rolloff(params) if edge is None else edge
    mid = midline(params) if mid is None else mid
    out = {"edge_rolloff": {}, "midline": {}}
    for g in sorted(set(edge["setting"])):
        s = edge[edge["setting"] == g]
        area = np.asarray(s["area"])
        reach = int(np.argmax(area > 0.99)) if np.any(area > 0.99) else len(area)
        out["edge_rolloff"][f"xi_guard={g:+g}"] = {
            "area_column0": float(area[0]), "dx_column0": float(s["dx"][0]),
            "columns_to_area_0.99": reach}
    for v in sorted(set(mid["setting"])):
        s = mid[mid["setting"] == v]
        area = np.asarray(s["area"])
        n = len(area) // 2
        out["midline"][f"v_bss={v:g}"] = {"area_rows_beside_stop": float(area[n]),
                                          "area_next_rows": float(area[n + 1]),
                                          "dy_row0": float(s["dy"][n])}
    if "tearing" in tables:
        out["tearing_onset"] = tearing_summary(tables["tearing"])
    if "bamboo" in tables:
        out["bamboo"] = bamboo_summary(tables["bamboo"])
    if "prnu" in tables:
        r = tables["prnu"]
        out["prnu"] = {**r["summary"], "settings": r["settings"],
                       "lags": [int(v) for v in r["lags"]],
                       "D": {k: [float(x) for x in v] for k, v in r["D"].items()}}
    return _clean(out)


def write_figures(numbers, template, scan, tables, out):
    """Write every reproduction figure (PNG) into directory ``out``.

    Returns
    -------
    list of str
        The files written.
    """
    # the plots modules import matplotlib: heavy, only when figures are written
    from lsst_bfdrift.templates.plots import plot_template
    from lsst_bfdrift.utils.plotting import save_figure
    from lsst_bfdrift.validation.plots import (plot_feature_profiles, plot_pixel_contours,
                                               plot_radial, plot_ratio_scan, plot_recovery,
                                               plot_structure_functions, plot_tearing_onset)
    os.makedirs(out, exist_ok=True)
    v_bss, xi_ck, ratio = scan
    fid = numbers["ratio_01_10"]["package"]
    figs = {
        "template.png": plot_template(template),
        "ratio_scan.png": plot_ratio_scan(v_bss, xi_ck, ratio, fiducial=(-50.0, 5.0, fid)),
        "radial.png": plot_radial(*radial_profile(template)),
        "recovery.png": plot_recovery(template),
    }
    labels = {"edge_rolloff": "column from the edge",
              "midline": "row (bloom stop below row 0)"}
    for name, lab in labels.items():
        if name in tables:
            t = tables[name]
            figs[f"{name}.png"] = plot_feature_profiles(t, xlabel=lab)
            # contours of the pixels where the feature is strong
            near = t[t["index"] < 8] if name == "edge_rolloff" else t[np.abs(t["index"] + 0.5) < 4]
            figs[f"{name}_contours.png"] = plot_pixel_contours(
                near, vertical=name == "edge_rolloff")
    if "tearing" in tables:
        t = tables["tearing"]
        figs["tearing_contours.png"] = plot_pixel_contours(t)
        b = int(np.min(t["i"])) + (int(np.max(t["i"])) - int(np.min(t["i"])) + 1) // 2
        prof = t[t["i"] == b]
        prof["index"] = prof["j"]
        prof.meta["feature"] = f"tearing onset: column {b} (right of the weakened stop) " \
                               "against row; setting = weakening f"
        figs["tearing_profile.png"] = plot_feature_profiles(prof, xlabel="row j (stop "
                                                           "weakened above row boundary 0)")
        figs["tearing_onset.png"] = plot_tearing_onset(t)
    if "bamboo" in tables:
        t = tables["bamboo"]
        prof = t.copy()
        prof["index"] = prof["i"]
        figs["bamboo.png"] = plot_feature_profiles(prof, xlabel="column i")
        figs["bamboo_contours.png"] = plot_pixel_contours(t, vertical=True)
    if "prnu" in tables:
        figs["prnu.png"] = plot_structure_functions(tables["prnu"])
    written = []
    for fname, fig in figs.items():
        written.append(save_figure(fig, os.path.join(out, fname)))
    return written
