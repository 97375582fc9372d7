"""Export of a template as GalSim sensor files (the ``.cfg`` / ``.dat`` pair).

:func:`export_galsim_sensor` writes the files that
``galsim.SiliconSensor(name=PREFIX)`` reads, so that a sensor calibrated
here can be simulated in GalSim and imSim. The format is the one
:mod:`~lsst_bfdrift.templates.galsim_io` reads (Poisson_CCD's output):

``PREFIX.dat``
    A header line ``X0 Y0 Theta X Y`` and, for each pixel of the N x N stamp
    (x index slowest), its 4 n + 4 vertices (4 corners and n per edge at
    GalSim's tan-spaced fractions (tan(theta_k) + 1) / 2, theta_k = -pi/4 +
    (k + 1) pi / (2 (n + 1))) sorted by polar angle about the pixel centre;
    X0, Y0 is the pixel centre and X, Y the vertex (um), Theta the vertex's
    polar angle (rad, 0 to 2 pi). The stamp's lower-left corner is at
    (10, 10) um, as in GalSim's own files.
``PREFIX.cfg``
    ``key = value`` lines. Written from the template: ``NumVertices`` (n),
    ``PixelBoundaryNx``/``Ny`` (N), ``PixelSizeX``/``Y`` and
    ``SensorThickness`` (um, from the template's sensor parameters when it
    has them), ``CollectedCharge_0_0`` (the template's aggressor charge, e),
    ``FilledPixelCoords_0_0`` (the aggressor's centre, um),
    ``PixelBoundaryLowerLeft``/``UpperRight``. GalSim also reads the keys of
    its diffusion step (``NumPhases``, ``CollectingPhases``,
    ``ChannelStopWidth``, ``FieldOxideTaper``, ``Vbb``, ``Vparallel_lo``,
    ``Vparallel_hi``, ``qfh``, ``CCDTemperature``): they are copied from a
    GalSim sensor configuration (``diffusion_from``, default lsst_itl_50_8's)
    with ``Vbb`` the template's backside bias when known. They set GalSim's
    diffusion, not the distortions.

Edges whose samples sit at other fractions than GalSim's are interpolated
linearly along the edge (corners included), normal and tangential
displacements alike.
"""

import math
import os

import numpy as np

from lsst_bfdrift.templates.galsim_io import (galsim_nominal_vertices, galsim_sensor_files,
                                              read_galsim_config)
from lsst_bfdrift.templates.template import DistortionTemplate
from lsst_bfdrift.utils.io import atomic_output, check_output
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["export_galsim_sensor", "DIFFUSION_KEYS"]

#: Keys of GalSim's diffusion step, copied from ``diffusion_from``.
DIFFUSION_KEYS = ("NumPhases", "CollectingPhases", "ChannelStopWidth", "FieldOxideTaper", "Vbb",
                  "Vparallel_lo", "Vparallel_hi", "qfh", "CCDTemperature")

_LOWER_LEFT = 10.0  # um, as in GalSim's files


def _edge_at(values, fr_from, fr_to, start, end):
    """Samples at ``fr_to`` of an edge known at ``fr_from`` and its ends."""
    x = np.concatenate([[0.0], fr_from, [1.0]])
    y = np.concatenate([[start], values, [end]])
    return np.interp(fr_to, x, y)


def export_galsim_sensor(template, prefix, *, num_vertices=None, pixel_size=None,
                         thickness=None, diffusion_from="lsst_itl_50_8", overwrite=False):
    """Write ``template`` as GalSim sensor files ``prefix.cfg`` and ``prefix.dat``.

    Parameters
    ----------
    template : DistortionTemplate
        The template (e.g. from ``bfdrift calibrate``).
    prefix : str or os.PathLike
        Path without extension; ``galsim.SiliconSensor(name=prefix)`` reads it.
    num_vertices : int, optional
        Vertices per edge (GalSim's ``NumVertices``); default the template's
        edge samples.
    pixel_size, thickness : float, optional
        Pixel pitch and silicon thickness (um); default the template's sensor
        parameters, else 10 and 100.
    diffusion_from : str, optional
        GalSim sensor whose diffusion keys are copied (module docstring).
    overwrite : bool, optional
        Replace existing files; otherwise an existing one is an error.

    Returns
    -------
    (str, str)
        Paths of the ``.cfg`` and ``.dat`` files.

    Raises
    ------
    TypeError
        ``template`` is not a DistortionTemplate.
    FileExistsError
        A file exists and ``overwrite`` is False (nothing is written).
    ValueError
        ``num_vertices`` below 1.
    """
    if not isinstance(template, DistortionTemplate):
        raise InputTypeError("template must be a DistortionTemplate, "
                             f"got {type(template).__name__}")
    prefix = os.fspath(prefix)
    cfg_path, dat_path = prefix + ".cfg", prefix + ".dat"
    for path in (cfg_path, dat_path):
        check_output(path, overwrite=overwrite)
    nv = template.edge_samples if num_vertices is None else int(num_vertices)
    if nv < 1:
        raise InputError(f"num_vertices must be >= 1, got {num_vertices!r}")
    params = template.meta.get("params") or {}
    pitch = float(pixel_size if pixel_size is not None else params.get("pixel_pitch", 10.0))
    thick = float(thickness if thickness is not None else params.get("thickness", 100.0))
    base = read_galsim_config(galsim_sensor_files(diffusion_from)[0])
    diffusion = {k: base[k] for k in DIFFUSION_KEYS}
    if "v_bss" in params:
        diffusion["Vbb"] = float(params["v_bss"])
    n, c = template.size, template.center
    xs, ys, kinds, fr = galsim_nominal_vertices(nv)
    tfr = template.fractions
    rows = {(int(r["di"]), int(r["dj"]), str(r["edge"]).strip()): r
            for r in template.to_table()}
    lines = ["X0             Y0             Theta          X              Y"]
    for ix in range(n):  # x index slowest, as GalSim reads
        for iy in range(n):
            key = (ix - c, iy - c)
            L, T, R, B = (rows[key + (e,)] for e in ("left", "top", "right", "bottom"))
            corners = {(0.0, 0.0): (L["c0x"], L["c0y"]), (0.0, 1.0): (L["c1x"], L["c1y"]),
                       (1.0, 1.0): (T["c1x"], T["c1y"]), (1.0, 0.0): (R["c0x"], R["c0y"])}
            edge = {}
            for name, row, c0, c1, normal_is_x in (
                    ("left", L, (0.0, 0.0), (0.0, 1.0), True),
                    ("right", R, (1.0, 0.0), (1.0, 1.0), True),
                    ("bottom", B, (0.0, 0.0), (1.0, 0.0), False),
                    ("top", T, (0.0, 1.0), (1.0, 1.0), False)):
                # normal and tangential displacement along the edge, corners at its ends
                n0, n1 = (corners[c0][0], corners[c1][0]) if normal_is_x else \
                    (corners[c0][1], corners[c1][1])
                t0, t1 = (corners[c0][1], corners[c1][1]) if normal_is_x else \
                    (corners[c0][0], corners[c1][0])
                edge[name] = (_edge_at(np.asarray(row["normal"], float), tfr, fr, n0, n1),
                              _edge_at(np.asarray(row["tangent"], float), tfr, fr, t0, t1))
            x0 = _LOWER_LEFT + (ix + 0.5) * pitch
            y0 = _LOWER_LEFT + (iy + 0.5) * pitch
            count = {"left": 0, "right": 0, "bottom": 0, "top": 0}
            for xn, yn, kind in zip(xs, ys, kinds):
                if kind == "corner":
                    dx, dy = corners[(float(xn), float(yn))]
                else:
                    k = int(np.argmin(np.abs(fr - (yn if kind in ("left", "right") else xn))))
                    count[kind] += 1
                    nrm, tan = edge[kind][0][k], edge[kind][1][k]
                    dx, dy = (nrm, tan) if kind in ("left", "right") else (tan, nrm)
                vx = x0 + (xn - 0.5 + dx) * pitch
                vy = y0 + (yn - 0.5 + dy) * pitch
                theta = math.atan2(vy - y0, vx - x0) % (2 * math.pi)
                lines.append(f"{x0:.6f} {y0:.6f} {theta:.8f} {vx:.10f} {vy:.10f}")
    upper = _LOWER_LEFT + n * pitch
    cfg = {"NumVertices": nv, "PixelBoundaryNx": n, "PixelBoundaryNy": n,
           "PixelSizeX": pitch, "PixelSizeY": pitch, "SensorThickness": thick,
           "CollectedCharge_0_0": template.charge,
           "FilledPixelCoords_0_0": f"{_LOWER_LEFT + (c + 0.5) * pitch} "
                                    f"{_LOWER_LEFT + (c + 0.5) * pitch}",
           "PixelBoundaryLowerLeft": f"{_LOWER_LEFT} {_LOWER_LEFT}",
           "PixelBoundaryUpperRight": f"{upper} {upper}", **diffusion}
    cfg_lines = ["# GalSim sensor configuration written by lsst_bfdrift "
                 "(templates.galsim_export.export_galsim_sensor)",
                 f"# source: {template.meta.get('source', 'template')}; diffusion keys from "
                 f"{diffusion_from}"]
    cfg_lines += [f"{k} = {v}" for k, v in cfg.items()]
    with atomic_output(dat_path, overwrite=True) as tmp_dat, \
            atomic_output(cfg_path, overwrite=True) as tmp_cfg:
        with open(tmp_dat, "w") as fh:
            fh.write("\n".join(lines) + "\n")
        with open(tmp_cfg, "w") as fh:
            fh.write("\n".join(cfg_lines) + "\n")
    return cfg_path, dat_path
