"""Plotting helpers shared by the figure modules of every stage.

Importing this module selects matplotlib's Agg backend, so that nothing
needs a display. The figure functions live beside the stage they show
(``templates.plots``, ``geometry.plots``, ``simulation.plots``,
``validation.plots``) and return a matplotlib Figure; :func:`save_figure`
writes one atomically.
"""

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from lsst_bfdrift.utils.io import atomic_output  # noqa: E402

__all__ = ["plt", "save_figure"]


def save_figure(fig, path, *, dpi=110):
    """Write ``fig`` to ``path`` atomically (temporary file, then rename)."""
    try:
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=os.path.splitext(path)[1][1:] or "png")
    finally:
        plt.close(fig)
    return path
