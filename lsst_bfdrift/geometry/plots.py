"""Figure of the moment maps of a charge image."""

import numpy as np
from matplotlib.colors import AsinhNorm

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ['plot_moment_maps', 'robust_limit']


def robust_limit(arr, *, percentile=99.5):
    """Symmetric colour limit: the ``percentile`` of abs(arr) over finite pixels (a few
    bright stars do not wash out a full CCD), at least 1e-12."""
    a = np.abs(np.asarray(arr, float))
    a = a[np.isfinite(a)]
    if a.size == 0:
        return 1.0
    return max(float(np.percentile(a, percentile)), 1e-12)


def plot_moment_maps(maps, *, image=None, title=None, percentile=99.5):
    """Area, centroid-shift and ellipticity maps side by side.

    Each panel has pixel axes (x serial, y parallel), a colour bar with its
    unit, and a robust symmetric stretch (``percentile`` of the absolute
    values, :func:`robust_limit`) so that a full CCD with a few bright stars
    stays readable; where it clips, the panel's title gives the full range and
    the colour bar has arrows. The charge image uses an asinh stretch.

    Parameters
    ----------
    maps : MomentMaps
        From :func:`~lsst_bfdrift.geometry.superpose.moment_maps`.
    image : ndarray, optional
        The charge image (e), drawn first.
    title : str, optional
        Figure title.
    percentile : float, optional
        Percentile of abs(map) at the ends of the colour scale.

    Returns
    -------
    matplotlib.figure.Figure
    """
    panels = [("area - 1", "px$^2$", maps.area - 1.0), ("centroid shift x", "px", maps.dx),
              ("centroid shift y", "px", maps.dy), ("e1", "dimensionless", maps.e1),
              ("e2", "dimensionless", maps.e2)]
    if image is not None:
        panels.insert(0, ("charge", "e", np.asarray(image, float)))
    fig, axes = plt.subplots(1, len(panels), figsize=(3.6 * len(panels), 3.6),
                             constrained_layout=True)
    for ax, (name, unit, arr) in zip(np.atleast_1d(axes), panels):
        if name == "charge":
            finite = arr[np.isfinite(arr)]
            med = float(np.median(finite)) if finite.size else 0.0
            top = float(np.percentile(finite, 99.9)) if finite.size else 1.0
            im = ax.imshow(arr, origin="lower", cmap="viridis",
                           norm=AsinhNorm(linear_width=max(abs(med), 1.0), vmin=min(med, top),
                                          vmax=max(top, med + 1.0)), interpolation="nearest")
            extend, clip = "neither", ""
        else:
            lim = robust_limit(arr, percentile=percentile)
            im = ax.imshow(arr, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim,
                           interpolation="nearest")
            finite = arr[np.isfinite(arr)]
            lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 0.0)
            extend = {(False, False): "neither", (True, False): "min", (False, True): "max",
                      (True, True): "both"}[(lo < -lim, hi > lim)]
            # say so when the stretch clips: the colours then do not reach the extremes
            clip = "" if extend == "neither" else \
                f"\nscale clipped at {percentile:g} %: range {lo:.3g} to {hi:.3g}"
        ax.set_title(name + clip, fontsize=10 if clip else None)
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        fig.colorbar(im, ax=ax, shrink=0.75, label=unit, extend=extend)
    if title:
        fig.suptitle(title)
    return fig
