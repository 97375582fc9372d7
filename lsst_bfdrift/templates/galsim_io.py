"""Import of GalSim's sensor distortion files into
:class:`~lsst_bfdrift.templates.template.DistortionTemplate`.

GalSim's ``share/sensors/NAME.dat`` (written by the Poisson_CCD solver) lists,
for each pixel of an Nx x Ny stamp around a pixel holding
``CollectedCharge_0_0`` electrons, the distorted positions of 4 n + 4 vertices
(4 corners and n per edge, n = ``NumVertices``). Rows are ordered pixel by
pixel (x index slowest), and within a pixel in the order of GalSim's nominal
vertex list sorted by polar angle about the pixel centre (atan2, ascending
from -pi). Nominal edge vertices sit at fractions (tan(theta_k) + 1) / 2,
theta_k = -pi/4 + (k + 1) pi / (2 (n + 1)). Columns: X0, Y0 (pixel centre,
um), Theta, X, Y (vertex, um).

This module reads those files with its own parser (no GalSim internals) and
returns the per-pixel, per-edge table of the paper's portable form.
"""

import os
import warnings

import numpy as np
from astropy.table import Table
from astropy.utils.exceptions import AstropyUserWarning

from lsst_bfdrift.templates.galsim_rules import (add_templates_galsim, galsim_boxes,
                                                 galsim_edge_templates, locate_galsim,
                                                 nominal_edges)
from lsst_bfdrift.templates.template import DistortionTemplate
from lsst_bfdrift.utils.errors import InputError, InputNotFoundError

__all__ = ["import_galsim_sensor", "galsim_sensor_files", "read_galsim_config",
           "galsim_nominal_vertices", "galsim_vertex_table", "galsim_ring_offset",
           "read_galsim_sensor", "match_galsim_areas", "edge_integrals",
           "galsim_effective_moves", "transfers_from_moves", "match_galsim_transfers"]


def import_galsim_sensor(name="lsst_itl_50_8", *, match="areas", qdist=3, transfer_charge=1e4,
                         transfer_cells=4000):
    """Import one of GalSim's sensor distortion files (Poisson_CCD output).

    Parameters
    ----------
    name : str
        Sensor name in galsim's ``share/sensors`` (e.g. ``lsst_itl_50_8``)
        or a path without extension to a ``.cfg``/``.dat`` pair.
    match : {'areas', 'transfers', 'none'}, optional
        'areas' (the default): the shared corners are moved so that every
        pixel polygon's area equals GalSim's own
        (:func:`~lsst_bfdrift.templates.galsim_io.match_galsim_areas`).
        'transfers': the edge samples are shifted so that every edge's
        swept area equals the area galsim.SiliconSensor effectively moves
        across it (its non-tiling pixels and nominal-pixel-first rule,
        :func:`~lsst_bfdrift.templates.galsim_io.match_galsim_transfers`); the
        swept-area kernels' pixel areas then equal GalSim's effective
        areas (what a flat measures). 'none': each edge and corner is
        taken from the pixel nearest the aggressor.
    qdist : int, optional
        GalSim's ``qdist`` of the simulation to match (its default 3);
        used by ``match='transfers'``.
    transfer_charge : float, optional
        Aggressor charge (e) at which ``match='transfers'`` measures
        GalSim's transfers, scaled linearly to the file's charge. GalSim's
        effective transfers per electron are not quite constant (its rule
        near the non-tiling corners): the central pixel's area change per
        1e5 e is -0.1070, -0.1068, -0.1062 and -0.1044 px^2 at 3e3, 1e4,
        3e4 and 1e5 e. The corrections are linear in the charge, so the
        default takes the small-charge limit (1e4 e); the file's own
        charge is ``transfer_charge=None``.
    transfer_cells : int, optional
        Sampling cells per pixel side of the transfer measurement
        (:func:`~lsst_bfdrift.templates.galsim_io.galsim_effective_moves`).

    Returns
    -------
    DistortionTemplate
        Charge ``CollectedCharge_0_0`` of the file; sample fractions are
        GalSim's tan-spaced vertex positions; tangential displacements kept.
        The per-pixel table keeps the file's vertices exactly
        (``polygons(per_pixel=True)``). ``meta['galsim_match']`` records
        the match.

    Examples
    --------
    GalSim's LSST ITL sensor as a template (the file's 9 x 9 pixels around
    an aggressor of 1e5 e), ready for the Task:

    >>> from lsst_bfdrift import BrighterFatterDriftTask, import_galsim_sensor
    >>> t = import_galsim_sensor("lsst_itl_50_8")
    >>> t.size, t.charge, t.meta["galsim_match"]
    (9, 100000.0, 'areas')
    >>> task = BrighterFatterDriftTask(template=t)
    """
    if match not in ("areas", "transfers", "none"):
        raise InputError(f"match must be 'areas', 'transfers' or 'none', got {match!r}")
    tpl = read_galsim_sensor(name)
    if match == "areas":
        tpl = match_galsim_areas(tpl, name)
    elif match == "transfers":
        tpl = match_galsim_transfers(tpl, name, qdist=qdist, charge=transfer_charge,
                                     cells=transfer_cells)
    tpl.meta["galsim_match"] = match
    return tpl


def galsim_sensor_files(name):
    """Paths (cfg, dat) of a GalSim sensor, by name or path prefix."""
    cfg, dat = name + ".cfg", name + ".dat"
    if not os.path.isfile(cfg):
        import galsim  # heavy: only for the path of its bundled sensor files
        base = os.path.join(galsim.meta_data.share_dir, "sensors", name)
        cfg, dat = base + ".cfg", base + ".dat"
    for path in (cfg, dat):
        if not os.path.isfile(path):
            raise InputNotFoundError(f"GalSim sensor file {path} not found")
    return cfg, dat


def read_galsim_config(path):
    """Parse a Poisson_CCD ``.cfg`` file (``key = value  # comment``)."""
    config = {}
    with open(path) as fh:
        for lineno, line in enumerate(fh, 1):
            line = line.split("#", 1)[0].strip()
            if not line:
                continue
            parts = line.split("=", 1)
            if len(parts) != 2:
                raise InputError(f"{path}:{lineno}: expected 'key = value', got {line!r}")
            key, value = parts[0].strip(), parts[1].strip()
            for conv in (int, float):
                try:
                    value = conv(value)
                    break
                except ValueError:
                    continue
            config[key] = value
    return config


def galsim_nominal_vertices(num_vertices):
    """Nominal vertices of a unit pixel ([0, 1]^2) in GalSim's sorted order.

    Returns
    -------
    x, y : ndarray, shape (4 n + 4,)
    kind : ndarray of str
        'corner', 'left', 'right', 'bottom' or 'top'.
    fractions : ndarray, shape (n,)
        Edge fractions (tan spaced).
    """
    n = int(num_vertices)
    theta = -np.pi / 4 + (np.arange(n) + 1.0) * np.pi / (2.0 * (n + 1.0))
    fr = (np.tan(theta) + 1.0) / 2.0
    xs, ys, kinds = [], [], []
    for cx in (0.0, 1.0):
        for cy in (0.0, 1.0):
            xs.append(cx), ys.append(cy), kinds.append("corner")
    for cx, kind in ((0.0, "left"), (1.0, "right")):
        xs += [cx] * n
        ys += list(fr)
        kinds += [kind] * n
    for cy, kind in ((0.0, "bottom"), (1.0, "top")):
        xs += list(fr)
        ys += [cy] * n
        kinds += [kind] * n
    xs, ys, kinds = np.array(xs), np.array(ys), np.array(kinds)
    order = np.argsort(np.arctan2(ys - 0.5, xs - 0.5), kind="stable")
    return xs[order], ys[order], kinds[order], fr


def galsim_vertex_table(name):
    """The raw vertices of a GalSim sensor file, with their nominal positions.

    Returns
    -------
    astropy.table.Table
        Columns ``i, j`` (pixel offset from the filled pixel), ``kind``,
        ``x_nom, y_nom`` (nominal vertex in the pixel frame, pixel units,
        origin at the lower-left corner) and ``x, y`` (vertex read from the
        file, same frame).
    config : dict
        The parsed configuration.
    """
    cfg, dat = galsim_sensor_files(name)
    config = read_galsim_config(cfg)
    try:
        nv = int(config["NumVertices"])
        nx, ny = int(config["PixelBoundaryNx"]), int(config["PixelBoundaryNy"])
        pitch = float(config["PixelSizeX"])
        fx, fy = (float(v) for v in str(config["FilledPixelCoords_0_0"]).split()) \
            if isinstance(config["FilledPixelCoords_0_0"], str) else (None, None)
    except KeyError as exc:
        raise InputError(f"{cfg}: missing configuration key {exc}") from exc
    data = np.loadtxt(dat, skiprows=1)
    npv = 4 * nv + 4
    if data.shape != (nx * ny * npv, 5):
        raise InputError(f"{dat} has shape {data.shape}, config {cfg} implies "
                         f"({nx * ny * npv}, 5)")
    xn, yn, kind, _ = galsim_nominal_vertices(nv)
    x0, y0, _, xv, yv = data.T
    pix_i = np.rint((x0 - fx) / pitch).astype(int) if fx is not None else None
    pix_j = np.rint((y0 - fy) / pitch).astype(int) if fy is not None else None
    t = Table()
    t["i"] = pix_i
    t["j"] = pix_j
    t["kind"] = np.tile(kind, nx * ny)
    t["x_nom"] = np.tile(xn, nx * ny)
    t["y_nom"] = np.tile(yn, nx * ny)
    t["x"] = (xv - x0) / pitch + 0.5
    t["y"] = (yv - y0) / pitch + 0.5
    return t, config


#: Ring offset (fraction of the file's largest vertex displacement) above
#: which :func:`read_galsim_sensor` warns. GalSim's lsst_*_50_* files and
#: lsst_itl_8/32 show none (below 1e-4 px); lsst_e2v_8 and lsst_e2v_32
#: show 0.31 of it.
RING_OFFSET_WARN = 0.1


def galsim_ring_offset(raw):
    """Median displacement (px) of the boundaries of a GalSim file's outermost
    ring of pixels, where the brighter-fatter displacements have faded.

    Parameters
    ----------
    raw : astropy.table.Table
        From :func:`galsim_vertex_table`.

    Returns
    -------
    dx, dy : float
        Median x displacement of the vertical edges' vertices and median y
        displacement of the horizontal edges' vertices (px) of the pixels
        farthest from the aggressor (Chebyshev distance). Both are about 0
        when the file's distortions are due to the aggressor's charge alone;
        a value comparable to the displacements near the aggressor is a
        charge-independent offset of the solver's grid, which
        galsim.SiliconSensor nevertheless scales with each pixel's charge
        (it reads every displacement as per electron).
    max_displacement : float
        Largest vertex displacement of the file (px).
    """
    i, j = np.asarray(raw["i"]), np.asarray(raw["j"])
    kind = np.asarray(raw["kind"])
    dx = np.asarray(raw["x"] - raw["x_nom"], float)
    dy = np.asarray(raw["y"] - raw["y_nom"], float)
    cheb = np.maximum(np.abs(i), np.abs(j))
    ring = cheb == cheb.max()
    vert = ring & np.isin(kind, ["left", "right"])
    horiz = ring & np.isin(kind, ["top", "bottom"])
    return (float(np.median(dx[vert])), float(np.median(dy[horiz])),
            float(max(np.abs(dx).max(), np.abs(dy).max())))


def read_galsim_sensor(name):
    """Build a :class:`~lsst_bfdrift.templates.template.DistortionTemplate` from a GalSim file.

    The file's ring offset (:func:`galsim_ring_offset`) is kept in
    ``meta['galsim_ring_offset']`` ([dx, dy], px); when it exceeds
    ``RING_OFFSET_WARN`` of the largest displacement an
    ``AstropyUserWarning`` says so: the template carries the offset as
    GalSim does (scaled by charge), which in bright stars adds up to
    boundary shifts of tenths of a pixel.
    """
    raw, config = galsim_vertex_table(name)
    ring_dx, ring_dy, dmax = galsim_ring_offset(raw)
    if max(abs(ring_dx), abs(ring_dy)) > RING_OFFSET_WARN * dmax:
        q = float(config["CollectedCharge_0_0"])
        warnings.warn(
            f"GalSim sensor file {name}: the boundaries of the pixels farthest from the "
            f"aggressor are displaced by a median dx = {ring_dx:+.4f}, dy = {ring_dy:+.4f} px "
            f"({max(abs(ring_dx), abs(ring_dy)) / dmax:.0%} of the largest displacement, "
            f"{dmax:.4f} px): a charge-independent offset of the solver's grid, which "
            f"galsim.SiliconSensor and this template scale with charge as if the "
            f"{q:.6g} e aggressor caused it (per 1e6 e within GalSim's qdist: "
            f"{max(abs(ring_dx), abs(ring_dy)) * 1e6 / q:.2f} px); templates imported "
            "from it are outside the linear regime for bright stars", AstropyUserWarning)
    nv = int(config["NumVertices"])
    nx, ny = int(config["PixelBoundaryNx"]), int(config["PixelBoundaryNy"])
    if nx != ny or nx % 2 != 1:
        raise InputError(f"GalSim sensor stamp must be square and odd, got {nx} x {ny}")
    charge = float(config["CollectedCharge_0_0"])
    _, _, _, fr = galsim_nominal_vertices(nv)
    dx = np.asarray(raw["x"] - raw["x_nom"])
    dy = np.asarray(raw["y"] - raw["y_nom"])
    rows = {k: [] for k in ("di", "dj", "edge", "c0x", "c0y", "c1x", "c1y", "normal",
                            "tangent")}
    npv = 4 * nv + 4
    for p in range(nx * ny):
        sl = slice(p * npv, (p + 1) * npv)
        kinds = np.asarray(raw["kind"][sl])
        xn, yn = np.asarray(raw["x_nom"][sl]), np.asarray(raw["y_nom"][sl])
        ddx, ddy = dx[sl], dy[sl]

        def corner(cx, cy):
            k = np.flatnonzero((kinds == "corner") & (xn == cx) & (yn == cy))[0]
            return ddx[k], ddy[k]

        for edge, (a, b) in {"left": ((0, 0), (0, 1)), "top": ((0, 1), (1, 1)),
                             "right": ((1, 0), (1, 1)), "bottom": ((0, 0), (1, 0))}.items():
            sel = np.flatnonzero(kinds == edge)
            along = yn[sel] if edge in ("left", "right") else xn[sel]
            sel = sel[np.argsort(along)]
            if edge in ("left", "right"):
                normal, tangent = ddx[sel], ddy[sel]
            else:
                normal, tangent = ddy[sel], ddx[sel]
            c0, c1 = corner(*a), corner(*b)
            rows["di"].append(int(raw["i"][p * npv]))
            rows["dj"].append(int(raw["j"][p * npv]))
            rows["edge"].append(edge)
            rows["c0x"].append(c0[0])
            rows["c0y"].append(c0[1])
            rows["c1x"].append(c1[0])
            rows["c1y"].append(c1[1])
            rows["normal"].append(normal)
            rows["tangent"].append(tangent)
    table = Table({k: (np.array(v) if k not in ("normal", "tangent") else np.array(v))
                   for k, v in rows.items()})
    meta = {"source": f"galsim:{name}", "merge": "nearest",
            "galsim_ring_offset": [ring_dx, ring_dy],
            "galsim_config": {k: v for k, v in config.items()
                              if isinstance(v, (int, float, str))}}
    return DistortionTemplate.from_table(table, fr, charge, meta=meta, merge="nearest")


def match_galsim_areas(template, name):
    """Adjust the shared corners so that pixel areas equal GalSim's own.

    GalSim keeps per-edge copies of pixel corners, so its pixels do not tile
    and no shared (tiling) boundary set reproduces all its vertices. The
    areas matter most for the flux, so the corners of the shared form are
    moved by the smallest amount (minimum-norm least squares on the
    linearised shoelace areas, then one Newton refinement) that makes every
    pixel area equal ``galsim.SiliconSensor(name).calculate_pixel_areas`` for
    the file's aggressor charge.

    Returns
    -------
    DistortionTemplate
        A copy with adjusted corners (``meta['area_matched']`` records the
        largest corner change, px).
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    n, c = template.size, template.center
    sensor = galsim.SiliconSensor(name)
    big = n + 2 * sensor.qdist + 4
    img = galsim.ImageD(big, big)
    img.setCenter(0, 0)
    img[0, 0] = template.charge
    ref = sensor.calculate_pixel_areas(img).array
    mid = big // 2
    target = ref[mid - c:mid + c + 1, mid - c:mid + c + 1]

    def areas(cd):
        t = type(template)(cd, template.vedge_d, template.hedge_d, template.fractions,
                           template.charge, vedge_t=template.vedge_t, hedge_t=template.hedge_t,
                           meta=template.meta)
        return t.moments().area

    cd = template.corner_d.copy()
    total = np.zeros_like(cd)
    for _ in range(2):
        a0 = areas(cd)
        eps = 1e-6
        jac = np.empty((n * n, cd.size))
        flat = cd.ravel()
        for k in range(cd.size):
            pert = flat.copy()
            pert[k] += eps
            jac[:, k] = ((areas(pert.reshape(cd.shape)) - a0) / eps).ravel()
        step = np.linalg.lstsq(jac, (target - a0).ravel(), rcond=None)[0].reshape(cd.shape)
        cd = cd + step
        total += step
    meta = dict(template.meta)
    meta["area_matched"] = float(np.abs(total).max())
    return type(template)(cd, template.vedge_d, template.hedge_d, template.fractions,
                          template.charge, vedge_t=template.vedge_t, hedge_t=template.hedge_t,
                          meta=meta, pixel_table=template._pixel_table)


# -- effective transfers -------------------------------------------------------

_ENGINES = ("galsim", "rules")


def _trapezoid_weights(fractions):
    """Weights w_k of the interior knots in the trapezoid integral over [0, 1]."""
    s = np.concatenate([[0.0], np.asarray(fractions, float), [1.0]])
    return 0.5 * (s[2:] - s[:-2])


def edge_integrals(template):
    """Normal displacement of every template edge integrated along it (px^2).

    The trapezoid integral of the piecewise-linear profile through the two
    corners and the edge samples (the quantity
    :func:`lsst_bfdrift.templates.swept.swept_area_kernels` uses as swept area).

    Returns
    -------
    kv : ndarray, shape (N, N + 1)
        Vertical edges, positive towards +x.
    kh : ndarray, shape (N + 1, N)
        Horizontal edges, positive towards +y.
    """
    t = template
    s = np.concatenate([[0.0], t.fractions, [1.0]])

    def integ(c0, samples, c1):
        vals = np.concatenate([c0[..., None], samples, c1[..., None]], axis=-1)
        return np.sum(0.5 * (vals[..., 1:] + vals[..., :-1]) * np.diff(s), axis=-1)

    kv = integ(t.corner_d[:-1, :, 0], t.vedge_d, t.corner_d[1:, :, 0])
    kh = integ(t.corner_d[:, :-1, 1], t.hedge_d, t.corner_d[:, 1:, 1])
    return kv, kh


def _galsim_layout(template, half, pad, qdist, charge):
    """GalSim's edge polylines (:mod:`lsst_bfdrift.templates.galsim_rules`) of a stamp of
    side 2 (half + pad) + 1 with ``charge`` (e) in the central pixel."""
    big = 2 * (half + pad) + 1
    tv, th = galsim_edge_templates(template, qdist=qdist)
    V, H = nominal_edges(big, big, template.fractions)
    dq = np.zeros((big, big))
    dq[big // 2, big // 2] = charge
    add_templates_galsim(dq, 1.0 / template.charge, template.center, V, H, tv, th)
    return V, H


def _band_widths(V, H, half, pad, fractions):
    """Largest vertex displacement (px) of each pixel polygon of the layout,
    pixels -half..half; beyond it from the nominal square's boundary every
    point lies inside the polygon (and GalSim assigns it to its nominal pixel)."""
    v0, h0 = nominal_edges(V.shape[0], H.shape[1], fractions)
    dv = np.abs(V - v0).max(axis=(2, 3))
    dh = np.abs(H - h0).max(axis=(2, 3))
    w = np.maximum(np.maximum(dv[:, :-1], dv[:, 1:]), np.maximum(dh[:-1, :], dh[1:, :]))
    return w[pad:pad + 2 * half + 1, pad:pad + 2 * half + 1]


def _band_points(widths, cells, rng):
    """Stratified points (one uniform random point per cell of side 1 / cells) of
    the band of each nominal pixel within ``widths`` (px, rounded up to whole
    cells plus two) of its boundary.

    Returns, per pixel (j, i) of ``widths``: x, y relative to the pixel centre
    and the interior area (px^2) left out (always the nominal pixel's).
    """
    h = 1.0 / cells
    out = {}
    for (j, i), w in np.ndenumerate(widths):
        nb = min(int(np.ceil(w / h)) + 2, cells // 2)
        k = np.arange(cells)
        side = np.concatenate([k[:nb], k[cells - nb:]])
        mid = k[nb:cells - nb]
        # row-major: nb full rows, the middle rows' edge cells, nb full rows
        ky = np.concatenate([np.repeat(k[:nb], cells), np.repeat(mid, side.size),
                             np.repeat(k[cells - nb:], cells)])
        kx = np.concatenate([np.tile(k, nb), np.tile(side, mid.size), np.tile(k, nb)])
        x = (kx + rng.random(kx.size)) * h - 0.5
        y = (ky + rng.random(ky.size)) * h - 0.5
        out[j, i] = (x, y, ((cells - 2 * nb) * h) ** 2 if cells > 2 * nb else 0.0)
    return out


def _moves_galsim(name, template, half, cells, qdist, seed, charge):
    """moves[j, i, b, a]: area (px^2) of nominal pixel (i, j) that galsim.SiliconSensor
    assigns to pixel (i + a - 1, j + b - 1), pixel indices -half..half -> 0..2 half.

    The points of nominal pixels three apart are accumulated together (GalSim
    assigns a conversion to its nominal pixel or one of the eight neighbours,
    so each pixel's count comes from one sampled pixel), with diffusion off
    and the boundaries frozen at those of ``charge`` e in pixel (0, 0).
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    pad = 3  # GalSim's stamp-edge rules and fixed top/right boundaries stay far away
    big = 2 * (half + pad) + 1
    V, H = _galsim_layout(template, half, pad, qdist, charge)
    pts = _band_points(1.5 * _band_widths(V, H, half, pad, template.fractions), cells,
                       np.random.default_rng(seed))
    moves = np.zeros((2 * half + 1, 2 * half + 1, 3, 3))
    w = 1.0 / cells**2
    for oy in range(3):
        for ox in range(3):
            sub = [(j, i) for j in range(oy, 2 * half + 1, 3) for i in range(ox, 2 * half + 1, 3)]
            x = np.concatenate([pts[p][0] + p[1] - half for p in sub])
            y = np.concatenate([pts[p][1] + p[0] - half for p in sub])
            sensor = galsim.SiliconSensor(name, diffusion_factor=0.0, nrecalc=1e18,
                                          qdist=int(qdist), rng=galsim.BaseDeviate(int(seed)))
            img = galsim.ImageD(big, big)
            img.setCenter(0, 0)
            img[0, 0] = charge
            sensor.accumulate(galsim.PhotonArray(x.size, x=x, y=y, flux=np.full(x.size, w)),
                              img)
            got = img.array.copy()
            got[half + pad, half + pad] -= charge
            got = got[pad - 1:pad + 2 * half + 2, pad - 1:pad + 2 * half + 2]  # half + 1 ring
            for j, i in sub:
                moves[j, i] = got[j:j + 3, i:i + 3]
                moves[j, i, 1, 1] += pts[j, i][2]
    return moves


def _moves_rules(template, half, cells, qdist, seed, charge):
    """As :func:`_moves_galsim`, with the re-implementation of GalSim's layout and
    rule (:mod:`lsst_bfdrift.templates.galsim_rules`); a point found in no pixel counts
    half to its nominal pixel and half to the first neighbour tried (GalSim's
    expectation). Same points as :func:`_moves_galsim` for the same seed."""
    pad = 3
    big = 2 * (half + pad) + 1
    V, H = _galsim_layout(template, half, pad, qdist, charge)
    box = np.empty((big, big, 4))
    galsim_boxes(V, H, 0, big, 0, big, box)
    pts = _band_points(1.5 * _band_widths(V, H, half, pad, template.fractions), cells,
                       np.random.default_rng(seed))
    moves = np.zeros((2 * half + 1, 2 * half + 1, 3, 3))
    w = 0.5 / cells**2
    for (j, i), (sx, sy, interior) in pts.items():
        px, py = sx + (i + pad), sy + (j + pad)
        oi = np.empty(px.size, np.int64)
        oj = np.empty(px.size, np.int64)
        for u in (0.75, 0.25):
            locate_galsim(px, py, np.full(px.size, u), V, H, box, oi, oj)
            np.add.at(moves[j, i], (oj - (j + pad) + 1, oi - (i + pad) + 1), w)
        moves[j, i, 1, 1] += interior
    return moves


def transfers_from_moves(moves):
    """Net area crossing each edge between nominal neighbours (px^2).

    A point of nominal pixel A assigned to a side neighbour B crosses the edge
    A|B. One assigned to a diagonal neighbour D is split in halves between the
    two paths through the pixels beside both (A -> (D_x, A_y) -> D and
    A -> (A_x, D_y) -> D), so that every pixel's net gain is kept exactly.

    Parameters
    ----------
    moves : ndarray, shape (M, M, 3, 3)
        From :func:`galsim_effective_moves`.

    Returns
    -------
    tv : ndarray, shape (M, M + 1)
        Vertical edges (``tv[j, i]``: left edge of pixel i), net area moved
        to the left pixel, i.e. positive when the edge moved towards +x.
    th : ndarray, shape (M + 1, M)
        Horizontal edges (bottom edge of pixel j), positive towards +y.
    """
    m = moves.shape[0]
    tv = np.zeros((m, m + 1))
    th = np.zeros((m + 1, m))

    def cross_x(j, i, sx, a):  # a moved from column i to i + sx in row j
        tv[j, i + (sx > 0)] -= sx * a

    def cross_y(j, i, sy, a):
        th[j + (sy > 0), i] -= sy * a

    for j in range(m):
        for i in range(m):
            for b in range(3):
                for a in range(3):
                    sx, sy, amt = a - 1, b - 1, moves[j, i, b, a]
                    if amt == 0.0 or (sx == 0 and sy == 0):
                        continue
                    if sy == 0:
                        cross_x(j, i, sx, amt)
                    elif sx == 0:
                        cross_y(j, i, sy, amt)
                    else:
                        cross_x(j, i, sx, 0.5 * amt)
                        cross_y(j, i + sx, sy, 0.5 * amt)
                        cross_y(j, i, sy, 0.5 * amt)
                        cross_x(j + sy, i, sx, 0.5 * amt)
    return tv, th


def galsim_effective_moves(name, *, template=None, engine="galsim", cells=2000, margin=2,
                           qdist=3, seed=20151, charge=None):
    """Where galsim.SiliconSensor sends the points of each nominal pixel.

    With ``charge`` e (default: the file's) in pixel (0, 0) and the boundaries
    frozen, points over the template's footprint plus ``margin`` pixels are
    assigned to pixels by GalSim's rule: nominal pixel first, then the
    neighbours, with per-edge (not tiling) corner copies; a point found in
    no pixel goes to the nominal pixel or the first neighbour tried with
    equal probability. Each pixel is cut into ``cells`` x ``cells`` cells;
    only the cells of a band along its boundary, 1.5 times as wide as the
    largest displacement of its polygon's vertices (plus two cells), get a
    point each (uniform in the cell: stratified sampling, so that an edge
    parallel to the cells leaves no systematic error; about ``cells**-1.5``
    px^2 of random error per edge); the interior, inside the polygon, is the
    nominal pixel's.

    Parameters
    ----------
    name : str
        GalSim sensor name.
    template : DistortionTemplate, optional
        The file's template (``read_galsim_sensor``); needed by
        ``engine='rules'``, read when None.
    engine : {'galsim', 'rules'}, optional
        'galsim': galsim.SiliconSensor itself (diffusion off, no boundary
        update during the accumulation, nine accumulations of pixels three
        apart). 'rules': the re-implementation
        :mod:`lsst_bfdrift.templates.galsim_rules` (same layout and rule, deterministic
        expectation of the random choice).
    cells : int, optional
        Sampling cells per pixel side.
    margin : int, optional
        Pixels sampled beyond the template's footprint on each side.
    qdist : int, optional
        GalSim's ``qdist`` (its default 3; must match the simulation).
    seed : int, optional
        Seed of the points within their cells and of GalSim's random choice
        for points found in no pixel.
    charge : float, optional
        Aggressor charge (e); default the file's (the template's).

    Returns
    -------
    moves : ndarray, shape (M, M, 3, 3), M = N + 2 margin
        ``moves[j, i, b, a]``: area (px^2) of nominal pixel (i - h, j - h)
        (h = M // 2) assigned to pixel (i - h + a - 1, j - h + b - 1).
    """
    if engine not in _ENGINES:
        raise InputError(f"engine must be one of {_ENGINES}, got {engine!r}")
    if int(cells) != cells or cells < 10:
        raise InputError(f"cells must be an integer >= 10, got {cells!r}")
    if int(margin) != margin or margin < 1:
        raise InputError(f"margin must be an integer >= 1, got {margin!r}")
    if template is None:
        template = read_galsim_sensor(name)
    half = template.center + int(margin)
    charge = template.charge if charge is None else float(charge)
    if not (np.isfinite(charge) and charge > 0):
        raise InputError(f"charge must be positive, got {charge!r}")
    if engine == "galsim":
        return _moves_galsim(name, template, half, int(cells), qdist, seed, charge)
    return _moves_rules(template, half, int(cells), qdist, seed, charge)


def match_galsim_transfers(template, name, *, engine="galsim", cells=2000, margin=2,
                           qdist=3, seed=20151, charge=None):
    """Adjust the edge samples so that every edge's swept area is GalSim's effective one.

    GalSim's pixels do not tile (per-edge corner copies), and a conversion is
    tested in its nominal pixel first, so the charge GalSim effectively moves
    across an edge is not what its polygons' areas imply. This measures the
    net area moved across every edge between nominal neighbours
    (:func:`galsim_effective_moves`, :func:`transfers_from_moves`) and shifts
    each edge's normal samples by the minimum-norm amount (corners and
    tangential displacements untouched) that makes the trapezoid integral of
    its normal displacement (:func:`edge_integrals`, the swept-area kernel of
    the corrections) equal to it. Pixel areas implied by the kernels then
    equal GalSim's effective areas, conservation included (every transfer
    leaves one pixel and enters its neighbour).

    Parameters
    ----------
    template : DistortionTemplate
        The file's template (``merge='nearest'``, :func:`read_galsim_sensor`).
    name : str
        GalSim sensor name.
    engine, cells, margin, qdist, seed
        See :func:`galsim_effective_moves`.
    charge : float, optional
        Aggressor charge (e) at which the transfers are measured, then
        scaled linearly to the template's charge; default the template's.
        GalSim's polygons move linearly with charge but the areas its rule
        moves near the non-tiling corners do not quite (second order).

    Returns
    -------
    DistortionTemplate
        Adjusted copy; ``meta['transfer_matched']`` records the options, the
        largest sample change (px) and the largest effective transfer found
        outside the template's footprint (px^2, dropped).
    """
    moves = galsim_effective_moves(name, template=template, engine=engine,
                                   cells=cells, margin=margin, qdist=qdist, seed=seed,
                                   charge=charge)
    tv, th = transfers_from_moves(moves)
    scale = 1.0 if charge is None else template.charge / float(charge)
    tv, th = tv * scale, th * scale
    n, mg = template.size, int(margin)
    kv_t = tv[mg:mg + n, mg:mg + n + 1]
    kh_t = th[mg:mg + n + 1, mg:mg + n]
    outside_v = tv.copy()
    outside_v[mg:mg + n, mg:mg + n + 1] = 0.0
    outside_h = th.copy()
    outside_h[mg:mg + n + 1, mg:mg + n] = 0.0
    kv0, kh0 = edge_integrals(template)
    w = _trapezoid_weights(template.fractions)
    unit = w / np.sum(w * w)  # minimum-norm sample shift per unit of integral
    vedge = template.vedge_d + (kv_t - kv0)[..., None] * unit
    hedge = template.hedge_d + (kh_t - kh0)[..., None] * unit
    meta = dict(template.meta)
    meta["transfer_matched"] = {
        "engine": engine, "cells": int(cells), "margin": int(margin),
        "qdist": int(qdist), "seed": int(seed),
        "charge": template.charge if charge is None else float(charge),
        "max_sample_change_px": float(max(np.abs(vedge - template.vedge_d).max(),
                                          np.abs(hedge - template.hedge_d).max())),
        "max_outside_transfer_px2": float(max(np.abs(outside_v).max(),
                                              np.abs(outside_h).max())),
    }
    return type(template)(template.corner_d, vedge, hedge, template.fractions,
                          template.charge, vedge_t=template.vedge_t, hedge_t=template.hedge_t,
                          meta=meta, pixel_table=template._pixel_table)
