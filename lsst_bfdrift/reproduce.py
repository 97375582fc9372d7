"""Reproduce the numbers of Rasmussen 2015 with the calibrated model.

The calibrated parameters come from ``benchmarks/calibrate.py`` (fit of
xi0, channel depth and clock-pair separation to the paper's A00..A11, with
collection 1 um above the gates; see ``docs/calibration.rst``).
"""

import numpy as np

from .sensor import SensorParameters
from .template import TemplateSettings, build_template

__all__ = ["PAPER", "paper_parameters", "radial_profile", "radial_fits",
           "neighbour_recovery", "ratio_scan", "reproduce", "feature_summary"]

#: The paper's numbers (section 4.1; fiducial template for a 1e4 e aggressor).
PAPER = {"A00": 0.9033, "A01": 1.0077, "A10": 1.0027, "A11": 1.0033, "ratio_01_10": 2.86,
         "slope_area": -1.288, "slope_shift": -1.033, "slope_ellipticity": -1.410,
         "neighbour_recovery": 0.35}

#: Fitted by benchmarks/calibrate.py (values +- 1 sigma: 8299 +- 130 e,
#: 4.203 +- 0.025 um, 2.62 +- 0.10 um).
_CALIBRATED = {"xi0": 8299.2, "channel_depth": 4.2026, "clock_separation": 2.6164,
               "collection_height": 1.0}


def paper_parameters(**changes):
    """SensorParameters calibrated to the paper's template (plus ``changes``)."""
    return SensorParameters(**{**_CALIBRATED, **changes})


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
              xi_ck=(3.0, 4.0, 5.0, 6.0, 7.0), progress=None):
    """All numbers: paper value next to package value, plus the inputs.

    Returns
    -------
    numbers : dict
        ``{key: {"paper": x, "package": y}}`` and ``xi0_si``, ``channel_depth_um``.
    template : DistortionTemplate
        The calibrated template (``size`` x ``size``).
    scan : tuple
        :func:`ratio_scan` output.
    """
    p = paper_parameters()
    tpl = build_template(p, TemplateSettings(size=size, edge_samples=edge_samples))
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
    numbers["features"] = feature_summary(p)
    return numbers, tpl, scan


def feature_summary(params, *, edge=None, mid=None):
    """Key numbers of the edge roll-off and midline profiles (see features)."""
    from .features import edge_rolloff, midline
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
    return out
