"""Barrier-variation fixed patterns: tearing onset, bamboo and PRNU (Rasmussen 2015, 4.2).

Static pixel distortions (no collected charge) caused by departures of the
barrier dipoles from the regular grid, computed with the electrostatic model
and the boundary machinery shared with :mod:`lsst_bfdrift.physics.features`:

* :func:`tearing_onset` -- an *isolated* variation: the channel stop on one
  column boundary is weakened by a fraction ``f`` beyond a row boundary (a
  truncated extra channel-stop dipole of strength ``-f xi_CS``), so the two
  columns beside it see a full stop on one side of the truncation and a
  weakened (``f = 1``: absent) stop on the other. The pixel pattern around the
  end of the stop is computed for several ``f``; its amplitude against ``f``
  shows the onset of tearing.
* :func:`bamboo` -- a *collective* variation: channel-stop strengths modulated
  periodically from column to column, ``delta xi_b = a cos(2 pi b / P)`` on
  column boundary ``b``; the areas show the same period (stripes along the
  columns).
* :func:`jitter_area_map` and :func:`channel_stop_area_map` -- random (seeded)
  lithographic displacements of the clock-barrier dipole pairs (row
  boundaries) and, separately, random channel-stop strengths (column
  boundaries). :func:`structure_function` D(lag) = <(A(x + lag) - A(x))^2>
  along the serial and parallel axes separates the two (the paper's PRNU
  point): jitter gives anticorrelated neighbouring rows (D(1) > D(2) along
  the parallel axis, nothing along the serial axis), channel-stop variations
  a column pattern with positively correlated neighbours (D(1) < D(2) along
  the serial axis, nothing along the parallel axis).

Distances are in pixels unless stated; areas in px^2; dipole strengths in
units of the paper's xi0 (:class:`~lsst_bfdrift.physics.sensor.SensorParameters`).
"""

import numpy as np
from astropy.table import Table, vstack

from lsst_bfdrift.physics.boundaries import pixel_boundaries
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters
from lsst_bfdrift.utils.errors import InputError

__all__ = ["block_geometry", "tearing_onset", "tearing_summary", "bamboo", "bamboo_summary",
           "jitter_area_map", "channel_stop_area_map", "jitter_response",
           "channel_stop_response", "structure_function", "expected_structure_function",
           "prnu"]


def block_geometry(params, i_range, j_range, *, edge_samples=8, tol=1e-4):
    """Pixel polygons and moments of a block for a model without collected charge.

    Parameters
    ----------
    params : SensorParameters
        The model.
    i_range, j_range : tuple of int
        Half-open ranges of columns and rows.
    edge_samples : int, optional
        Samples per edge.
    tol : float, optional
        Bisection tolerance (px).

    Returns
    -------
    astropy.table.Table
        One row per pixel: ``i``, ``j``, ``area`` (px^2), ``dx``, ``dy``
        (centroid shift from the pixel centre, px), ``e1``, ``e2`` and the
        clockwise vertex arrays ``xv``, ``yv`` (px).
    """
    g = pixel_boundaries(SensorModel(params), i_range, j_range, edge_samples=edge_samples,
                         tol=tol)
    x, y = pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions, i0=g.i0, j0=g.j0)
    jj, ii = np.mgrid[j_range[0]:j_range[1], i_range[0]:i_range[1]]
    m = polygon_moments(x, y, origin=(ii, jj))
    nv = x.shape[-1]
    return Table({"i": ii.ravel(), "j": jj.ravel(), "area": m.area.ravel(),
                  "dx": (m.x - ii).ravel(), "dy": (m.y - jj).ravel(), "e1": m.e1.ravel(),
                  "e2": m.e2.ravel(), "xv": x.reshape(-1, nv), "yv": y.reshape(-1, nv)})


def _stack(blocks, settings, meta):
    for b, s in zip(blocks, settings):
        b.add_column(np.full(len(b), float(s)), name="setting", index=0)
    t = vstack(blocks)
    t.meta["feature"] = meta
    return t


def tearing_onset(params=None, *, weakening=(0.0, 0.25, 0.5, 0.75, 1.0), boundary=0,
                  i_range=(-3, 3), j_range=(-4, 4), edge_samples=8, tol=1e-4):
    """Pixels around the end of a weakened channel stop, for several weakenings.

    The channel stop on column boundary ``boundary`` keeps its full strength
    for y < 0 and is weakened by the fraction ``f`` for y > 0 (row boundary 0),
    through a truncated line dipole of strength ``-f xi_CS`` (the paper's
    eq. 3.10). ``f = 0`` is the regular grid.

    Parameters
    ----------
    params : SensorParameters, optional
        Base model (default: package defaults); its ``truncations`` are
        replaced.
    weakening : sequence of float, optional
        Fractions f (0: full stop, 1: no stop beyond the truncation).
    boundary : int, optional
        Column boundary of the weakened stop.
    i_range, j_range : tuple of int, optional
        Block of pixels computed.

    Returns
    -------
    astropy.table.Table
        :func:`block_geometry` rows with a leading ``setting`` column (f).
    """
    base = SensorParameters() if params is None else params
    f = [float(v) for v in weakening]
    if any(not 0.0 <= v <= 1.0 for v in f):
        raise InputError(f"weakening fractions must lie in [0, 1], got {weakening!r}")
    blocks = []
    for v in f:
        trunc = ((float(boundary), 0.0, 1.0, -v * base.xi_cs),) if v else ()
        blocks.append(block_geometry(base.replace(truncations=trunc), i_range, j_range,
                                     edge_samples=edge_samples, tol=tol))
    return _stack(blocks, f, f"tearing onset at column boundary {boundary}; "
                             "setting = weakening f of the stop for y > 0")


def tearing_summary(table):
    """Per weakening f: largest absolute A - 1 and dx, areas far beyond and at the end.

    Returns
    -------
    dict
        ``{"f=<f>": {"max_abs_dA", "max_abs_dx", "area_far", "area_end"}}``;
        ``area_far`` is the pixel just right of the stop in the top row,
        ``area_end`` the one in row 0 (just past the truncation).
    """
    out = {}
    for f in sorted(set(table["setting"])):
        s = table[table["setting"] == f]
        area = np.asarray(s["area"])
        b = int(np.min(s["i"])) + (int(np.max(s["i"])) - int(np.min(s["i"])) + 1) // 2
        top = (s["i"] == b) & (s["j"] == np.max(s["j"]))
        end = (s["i"] == b) & (s["j"] == 0)
        out[f"f={f:g}"] = {"max_abs_dA": float(np.max(np.abs(area - 1))),
                           "max_abs_dx": float(np.max(np.abs(s["dx"]))),
                           "area_far": float(area[top][0]), "area_end": float(area[end][0])}
    return out


def _periodic_overrides(amplitude, period, n_periods):
    """Column-boundary overrides a cos(2 pi b / P) over +-n_periods periods."""
    bs = np.arange(-n_periods * period, (n_periods + 1) * period + 1)
    return tuple((float(b), float(amplitude * np.cos(2 * np.pi * b / period))) for b in bs)


def bamboo(params=None, *, amplitudes=(0.5, 1.0, 2.0), period=8, n_periods=3, edge_samples=8,
           tol=1e-4):
    """One period of columns under a periodic channel-stop strength modulation.

    Column boundary ``b`` carries an extra channel-stop dipole
    ``a cos(2 pi b / period)`` xi0 (the same sign convention as ``xi_cs``,
    along +z), for boundaries within ``n_periods`` periods of the strip. The
    pattern is uniform along the columns, so a one-row strip of ``period``
    columns (0 .. period - 1) is computed.

    Returns
    -------
    astropy.table.Table
        :func:`block_geometry` rows with a leading ``setting`` column (a).
    """
    base = SensorParameters() if params is None else params
    if int(period) != period or period < 2:
        raise InputError(f"period must be an integer >= 2 columns, got {period!r}")
    blocks = []
    for a in amplitudes:
        p = base.replace(column_overrides=_periodic_overrides(a, int(period), int(n_periods)))
        blocks.append(block_geometry(p, (0, int(period)), (0, 1), edge_samples=edge_samples,
                                     tol=tol))
    return _stack(blocks, amplitudes, f"bamboo: channel-stop modulation a cos(2 pi b / "
                                      f"{int(period)}); setting = a (xi0)")


def bamboo_summary(table):
    """Per amplitude: peak-to-peak area, area sum over the period, dA per unit a."""
    out = {}
    for a in sorted(set(table["setting"])):
        area = np.asarray(table[table["setting"] == a]["area"])
        out[f"a={a:g}"] = {"area_peak_to_peak": float(np.ptp(area)),
                           "area_sum_minus_period": float(area.sum() - area.size),
                           "area_column0": float(area[0]),
                           "area_peak_to_peak_per_xi0":
                               float(np.ptp(area) / abs(a)) if a else float("nan")}
    return out


def jitter_area_map(params=None, *, sigma=0.1, shape=(32, 32), seed=1, edge_samples=8,
                    tol=1e-5):
    """Area map of a patch whose clock-barrier pairs are randomly displaced.

    Every row boundary ``b`` of the patch (and ``margin`` beyond it) has its
    clock dipole pair moved by a Gaussian ``delta_b`` (um, standard deviation
    ``sigma``) along y. The pattern is uniform along x, so one column is
    computed and repeated.

    Parameters
    ----------
    sigma : float, optional
        Standard deviation of the displacements (um).
    shape : tuple of int, optional
        (rows, columns) of the map.
    seed : int, optional
        Seed of numpy's default_rng.

    Returns
    -------
    area : ndarray, shape ``shape``
        Pixel areas (px^2), indexed [row, column].
    shifts : ndarray
        The displacements (um) of row boundaries ``-margin .. rows + margin``.
    """
    return _random_stripes(params, "row_shifts", sigma, shape, seed, edge_samples, tol)


def channel_stop_area_map(params=None, *, sigma=0.5, shape=(32, 32), seed=2, edge_samples=8,
                          tol=1e-5):
    """Area map of a patch whose channel-stop strengths vary randomly.

    Every column boundary ``b`` of the patch (and ``margin`` beyond it) gets
    an extra channel-stop dipole, Gaussian with standard deviation ``sigma``
    (xi0). The pattern is uniform along y, so one row is computed and
    repeated.

    Returns
    -------
    area : ndarray, shape ``shape``
        Pixel areas (px^2), indexed [row, column].
    deltas : ndarray
        The strength changes (xi0) of column boundaries ``-margin .. columns + margin``.
    """
    return _random_stripes(params, "column_overrides", sigma, shape, seed, edge_samples, tol)


def _random_stripes(params, field, sigma, shape, seed, edge_samples, tol):
    """Area map of Gaussian values (standard deviation ``sigma``) on every
    boundary of one direction, patch plus a margin of 4: ``field`` is
    'row_shifts' (row boundaries; one column computed) or 'column_overrides'
    (column boundaries; one row computed); the line is repeated across the
    patch. Returns (area, values)."""
    base = SensorParameters() if params is None else params
    ny, nx = (int(v) for v in shape)
    margin = 4
    rows = field == "row_shifts"
    bs = np.arange(-margin, (ny if rows else nx) + margin + 1)
    values = np.random.default_rng(seed).normal(0.0, sigma, bs.size)
    p = base.replace(**{field: tuple((float(b), float(v)) for b, v in zip(bs, values))})
    if rows:
        line = block_geometry(p, (0, 1), (0, ny), edge_samples=edge_samples, tol=tol)
        return np.repeat(np.asarray(line["area"])[:, None], nx, axis=1), values
    line = block_geometry(p, (0, nx), (0, 1), edge_samples=edge_samples, tol=tol)
    return np.repeat(np.asarray(line["area"])[None, :], ny, axis=0), values


def jitter_response(params=None, *, delta=0.2, half_width=6, edge_samples=8, tol=1e-5):
    """Area change of the rows around one displaced clock-barrier pair, per um.

    The pair on row boundary 0 is moved by ``delta`` um along +y.

    Returns
    -------
    rows : ndarray of int
        Rows ``-half_width .. half_width - 1``.
    kernel : ndarray
        (A_j - 1) / delta, px^2 per um.
    """
    base = SensorParameters() if params is None else params
    t = block_geometry(base.replace(row_shifts=((0.0, float(delta)),)), (0, 1),
                       (-half_width, half_width), edge_samples=edge_samples, tol=tol)
    return np.asarray(t["j"]), (np.asarray(t["area"]) - 1.0) / delta


def channel_stop_response(params=None, *, delta=1.0, half_width=6, edge_samples=8, tol=1e-5):
    """Area change of the columns around one channel stop changed by ``delta`` xi0, per xi0.

    Returns
    -------
    columns : ndarray of int
        Columns ``-half_width .. half_width - 1`` (the stop is on boundary 0).
    kernel : ndarray
        (A_i - 1) / delta, px^2 per xi0.
    """
    base = SensorParameters() if params is None else params
    t = block_geometry(base.replace(column_overrides=((0.0, float(delta)),)),
                       (-half_width, half_width), (0, 1), edge_samples=edge_samples, tol=tol)
    return np.asarray(t["i"]), (np.asarray(t["area"]) - 1.0) / delta


def expected_structure_function(kernel, sigma, max_lag):
    """Ensemble structure function of white inputs filtered by a linear kernel.

    If A_k = 1 + sum_b K[k - b] s_b with independent s_b of standard deviation
    ``sigma``, then D(lag) = 2 sigma^2 (c(0) - c(lag)) with c the kernel's
    autocorrelation c(l) = sum_k K[k] K[k + l].

    Returns
    -------
    lags : ndarray of int
        1 .. max_lag.
    d : ndarray
    """
    k = np.asarray(kernel, dtype=float)
    lags = np.arange(1, int(max_lag) + 1)
    c0 = np.sum(k * k)
    c = np.array([np.sum(k[:-lag] * k[lag:]) if lag < k.size else 0.0 for lag in lags])
    return lags, 2.0 * sigma**2 * (c0 - c)


def structure_function(image, max_lag, *, axis):
    """Structure function D(lag) = <(A(x + lag) - A(x))^2> along one axis.

    Parameters
    ----------
    image : ndarray, 2-D
        The map (e.g. pixel areas), indexed [row, column].
    max_lag : int
        Largest lag (px); lags 1 .. max_lag are returned.
    axis : {'serial', 'parallel'}
        'serial' differences columns (x), 'parallel' differences rows (y).

    Returns
    -------
    lags : ndarray of int
    d : ndarray
        Mean squared difference at each lag (units of the map squared).
    """
    a = np.asarray(image, dtype=float)
    if a.ndim != 2:
        raise InputError(f"image must be 2-D, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError("image contains NaN or inf")
    ax = {"serial": 1, "parallel": 0}.get(axis)
    if ax is None:
        raise InputError(f"axis must be 'serial' or 'parallel', got {axis!r}")
    n = a.shape[ax]
    if not 1 <= int(max_lag) < n:
        raise InputError(f"max_lag must be between 1 and {n - 1}, got {max_lag!r}")
    lags = np.arange(1, int(max_lag) + 1)
    d = np.empty(lags.size)
    for k, lag in enumerate(lags):
        diff = np.diff(a, n=1, axis=ax) if lag == 1 else (
            a[lag:] - a[:-lag] if ax == 0 else a[:, lag:] - a[:, :-lag])
        d[k] = np.mean(diff**2)
    return lags, d


def prnu(params=None, *, jitter_sigma=0.1, cs_sigma=0.5, shape=(32, 32), max_lag=8,
         edge_samples=8, tol=1e-4, kernel_tol=1e-5, kernel_half_width=8, seeds=(1, 2)):
    """Area maps and structure functions of clock jitter and channel-stop variations.

    Parameters
    ----------
    params : SensorParameters, optional
        Base model.
    jitter_sigma : float, optional
        Standard deviation of the clock-pair displacements (um).
    cs_sigma : float, optional
        Standard deviation of the channel-stop strength changes (xi0).
    shape : tuple of int, optional
        (rows, columns) of the maps.
    max_lag : int, optional
        Largest lag of the structure functions (px).
    edge_samples, tol : optional
        Boundary sampling of the maps (tolerance in px).
    kernel_tol, kernel_half_width : optional
        Tolerance (px) and half width (px) of the single-barrier responses
        that give the ensemble-average structure functions.
    seeds : tuple of int, optional
        Seeds of the jitter and channel-stop draws.

    Returns
    -------
    dict
        ``maps`` {'jitter', 'channel_stop'} of areas; ``lags``; ``D`` with
        keys '<map>_<axis>'; ``summary`` with the rms area, D(1) / D(2) along
        each axis and the lag-1 correlation coefficient of neighbouring
        pixels along each axis.
    """
    ja, jsh = jitter_area_map(params, sigma=jitter_sigma, shape=shape, seed=seeds[0],
                              edge_samples=edge_samples, tol=tol)
    ca, cdel = channel_stop_area_map(params, sigma=cs_sigma, shape=shape, seed=seeds[1],
                                     edge_samples=edge_samples, tol=tol)
    out = {"maps": {"jitter": ja, "channel_stop": ca}, "inputs": {"jitter": jsh,
                                                                  "channel_stop": cdel},
           "D": {}, "summary": {}}
    for name, a in out["maps"].items():
        s = {"rms_area": float(np.std(a))}
        for axis in ("serial", "parallel"):
            lags, d = structure_function(a, max_lag, axis=axis)
            out["D"][f"{name}_{axis}"] = d
            s[f"D1_{axis}"] = float(d[0])
            s[f"D1_over_D2_{axis}"] = float(d[0] / d[1]) if d[1] > 0 else float("nan")
            v = a - a.mean()
            ax = 1 if axis == "serial" else 0
            n = a.shape[ax]
            x0 = np.take(v, np.arange(n - 1), axis=ax)
            x1 = np.take(v, np.arange(1, n), axis=ax)
            den = np.sqrt(np.mean(x0**2) * np.mean(x1**2))
            s[f"corr1_{axis}"] = float(np.mean(x0 * x1) / den) if den > 0 else float("nan")
        out["summary"][name] = s
    out["lags"] = lags
    hw = max(int(kernel_half_width), int(max_lag))
    for name, (resp, sig) in {"jitter": (jitter_response, jitter_sigma),
                              "channel_stop": (channel_stop_response, cs_sigma)}.items():
        idx, k = resp(params, half_width=hw, edge_samples=edge_samples, tol=kernel_tol)
        axis = "parallel" if name == "jitter" else "serial"
        _, d = expected_structure_function(k, sig, max_lag)
        out["inputs"][f"{name}_kernel"] = (idx, k)
        out["D"][f"{name}_{axis}_expected"] = d
        out["summary"][name][f"expected_D1_over_D2_{axis}"] = float(d[0] / d[1])
        c1 = np.sum(k[:-1] * k[1:]) / np.sum(k * k)
        out["summary"][name][f"expected_corr1_{axis}"] = float(c1)
        out["summary"][name]["kernel_peak"] = float(k[np.argmax(np.abs(k))])
    out["settings"] = {"jitter_sigma_um": jitter_sigma, "cs_sigma_xi0": cs_sigma,
                       "shape": list(shape), "seeds": list(seeds)}
    return out
