"""Figures of the sky validation: size and ellipticity against flux, whisker plots.

Uses the Agg backend of :mod:`lsst_bfdrift.plots`; write figures with
:func:`lsst_bfdrift.plots.save_figure`.
"""

import numpy as np

from .plots import plt  # Agg backend set there

__all__ = ["plot_sky_validation", "plot_whiskers"]

_STYLE = {"before": ("tab:red", "o", "before"), "catalog": ("tab:blue", "s", "catalogue route"),
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
        From :func:`~lsst_bfdrift.sky.validate_sky`.
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
