"""Figure of the moment maps of a charge image."""

import numpy as np

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ['plot_moment_maps']


def plot_moment_maps(maps, *, image=None, title=None):
    """Area, centroid-shift and ellipticity maps side by side.

    Parameters
    ----------
    maps : MomentMaps
        From :func:`~lsst_bfdrift.geometry.superpose.moment_maps`.
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
