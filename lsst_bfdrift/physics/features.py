"""Large fixed-pattern features (Rasmussen 2015, section 4.2).

Static pixel distortions, relative to square pixels, computed with the same
electrostatic model (no collected charge):

* edge roll-off: the channel-stop grid ends at the sensor edge (column
  boundary 0, array at x >= 0), with a guard-ring dipole just outside; the
  profile runs over columns for several guard-ring strengths (drain biases);
* midline: the bloom-stop implant along a row boundary; the profile runs over
  rows for several backside biases.

Both features are invariant along the other axis, so a one-pixel strip is
computed. Each returns an astropy Table with one row per pixel and setting:
``setting``, ``index`` (column or row), ``i``, ``j``, ``area`` (px^2),
``dx``, ``dy`` (centroid shift, px), ``e1``, ``e2`` and the pixel vertices
``xv``, ``yv`` (px). Barrier variations (tearing, bamboo, PRNU) are in
:mod:`lsst_bfdrift.physics.patterns`.
"""

import numpy as np
from astropy.table import vstack

from lsst_bfdrift.physics.boundaries import pixel_boundaries
from lsst_bfdrift.physics.patterns import block_geometry
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters

__all__ = ["strip_geometry", "edge_rolloff", "midline"]


def strip_geometry(params, i_range, j_range, *, edge_samples=8, tol=1e-4):
    """Moments of the pixels of a block for a model without collected charge."""
    g = pixel_boundaries(SensorModel(params), i_range, j_range, edge_samples=edge_samples,
                         tol=tol)
    x, y = pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions, i0=g.i0, j0=g.j0)
    jj, ii = np.mgrid[j_range[0]:j_range[1], i_range[0]:i_range[1]]
    m = polygon_moments(x, y, origin=(ii, jj))
    return m, ii, jj


def _profiles(settings, make_params, i_range, j_range, axis, edge_samples, tol, meta):
    """Profiles of a strip for each setting; ``axis`` 1 runs along columns.

    The rows are those of :func:`lsst_bfdrift.physics.patterns.block_geometry` (with
    the pixel vertices ``xv``, ``yv`` for contour plots) plus ``setting`` and
    ``index`` (column or row of the profile).
    """
    rows = []
    for value in settings:
        t = block_geometry(make_params(float(value)), i_range, j_range,
                           edge_samples=edge_samples, tol=tol)
        t.add_column(np.full(len(t), float(value)), name="setting", index=0)
        t.add_column(np.asarray(t["i"] if axis == 1 else t["j"]), name="index", index=1)
        rows.append(t)
    t = vstack(rows)
    t.meta["feature"] = meta
    return t


def edge_rolloff(params=None, *, xi_guard=(-5.0, 0.0, 5.0), n_columns=25, edge_samples=8,
                 tol=1e-4):
    """Pixel geometry across a sensor edge for several guard-ring dipoles.

    Parameters
    ----------
    params : SensorParameters, optional
        Base model (default: the package defaults); ``edge``, ``edge_side``
        and ``xi_guard`` are set here.
    xi_guard : sequence of float, optional
        Guard-ring dipole strengths (xi0, positive pointing into the array:
        the sign a negative drain bias gives).
    n_columns : int, optional
        Columns from the edge.

    Returns
    -------
    astropy.table.Table
    """
    base = SensorParameters() if params is None else params
    return _profiles(xi_guard, lambda g: base.replace(edge=0.0, edge_side=1, xi_guard=g),
                     (0, n_columns), (0, 1), 1, edge_samples, tol,
                     "edge roll-off; setting = guard-ring dipole (xi0)")


def midline(params=None, *, v_bss=(-70.0, -50.0, -30.0), n_rows=10, edge_samples=8,
            tol=1e-4):
    """Pixel geometry across the bloom-stop midline for several backside biases.

    The bloom stop lies on row boundary 0; rows ``-n_rows .. n_rows - 1``.

    Returns
    -------
    astropy.table.Table
    """
    base = SensorParameters() if params is None else params
    return _profiles(v_bss, lambda v: base.replace(bloom_stop=0.0, v_bss=v), (0, 1),
                     (-n_rows, n_rows), 0, edge_samples, tol,
                     "midline (bloom stop); setting = V_BSS (V)")
