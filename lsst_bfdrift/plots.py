"""Figures: distorted pixel boundaries and moment maps.

All functions return a matplotlib Figure; :func:`save_figure` writes it
atomically. The Agg backend is used so that nothing needs a display.
"""

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

from .io_utils import atomic_output  # noqa: E402

__all__ = ["plot_template", "plot_moment_maps", "plot_flat_simulation", "plot_star_history",
           "plot_ratio_scan", "plot_radial", "plot_feature_profiles", "plot_pixel_contours",
           "plot_structure_functions", "plot_recovery", "plot_tearing_onset", "save_figure"]


def _auto_exaggeration(template):
    c = template.center
    peak = np.max(np.abs(template.corner_d[c - 1:c + 3, c - 1:c + 3]))
    return 1.0 if peak == 0 else float(np.clip(0.15 / peak, 1.0, 1e6))


def plot_template(template, *, exaggerate=None, half_width=None):
    """Distorted pixel boundaries (exaggerated) and the area map of a template.

    Parameters
    ----------
    template : DistortionTemplate
        The template to draw.
    exaggerate : float, optional
        Factor applied to the displacements in the boundary panel; default
        makes the largest corner shift ~0.15 px.
    half_width : int, optional
        Pixels drawn on each side of the aggressor in the boundary panel
        (default 6).

    Returns
    -------
    matplotlib.figure.Figure
    """
    ex = _auto_exaggeration(template) if exaggerate is None else float(exaggerate)
    c = template.center
    hw = min(c, 6) if half_width is None else min(int(half_width), c)
    x, y = template.polygons(charge=template.charge * ex)
    sl = slice(c - hw, c + hw + 1)
    area = template.moments().area
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True)
    verts = np.stack([x[sl, sl], y[sl, sl]], axis=-1).reshape(-1, x.shape[-1], 2)
    dA = (area[sl, sl] - 1.0).ravel()
    lim = np.max(np.abs(dA)) or 1.0
    pc = PolyCollection(verts, array=dA, cmap="RdBu_r", edgecolors="k", linewidths=0.4)
    pc.set_clim(-lim, lim)
    ax0.add_collection(pc)
    ax0.set_xlim(-hw - 0.7, hw + 0.7)
    ax0.set_ylim(-hw - 0.7, hw + 0.7)
    ax0.set_aspect("equal")
    ax0.set_xlabel("serial offset di (px)")
    ax0.set_ylabel("parallel offset dj (px)")
    ax0.set_title(f"boundaries, displacements x{ex:.3g} (Q = {template.charge:.3g} e)")
    im = ax1.imshow(np.sign(area - 1) * np.log10(1 + np.abs(area - 1) / 1e-6), origin="lower",
                    extent=(-c - 0.5, c + 0.5, -c - 0.5, c + 0.5), cmap="RdBu_r")
    ax1.set_title("area map: sign(A-1) log10(1 + |A-1| / 1e-6)")
    ax1.set_xlabel("serial offset di (px)")
    ax1.set_ylabel("parallel offset dj (px)")
    fig.colorbar(im, ax=ax1, shrink=0.8)
    fig.colorbar(pc, ax=ax0, shrink=0.8, label="A - 1 (px$^2$)")
    return fig


def plot_moment_maps(maps, *, image=None, title=None):
    """Area, centroid-shift and ellipticity maps side by side.

    Parameters
    ----------
    maps : MomentMaps
        From :func:`~lsst_bfdrift.superpose.moment_maps`.
    image : ndarray, optional
        The charge image, drawn first.
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    panels = [("area - 1", maps.area - 1.0), ("dx (px)", maps.dx), ("dy (px)", maps.dy),
              ("e1", maps.e1), ("e2", maps.e2)]
    if image is not None:
        panels.insert(0, ("charge (e)", np.asarray(image)))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.3 * len(panels), 3.4),
                             constrained_layout=True)
    for ax, (name, arr) in zip(np.atleast_1d(axes), panels):
        if name.startswith("charge"):
            im = ax.imshow(arr, origin="lower", cmap="viridis")
        else:
            lim = np.nanmax(np.abs(arr)) or 1.0
            im = ax.imshow(arr, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim)
        ax.set_title(name)
        fig.colorbar(im, ax=ax, shrink=0.75)
    if title:
        fig.suptitle(title)
    return fig


def plot_flat_simulation(table, template=None):
    """Covariances against mean of a flat simulation (like the paper's Fig. 6).

    Left: C00 (e^2) with the Poisson line; right: C01, C10, C11 (e^2) with
    the first-order guides a_ij mu^2 from the template, both estimators.
    """
    mu = np.asarray(table["mu"])
    paper = np.asarray(table["paper"]) * mu[:, None, None]
    pairs = np.asarray(table["pairs"])
    err = np.asarray(table["pairs_err"])
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    ax0.plot(mu, paper[:, 0, 0], "o", ms=3, label="all pairs (paper)")
    ax0.errorbar(mu, pairs[:, 0, 0], err[:, 0, 0], fmt=".", ms=2, label="per pair (LSST)")
    ax0.plot(mu, mu, "k--", lw=1, label="Poisson")
    ax0.set_xlabel("mean (e)")
    ax0.set_ylabel("C00 (e$^2$)")
    ax0.legend()
    a = None
    if template is not None:
        c = template.center
        a = np.log(template.moments().area) / template.charge
    for (di, dj), col in (((0, 1), "C0"), ((1, 0), "C1"), ((1, 1), "C2")):
        ax1.plot(mu, paper[:, di, dj], "o", ms=3, color=col, label=f"C{di}{dj} all pairs")
        ax1.errorbar(mu, pairs[:, di, dj], err[:, di, dj], fmt=".", ms=2, color=col, alpha=0.5)
        if a is not None:
            ax1.plot(mu, a[c + dj, c + di] * mu**2, "--", color=col, lw=1,
                     label=f"a{di}{dj} mu$^2$ (template)")
    ax1.set_xlabel("mean (e)")
    ax1.set_ylabel("C$_{ij}$ (e$^2$)")
    ax1.legend(fontsize=8)
    return fig


def plot_star_history(history):
    """A star simulation against counts (like the paper's Fig. 7).

    Panels: central pixel counts, T = sigma_x^2 + sigma_y^2 with and without
    BF, FWHM growth by BF (RSS difference), ellipticity and orientation.
    """
    h = history
    n = np.asarray(h["counts"])
    fig, ax = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    ax[0, 0].plot(n, h["central"], ".-")
    ax[0, 0].set_ylabel("central pixel counts (e)")
    ax[0, 1].plot(n, h["T"], ".-", label="with BF")
    ax[0, 1].plot(n, h["T_nominal"], "--", label="square pixels")
    ax[0, 1].set_ylabel("$\\sigma_x^2 + \\sigma_y^2$ (px$^2$)")
    ax[0, 1].legend()
    rss = np.sqrt(np.clip(np.asarray(h["T"]) - np.asarray(h["T_nominal"]), 0, None) / 2)
    ax[0, 2].plot(h["central"], 2.3548 * rss, ".-")
    ax[0, 2].set_xlabel("central pixel counts (e)")
    ax[0, 2].set_ylabel("FWHM growth, RSS (px)")
    e = np.hypot(h["e1"], h["e2"])
    e0 = np.hypot(h["e1_nominal"], h["e2_nominal"])
    ax[1, 0].plot(h["central"], e, ".-", label="with BF")
    ax[1, 0].plot(h["central"], e0, "--", label="square pixels")
    ax[1, 0].set_ylabel("ellipticity |e|")
    ax[1, 0].legend()
    ax[1, 1].plot(h["central"], h["theta"], ".-", label="with BF")
    ax[1, 1].plot(h["central"], h["theta_nominal"], "--", label="square pixels")
    ax[1, 1].set_ylabel("orientation (deg from serial axis)")
    for col in h.colnames:
        if col.startswith("rate_"):
            ax[1, 2].plot(n, h[col], ".-", ms=2, label=col[5:].replace("_", ","))
    ax[1, 2].set_ylabel("arrivals per conversion")
    ax[1, 2].legend(fontsize=7, ncol=3)
    for a in ax.ravel():
        a.ticklabel_format(axis="x", style="sci", scilimits=(0, 0))
        if not a.get_xlabel():
            a.set_xlabel("counts (e)" if a in (ax[0, 0], ax[0, 1], ax[1, 2]) else
                         "central pixel counts (e)")
    return fig


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
        Rows of :func:`lsst_bfdrift.patterns.block_geometry` with a
        ``setting`` column (e.g. :func:`~lsst_bfdrift.patterns.tearing_onset`).
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
        Output of :func:`lsst_bfdrift.patterns.prnu`.

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


def save_figure(fig, path, *, dpi=110):
    """Write ``fig`` to ``path`` atomically (temporary file, then rename)."""
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=os.path.splitext(path)[1][1:] or "png")
    finally:
        plt.close(fig)
    return path
