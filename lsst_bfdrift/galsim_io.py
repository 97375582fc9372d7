"""Import of GalSim's sensor distortion files into
:class:`~lsst_bfdrift.template.DistortionTemplate`.

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

import numpy as np
from astropy.table import Table

__all__ = ["galsim_sensor_files", "read_galsim_config", "galsim_nominal_vertices",
           "galsim_vertex_table", "read_galsim_sensor", "match_galsim_areas"]


def galsim_sensor_files(name):
    """Paths (cfg, dat) of a GalSim sensor, by name or path prefix."""
    cfg, dat = name + ".cfg", name + ".dat"
    if not os.path.isfile(cfg):
        import galsim
        base = os.path.join(galsim.meta_data.share_dir, "sensors", name)
        cfg, dat = base + ".cfg", base + ".dat"
    for path in (cfg, dat):
        if not os.path.isfile(path):
            raise FileNotFoundError(f"GalSim sensor file {path} not found")
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
                raise ValueError(f"{path}:{lineno}: expected 'key = value', got {line!r}")
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
        raise ValueError(f"{cfg}: missing configuration key {exc}") from exc
    data = np.loadtxt(dat, skiprows=1)
    npv = 4 * nv + 4
    if data.shape != (nx * ny * npv, 5):
        raise ValueError(f"{dat} has shape {data.shape}, config {cfg} implies "
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


def read_galsim_sensor(cls, name):
    """Build a :class:`~lsst_bfdrift.template.DistortionTemplate` from a GalSim file."""
    raw, config = galsim_vertex_table(name)
    nv = int(config["NumVertices"])
    nx, ny = int(config["PixelBoundaryNx"]), int(config["PixelBoundaryNy"])
    if nx != ny or nx % 2 != 1:
        raise ValueError(f"GalSim sensor stamp must be square and odd, got {nx} x {ny}")
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
    meta = {"source": f"galsim:{name}", "merge": "nearest", "galsim_config": {k: v for k, v in config.items()
                                                          if isinstance(v, (int, float, str))}}
    return cls.from_table(table, fr, charge, meta=meta, merge="nearest")


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
    import galsim

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
