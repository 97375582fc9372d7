"""Figure of a template: distorted pixel boundaries and its area map."""

import numpy as np
from matplotlib.collections import PolyCollection

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ['plot_template']


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
