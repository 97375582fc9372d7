"""Figures of the catalogs: a spot series' moments against flux, with the fitted and
predicted slopes.

Uses the Agg backend of :mod:`lsst_bfdrift.utils.plotting`; write figures with
:func:`lsst_bfdrift.utils.plotting.save_figure`.
"""

import numpy as np

from lsst_bfdrift.catalogs.spots import SPOT_QUANTITIES
from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ["plot_spot_slopes"]

#: Axis label and scale of each spot quantity's panel.
_LABELS = {"sigma_x": (r"$\sigma_x - a_k$ (mpx)", 1e3), "sigma_y": (r"$\sigma_y - a_k$ (mpx)", 1e3),
           "size": (r"$\ln T - a_k$ ($10^{-3}$)", 1e3), "e1": (r"$e_1 - a_k$ ($10^{-3}$)", 1e3),
           "e2": (r"$e_2 - a_k$ ($10^{-3}$)", 1e3)}


def plot_spot_slopes(result, *, predicted=None, title=None):
    """Each spot quantity against flux, its intercept per spot removed, with the slopes.

    Parameters
    ----------
    result : dict
        From :func:`~lsst_bfdrift.catalogs.spot_slopes.spot_slopes`.
    predicted : dict, optional
        From :func:`~lsst_bfdrift.catalogs.spot_slopes.predict_spot_slopes`:
        its slopes are drawn dashed.
    title : str, optional
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        One panel per quantity (points coloured by image, the fitted line
        with its slope and error) and a panel of the per-spot size slopes
        against the common one.
    """
    names = [k for k in SPOT_QUANTITIES if k in result]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7.5))
    axes = axes.ravel()
    for ax, name in zip(axes, names):
        r = result[name]
        pts = r["points"]
        label, scale = _LABELS[name]
        g = pts["regressor"] * 1e5
        ax.scatter(g, pts["detrended"] * scale, c=pts["image"], s=8, cmap="viridis", alpha=0.7)
        gg = np.geomspace(max(g.min(), 1.0), g.max(), 50)
        ax.plot(gg, r["slope"] * gg / 1e5 * scale, color="tab:red",
                label=f"fit {r['slope']:+.3e} $\\pm$ {r['slope_err']:.1e} per 1e5 e")
        if predicted is not None and name in predicted:
            p = predicted[name]["slope"]
            ax.plot(gg, p * gg / 1e5 * scale, color="k", ls="--",
                    label=f"predicted {p:+.3e}")
        ax.axhline(0, color="0.6", lw=0.5)
        ax.set_xscale("log")
        ax.set_xlabel("spot flux (e)")
        ax.set_ylabel(label)
        ax.legend(fontsize=7, loc="upper left")
    ax = axes[len(names)]
    key = "size" if "size" in result else names[0]
    ps = result[key]["per_spot"]
    ok = np.isfinite(ps["slope"])
    ax.errorbar(ps["spot"][ok], ps["slope"][ok], yerr=ps["slope_err"][ok], fmt="o", ms=3)
    ax.axhline(result[key]["slope"], color="tab:red", label="common slope")
    ax.set_xlabel("spot")
    ax.set_ylabel(f"{key} slope per 1e5 e, per spot")
    ax.legend(fontsize=7)
    for extra in axes[len(names) + 1:]:
        extra.set_visible(False)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig
