"""Figures of the validation: the sky validation (size and ellipticity against
flux, whisker plots) and the reproduction of Rasmussen 2015's figures.

Uses the Agg backend of :mod:`lsst_bfdrift.utils.plotting`; write figures with
:func:`lsst_bfdrift.utils.plotting.save_figure`.
"""

import numpy as np
from matplotlib.collections import PolyCollection

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ["plot_sky_validation", "plot_whiskers", "plot_ratio_scan", "plot_radial",
           "plot_feature_profiles", "plot_pixel_contours", "plot_structure_functions",
           "plot_recovery", "plot_tearing_onset"]

_STYLE = {"before": ("tab:red", "o", "before"), "catalog": ("tab:blue", "s", "catalog route"),
          "pixel": ("tab:green", "^", "pixel route")}


def _panel(ax, fits, key, ylabel, scale):
    for name, rel in fits.items():
        color, marker, label = _STYLE.get(name, ("k", "x", name))
        r = rel[key]
        pts = r["points"]
        g = pts["regressor"] * 1e5
        ax.scatter(g, pts["detrended"] * scale, s=10, color=color,
                   marker=marker, alpha=0.6)
        gg = np.linspace(g.min(), g.max(), 50)
        ax.plot(gg, r["slope"] * gg / 1e5 * scale, color=color,
                label=f"{label}: {r['slope']:+.2e} $\\pm$ {r['slope_err']:.1e} (z={r['z']:+.1f})")
    ax.axhline(0, color="0.5", lw=0.5)
    ax.set_xscale("log")
    ax.set_xlabel("flux (e)")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7, loc="best")


def plot_whiskers(ax, x, y, e1, e2, *, scale=None, color="k", title=None, shape=None):
    """Whiskers of ellipticity (e1, e2) at star positions on ``ax``.

    Length is proportional to sqrt(e1^2 + e2^2) (``scale`` px per unit e; default: the
    largest whisker is 1/10 of the field), orientation the position angle
    0.5 atan2(e2, e1) from the x (serial) axis. A reference whisker of the
    median modulus is drawn in the corner.
    """
    e = np.hypot(e1, e2)
    th = 0.5 * np.arctan2(e2, e1)
    extent = max(np.ptp(x), np.ptp(y), 1.0) if shape is None else max(shape)
    if scale is None:
        scale = 0.1 * extent / max(np.nanmax(e), 1e-6)
    dx = 0.5 * scale * e * np.cos(th)
    dy = 0.5 * scale * e * np.sin(th)
    ax.quiver(x, y, dx, dy, angles="xy", scale_units="xy", scale=0.5, headwidth=0, headlength=0,
              headaxislength=0, pivot="middle", color=color, width=0.004)
    ref = float(np.nanmedian(e)) if np.any(np.isfinite(e)) else 0.0
    if ref > 0:
        x0 = (0 if shape is None else 0) + 0.05 * extent
        y0 = (shape[0] if shape is not None else np.max(y)) * 0.97
        ax.plot([x0, x0 + scale * ref], [y0, y0], color="k", lw=2)
        ax.text(x0, y0 * 0.985, f"|e| = {ref:.3g}", fontsize=7, va="top")
    if shape is not None:
        ax.set_xlim(0, shape[1])
        ax.set_ylim(0, shape[0])
    ax.set_aspect("equal")
    ax.set_xlabel("x (px)")
    ax.set_ylabel("y (px)")
    if title:
        ax.set_title(title, fontsize=9)
    return scale


def plot_sky_validation(result, *, title=None):
    """Size and ellipticity against flux before and after, and whisker plots.

    Parameters
    ----------
    result : SkyValidation
        From :func:`~lsst_bfdrift.validation.sky.validate_sky`.
    title : str, optional
        Figure title (default: the verdict).

    Returns
    -------
    matplotlib.figure.Figure
        Top row: T / T_PSF(x, y) - 1, e1 - e1_PSF(x, y), e2 - e2_PSF(x, y)
        against flux (position polynomial removed) with the fitted lines, for
        the recorded image and each correction route. Bottom row: star
        ellipticity whiskers, and residual (star minus position polynomial)
        ellipticity whiskers before and after correction, on one scale.
    """
    fits = result.fits
    shape = result.summary["image_shape"]
    fig, axes = plt.subplots(2, 3, figsize=(15, 9.5), constrained_layout=True)
    _panel(axes[0, 0], fits, "size", "T / T$_{PSF}$(x, y) - 1", 1.0)
    _panel(axes[0, 1], fits, "e1", "e1 - e1$_{PSF}$(x, y)", 1.0)
    _panel(axes[0, 2], fits, "e2", "e2 - e2$_{PSF}$(x, y)", 1.0)
    for ax in axes[0]:
        ax.yaxis.set_major_formatter(plt.FuncFormatter(lambda v, _: f"{v:.1e}"))
    b1, b2 = fits["before"]["e1"]["points"], fits["before"]["e2"]["points"]
    plot_whiskers(axes[1, 0], b1["x"], b1["y"], b1["detrended"] + _poly(b1),
                  b2["detrended"] + _poly(b2), title="star ellipticity (recorded)", shape=shape)
    after = [k for k in ("catalog", "pixel") if k in fits]
    r1, r2 = b1["detrended"], b2["detrended"]
    scale = plot_whiskers(axes[1, 1], b1["x"], b1["y"], r1, r2, color="tab:red",
                          title="residual ellipticity before correction", shape=shape)
    if after:
        a1, a2 = fits[after[0]]["e1"]["points"], fits[after[0]]["e2"]["points"]
        plot_whiskers(axes[1, 2], a1["x"], a1["y"], a1["detrended"], a2["detrended"],
                      color=_STYLE[after[0]][0], scale=scale,
                      title=f"residual ellipticity after ({_STYLE[after[0]][2]})", shape=shape)
    else:
        axes[1, 2].axis("off")
    fig.suptitle(title if title is not None else _wrap(result.summary.get("verdict", "")),
                 fontsize=9)
    return fig


def _poly(pts):
    """The position polynomial's value at each star (so that q = detrended + poly)."""
    a_coef = pts["coef"]
    k = pts["names"].index("slope")
    x0, y0, sx, sy = pts["frame"]
    u = (pts["x"] - x0) / sx
    v = (pts["y"] - y0) / sy
    order = int(round((np.sqrt(8 * k + 1) - 3) / 2))
    val = np.zeros_like(u)
    c = 0
    for kk in range(order + 1):
        for i in range(kk + 1):
            val += a_coef[c] * u ** i * v ** (kk - i)
            c += 1
    return val


def _wrap(text, width=180):
    words, lines, cur = text.split(" "), [], ""
    for w in words:
        if len(cur) + len(w) + 1 > width:
            lines.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}".strip()
    lines.append(cur)
    return "\n".join(lines)


def plot_ratio_scan(v_bss, xi_ck, ratio, *, fiducial=(-50.0, 5.0, None)):
    """d ln A01 / d ln A10 against V_BSS for several xi_CK (paper Fig. 5, upper left)."""
    fig, ax = plt.subplots(figsize=(6, 4.5), constrained_layout=True)
    for k, ck in enumerate(xi_ck):
        ax.plot(v_bss, ratio[k], "o-", label=f"|xi_CK| = {ck:g} xi0")
    if fiducial[2] is not None:
        ax.plot([fiducial[0]], [fiducial[2]], "ko", ms=9, label="fiducial")
    ax.set_xlabel("V_BSS (V)")
    ax.set_ylabel("d ln A01 / d ln A10")
    ax.set_ylim(0, 8)
    ax.axhline(2.86, color="grey", ls=":", lw=1)
    ax.legend(fontsize=8)
    return fig


def plot_radial(r2, dlna, p_r, e_r, *, r2_range=(4, 25)):
    """Magnitudes of d ln A, ln(1 - p_r) and ln(1 - e_r) against r^2 (paper Fig. 5, bottom)."""
    fig, ax = plt.subplots(figsize=(7, 4.5), constrained_layout=True)
    for y, name in ((dlna, "|d ln A|"), (np.log1p(-p_r), "|ln(1 - p_r)|"),
                    (np.log1p(-e_r), "|ln(1 - e_r)|")):
        ax.loglog(r2, np.abs(y), ".", label=name)
    ax.axvspan(*r2_range, color="grey", alpha=0.15, label="fit range")
    ax.set_xlabel("r$^2$ = di$^2$ + dj$^2$ (px$^2$)")
    ax.legend()
    return fig


def plot_feature_profiles(table, *, xlabel="index"):
    """Area, centroid shift and ellipticity profiles of a fixed-pattern feature."""
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8), constrained_layout=True)
    for setting in sorted(set(table["setting"])):
        s = table[table["setting"] == setting]
        lab = f"{setting:g}"
        ax[0].plot(s["index"], s["area"], ".-", label=lab)
        ax[1].plot(s["index"], s["dx"], ".-", label=f"dx {lab}")
        ax[1].plot(s["index"], s["dy"], "--", label=f"dy {lab}")
        ax[2].plot(s["index"], s["e1"], ".-", label=f"e1 {lab}")
    ax[0].set_ylabel("area (px$^2$)")
    ax[1].set_ylabel("centroid shift (px)")
    ax[2].set_ylabel("e1")
    for a in ax:
        a.set_xlabel(xlabel)
        a.legend(fontsize=7)
    fig.suptitle(table.meta.get("feature", ""))
    return fig


def plot_pixel_contours(table, *, settings=None, title=None, vertical=False):
    """Pixel contours (coloured by A - 1) of a block for several settings.

    Axes are in pixel units with pixel (i, j) nominally centred on (i, j).

    Parameters
    ----------
    table : astropy.table.Table
        Rows of :func:`lsst_bfdrift.physics.patterns.block_geometry` with a
        ``setting`` column (e.g. :func:`~lsst_bfdrift.physics.patterns.tearing_onset`).
    settings : sequence of float, optional
        Settings drawn (default all), one panel each.
    title : str, optional
        Figure title (default: the table's ``feature`` metadata).
    vertical : bool, optional
        Stack the panels (for one-row strips) instead of placing them side by
        side.

    Returns
    -------
    matplotlib.figure.Figure
    """
    vals = sorted(set(table["setting"])) if settings is None else list(settings)
    if vertical:
        fig, axes = plt.subplots(len(vals), 1, figsize=(10, 1.9 * len(vals) + 0.8),
                                 constrained_layout=True, squeeze=False)
        axes = axes.T
    else:
        fig, axes = plt.subplots(1, len(vals), figsize=(3.6 * len(vals) + 1, 4.2),
                                 constrained_layout=True, squeeze=False)
    lim = max(float(np.max(np.abs(table["area"] - 1))), 1e-6)
    pc = None
    for ax, v in zip(axes[0], vals):
        s = table[table["setting"] == v]
        xv, yv = np.asarray(s["xv"]), np.asarray(s["yv"])
        verts = np.stack([xv, yv], axis=-1)
        pc = PolyCollection(verts, array=np.asarray(s["area"]) - 1, cmap="RdBu_r",
                            edgecolors="k", linewidths=0.5)
        pc.set_clim(-lim, lim)
        ax.add_collection(pc)
        # vertices are in pixel units with pixel (i, j) centred on (i, j)
        ax.set_xlim(np.min(s["i"]) - 0.7, np.max(s["i"]) + 0.7)
        ax.set_ylim(np.min(s["j"]) - 0.7, np.max(s["j"]) + 0.7)
        ax.set_aspect("equal")
        ax.set_title(f"setting {v:g}", fontsize=9)
        ax.set_xlabel("column i")
    axes[0][0].set_ylabel("row j")
    if pc is not None:
        fig.colorbar(pc, ax=axes[0].tolist(), shrink=0.8, label="A - 1 (px$^2$)")
    fig.suptitle(title or table.meta.get("feature", ""), fontsize=10)
    return fig


def plot_structure_functions(result):
    """Area maps and structure functions of clock jitter and channel-stop variations.

    Parameters
    ----------
    result : dict
        Output of :func:`lsst_bfdrift.physics.patterns.prnu`.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2), constrained_layout=True)
    for a, name in zip(ax[:2], ("jitter", "channel_stop")):
        m = result["maps"][name]
        im = a.imshow(m - 1, origin="lower", cmap="RdBu_r",
                      vmin=-np.max(np.abs(m - 1)), vmax=np.max(np.abs(m - 1)))
        a.set_title(f"{name.replace('_', ' ')}: A - 1", fontsize=9)
        a.set_xlabel("column (serial)")
        a.set_ylabel("row (parallel)")
        fig.colorbar(im, ax=a, shrink=0.8)
    lags = result["lags"]
    for key, style in (("jitter_parallel", "o-"), ("jitter_serial", "o:"),
                       ("channel_stop_serial", "s-"), ("channel_stop_parallel", "s:")):
        d = np.asarray(result["D"][key])
        ax[2].plot(lags, np.where(d > 0, d, np.nan), style, label=key.replace("_", " "))
    for key in ("jitter_parallel_expected", "channel_stop_serial_expected"):
        if key in result["D"]:
            ax[2].plot(lags, result["D"][key], "k--", lw=0.8)
    ax[2].set_yscale("log")
    ax[2].set_xlabel("lag (px)")
    ax[2].set_ylabel("D(lag) = <(A(x+lag) - A(x))$^2$> (px$^4$)")
    ax[2].set_title("D(lag); dashed: ensemble from one-barrier response\n"
                    "(identically zero curves are not drawn)", fontsize=9)
    ax[2].legend(fontsize=8)
    return fig


def plot_recovery(template, *, r2_range=(4, 25)):
    """Where the aggressor's lost area goes, and the fall-off beyond 10 px.

    Left: fraction of the central loss 1 - A00 recovered by the pixels within
    Chebyshev radius R (R = 1: the 8 nearest neighbours; paper ~35%). Right:
    the magnitude of d ln A against r with the power law fitted over ``r2_range`` extended
    outwards.
    """
    a = template.moments().area
    c = template.center
    loss = 1.0 - a[c, c]
    jj, ii = np.mgrid[-c:c + 1, -c:c + 1]
    cheb = np.maximum(np.abs(ii), np.abs(jj))
    radii = np.arange(1, c + 1)
    frac = [(np.sum(a[(cheb <= r) & (cheb > 0)] - 1.0)) / loss for r in radii]
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.3), constrained_layout=True)
    ax[0].plot(radii, frac, "o-", label="package")
    ax[0].axhline(0.35, color="grey", ls=":", label="paper, R = 1 (~35%)")
    ax[0].set_xlabel("Chebyshev radius R (px)")
    ax[0].set_ylabel("fraction of 1 - A00 recovered within R")
    ax[0].legend()
    r2 = (ii**2 + jj**2).astype(float)
    keep = r2 > 0
    y = np.abs(np.log(a[keep]))
    ax[1].loglog(np.sqrt(r2[keep]), y, ".", label="|d ln A|")
    sel = keep & (r2 >= r2_range[0]) & (r2 <= r2_range[1])
    fit = np.polyfit(np.log(r2[sel]), np.log(np.abs(np.log(a[sel]))), 1)
    rr = np.linspace(np.sqrt(r2_range[0]), np.sqrt(r2.max()), 50)
    ax[1].loglog(rr, np.exp(np.polyval(fit, np.log(rr**2))), "k--",
                 label=f"fit r$^2$ in {r2_range}: slope {fit[0]:.3f} (per ln r$^2$)")
    ax[1].axvspan(10, np.sqrt(r2.max()), color="grey", alpha=0.15, label="r >= 10 px")
    ax[1].set_xlabel("r (px)")
    ax[1].legend(fontsize=8)
    return fig


def plot_tearing_onset(table):
    """Largest absolute A - 1 and dx of the tearing block against the weakening f."""
    fs = sorted(set(table["setting"]))
    da = [float(np.max(np.abs(table[table["setting"] == f]["area"] - 1))) for f in fs]
    dx = [float(np.max(np.abs(table[table["setting"] == f]["dx"]))) for f in fs]
    fig, ax = plt.subplots(figsize=(6, 4.2), constrained_layout=True)
    ax.plot(fs, da, "o-", label="max |A - 1| (px$^2$)")
    ax.plot(fs, dx, "s-", label="max |dx| (px)")
    ax.set_xlabel("weakening f of the channel stop beyond its end")
    ax.legend()
    ax.set_title("tearing onset")
    return fig
