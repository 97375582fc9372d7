"""Portable pixel-distortion templates (Rasmussen 2015, section 3 item 5).

A template is the boundary distortion of an N x N neighbourhood of pixels
around one aggressor pixel holding charge Q, stored as the paper says: for
every pixel and each of its four edges, the 2-d displacements of the edge's
two corners and an array of displacements sampled along the nominal edge.
Within the package the shared form is used (each corner and edge stored once,
so that superposed pixels tile the plane exactly).

Displacements are in pixel units; the aggressor is pixel (0, 0) of the
neighbourhood, offsets (di, dj) = (serial, parallel) run from -c to c with
c = N // 2. Array layouts follow :class:`~lsst_bfdrift.physics.boundaries.BoundaryGrid`
with ``i0 = j0 = -c``.
"""

import dataclasses
import hashlib
import json
import os
import warnings
from dataclasses import dataclass

import numpy as np
from astropy.io import fits
from astropy.table import Table

from lsst_bfdrift.physics.boundaries import BoundaryGrid, centred_boundaries
from lsst_bfdrift.physics.polygons import pixel_polygons, polygon_moments
from lsst_bfdrift.templates.template_io import (band_key, check_template_table,
                                                read_template_fits, template_file_bands)
from lsst_bfdrift.utils.io import atomic_output, check_output, data_path
from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.physics.sensor import SensorModel, SensorParameters, strict_from_dict
from lsst_bfdrift.utils.errors import (InputError, InputTypeError,
                                       TemplateFileError)

__all__ = ["TEMPLATE_SCHEMA_VERSION", "TemplateSettings", "DistortionTemplate",
           "TemplateFileError", "build_template", "window_leak", "default_template_path",
           "load_default_template"]

#: Version of the FITS layout written by :meth:`DistortionTemplate.save`.
TEMPLATE_SCHEMA_VERSION = 1

_EDGES = ("left", "top", "right", "bottom")


@dataclass(frozen=True)
class TemplateSettings:
    """How a template is computed from a sensor model.

    Parameters
    ----------
    size : int
        Side N of the neighbourhood (odd), default 21.
    aggressor_charge : float
        Charge Q of the aggressor pixel (e); default 1e4 (paper: p00 = -p0 k).
    edge_samples : int
        Samples per edge, uniformly spaced; default 32 (8 leave about 15 % of
        A10's change, see ``docs/calibration.rst``).
    tol : float
        Bisection tolerance (pixel units), default 1e-5: coarser tolerances
        lose the area change of the far pixels in the boundary noise (1e-4
        loses about 20 % of the aggressor's area change outside a 21 x 21
        window, 1e-5 about 3 %, :func:`window_leak`).
    conversion_height : float or None
        Height of the conversions (um); None: the entrance window.
    baseline : {'nominal', 'computed'}
        Displacements relative to square pixels ('nominal', exact for models
        symmetric about the pixel axes) or to the boundaries computed without
        the aggressor ('computed', for models with fixed-pattern features).
    step_scale, min_step, max_step : float
        Drift step control (see :mod:`lsst_bfdrift.physics.drift`).
    spacing : {'uniform', 'tan'}
        Placement of the edge samples; 'tan' (denser towards the corners)
        converges with fewer samples (see ``docs/templates.rst``).
    workers : int
        Processes sharing the drift lines with the numpy engine (forked; 1
        runs in-process). The compiled engine, used whenever the model allows,
        runs in-process on all cores and ignores it.
    """

    size: int = 21
    aggressor_charge: float = 1e4
    edge_samples: int = 32
    tol: float = 1e-5
    conversion_height: float = None
    baseline: str = "nominal"
    step_scale: float = 0.15
    min_step: float = 0.02
    max_step: float = 4.0
    workers: int = 2
    spacing: str = "uniform"

    def __post_init__(self):
        for name in ("size", "edge_samples", "workers"):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 1:
                raise InputError(f"template setting {name!r} must be a positive integer, "
                                 f"got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.size % 2 != 1:
            raise InputError(f"template setting 'size' must be odd, got {self.size}")
        for name in ("aggressor_charge", "tol", "step_scale", "min_step", "max_step"):
            v = float(getattr(self, name))
            if not np.isfinite(v):
                raise InputError(f"template setting {name!r} must be finite, got {v!r}")
            object.__setattr__(self, name, v)
        if self.aggressor_charge == 0:
            raise InputError("template setting 'aggressor_charge' must be non-zero")
        if not 0 < self.tol < 0.1:
            raise InputError(f"template setting 'tol' must be in (0, 0.1) px, got {self.tol}")
        if self.spacing not in ("uniform", "tan"):
            raise InputError(f"template setting 'spacing' must be 'uniform' or 'tan', "
                             f"got {self.spacing!r}")
        if self.baseline not in ("nominal", "computed"):
            raise InputError(f"template setting 'baseline' must be 'nominal' or 'computed', "
                             f"got {self.baseline!r}")
        if not 0 < self.min_step <= self.max_step:
            raise InputError("template settings need 0 < min_step <= max_step")

    @classmethod
    def from_dict(cls, mapping):
        """Build from a mapping, rejecting unknown keys by name."""
        return strict_from_dict(cls, mapping, "template setting")

    def to_dict(self):
        """Plain dictionary."""
        return dataclasses.asdict(self)

    def drift_kwargs(self):
        """Keyword arguments for :func:`~lsst_bfdrift.physics.drift.drift_lines`."""
        return dict(step_scale=self.step_scale, min_step=self.min_step, max_step=self.max_step)


class DistortionTemplate:
    """Boundary displacements of a neighbourhood around one aggressor pixel.

    Parameters
    ----------
    corner_d : ndarray, shape (N + 1, N + 1, 2)
        Corner displacements (dx, dy), pixel units.
    vedge_d : ndarray, shape (N, N + 1, ns)
        x displacements of the column-boundary samples.
    hedge_d : ndarray, shape (N + 1, N, ns)
        y displacements of the row-boundary samples.
    fractions : ndarray, shape (ns,)
        Sample positions along each edge (fractions of the edge from its lower
        or left corner).
    charge : float
        Aggressor charge Q (e) that produced the displacements.
    vedge_t, hedge_t : ndarray, optional
        Tangential displacements of the samples (y of vertical, x of
        horizontal); None means zero (bisection along the normal).
    meta : dict, optional
        Provenance: model parameters, settings, source.
    pixel_table : astropy.table.Table, optional
        The per-pixel, per-edge form when it is not exactly the shared one
        (e.g. GalSim's files, whose neighbouring pixels disagree slightly on
        their common edges); kept verbatim by :meth:`to_table` and used by
        ``polygons(per_pixel=True)``.
    """

    def __init__(self, corner_d, vedge_d, hedge_d, fractions, charge, *, vedge_t=None,
                 hedge_t=None, meta=None, pixel_table=None):
        self.corner_d = np.asarray(corner_d, dtype=float)
        self.vedge_d = np.asarray(vedge_d, dtype=float)
        self.hedge_d = np.asarray(hedge_d, dtype=float)
        self.fractions = np.asarray(fractions, dtype=float)
        self.charge = float(charge)
        self.vedge_t = None if vedge_t is None else np.asarray(vedge_t, dtype=float)
        self.hedge_t = None if hedge_t is None else np.asarray(hedge_t, dtype=float)
        self.meta = dict(meta or {})
        self._pixel_table = None if pixel_table is None else Table(pixel_table, copy=True)
        self._check()

    def _check(self):
        n = self.vedge_d.shape[0]
        ns = self.fractions.size
        expect = {"corner_d": (n + 1, n + 1, 2), "vedge_d": (n, n + 1, ns),
                  "hedge_d": (n + 1, n, ns)}
        if self.vedge_t is not None:
            expect["vedge_t"] = (n, n + 1, ns)
        if self.hedge_t is not None:
            expect["hedge_t"] = (n + 1, n, ns)
        for name, shape in expect.items():
            arr = getattr(self, name)
            if arr.shape != shape:
                raise InputError(f"template array {name} has shape {arr.shape}, expected {shape}")
            if not np.all(np.isfinite(arr)):
                raise InputError(f"template array {name} contains non-finite values")
        if n % 2 != 1:
            raise InputError(f"template size must be odd, got {n}")
        if not (np.all(np.diff(self.fractions) > 0) and self.fractions[0] > 0
                and self.fractions[-1] < 1):
            raise InputError("template edge fractions must increase strictly inside (0, 1)")
        if not np.isfinite(self.charge) or self.charge == 0:
            raise InputError(f"template charge must be finite and non-zero, got {self.charge}")

    # -- basic properties -------------------------------------------------
    @property
    def size(self):
        """Side N of the neighbourhood."""
        return self.vedge_d.shape[0]

    @property
    def center(self):
        """Index c of the aggressor in the arrays (offsets run -c..c)."""
        return self.size // 2

    @property
    def edge_samples(self):
        """Number of samples per edge."""
        return self.fractions.size

    def scaled(self, factor):
        """Template for ``factor`` times the charge (same displacements per e)."""
        f = float(factor)
        t = None if self.vedge_t is None else self.vedge_t * f
        h = None if self.hedge_t is None else self.hedge_t * f
        return DistortionTemplate(self.corner_d * f, self.vedge_d * f, self.hedge_d * f,
                                  self.fractions, self.charge * f, vedge_t=t, hedge_t=h,
                                  meta=self.meta, pixel_table=None)

    def cropped(self, size):
        """The template restricted to the central ``size`` x ``size`` pixels.

        The boundaries of those pixels are kept as they are; those outside
        no longer move. What the crop drops is what a window of that size
        cannot describe: for example GalSim's sensor files, which stop about
        4 px from the aggressor (``size=9``), against this model's far field.

        Parameters
        ----------
        size : int
            Odd side (px) of the neighbourhood kept, at most :attr:`size`.

        Returns
        -------
        DistortionTemplate
            Same charge (e), samples and provenance (``meta['cropped_from']``
            records the original side).
        """
        m = int(size)
        if m != size or m < 1 or m % 2 != 1 or m > self.size:
            raise InputError(f"crop size must be an odd number of pixels from 1 to "
                             f"{self.size}, got {size!r}")
        lo = self.center - m // 2
        px, edge = slice(lo, lo + m), slice(lo, lo + m + 1)

        def cut(arr, rows, cols):
            return None if arr is None else arr[rows, cols].copy()

        meta = dict(self.meta, cropped_from=self.size)
        return DistortionTemplate(cut(self.corner_d, edge, edge), cut(self.vedge_d, px, edge),
                                  cut(self.hedge_d, edge, px), self.fractions, self.charge,
                                  vedge_t=cut(self.vedge_t, px, edge),
                                  hedge_t=cut(self.hedge_t, edge, px), meta=meta)

    def boundary_grid(self, charge=None):
        """Absolute boundaries of the neighbourhood with aggressor ``charge`` (e).

        Default: the template's own charge. Displacements scale linearly.
        """
        f = 1.0 if charge is None else float(charge) / self.charge
        c = self.center
        nominal = BoundaryGrid(-c, -c, np.zeros(self.corner_d.shape), self.vedge_d,
                               self.hedge_d, self.fractions).nominal()
        grid = BoundaryGrid(-c, -c, nominal.corners + f * self.corner_d,
                            nominal.vedge + f * self.vedge_d, nominal.hedge + f * self.hedge_d,
                            self.fractions)
        grid.vedge_t = None if self.vedge_t is None else f * self.vedge_t
        grid.hedge_t = None if self.hedge_t is None else f * self.hedge_t
        return grid

    def polygons(self, charge=None, *, per_pixel=False):
        """Clockwise pixel polygons (x, y), shape (N, N, 4 + 4 ns).

        With ``per_pixel=True`` each pixel is built from its own rows of the
        per-pixel table (as GalSim does), otherwise from the shared boundaries.
        """
        if per_pixel:
            return self._per_pixel_polygons(charge)
        g = self.boundary_grid(charge)
        return pixel_polygons(g.corners, g.vedge, g.hedge, g.fractions, i0=g.i0, j0=g.j0,
                              vedge_t=g.vedge_t, hedge_t=g.hedge_t)

    def _per_pixel_polygons(self, charge=None):
        f = 1.0 if charge is None else float(charge) / self.charge
        t = self.to_table()
        n, c, ns = self.size, self.center, self.edge_samples
        fr = self.fractions
        x = np.zeros((n, n, 4 + 4 * ns))
        y = np.zeros((n, n, 4 + 4 * ns))
        rows = {(int(r["di"]), int(r["dj"]), str(r["edge"]).strip()): r for r in t}
        for J in range(n):
            for I in range(n):
                key = (I - c, J - c)
                L, T, R, B = (rows[key + (e,)] for e in _EDGES)
                xs = [[-0.5 + f * L["c0x"]], -0.5 + f * L["normal"], [-0.5 + f * L["c1x"]],
                      -0.5 + fr + f * T["tangent"], [0.5 + f * T["c1x"]],
                      (0.5 + f * R["normal"])[::-1], [0.5 + f * R["c0x"]],
                      (-0.5 + fr + f * B["tangent"])[::-1]]
                ys = [[-0.5 + f * L["c0y"]], -0.5 + fr + f * L["tangent"], [0.5 + f * L["c1y"]],
                      0.5 + f * T["normal"], [0.5 + f * T["c1y"]],
                      (-0.5 + fr + f * R["tangent"])[::-1], [-0.5 + f * R["c0y"]],
                      (-0.5 + f * B["normal"])[::-1]]
                x[J, I] = np.concatenate(xs) + key[0]
                y[J, I] = np.concatenate(ys) + key[1]
        return x, y

    def moments(self, charge=None, *, per_pixel=False):
        """:class:`~lsst_bfdrift.physics.polygons.PolygonMoments` of the N x N pixels."""
        x, y = self.polygons(charge, per_pixel=per_pixel)
        c = self.center
        jj, ii = np.mgrid[-c:c + 1, -c:c + 1]
        return polygon_moments(x, y, origin=(ii, jj))

    def area(self, di, dj, charge=None):
        """Area (px^2) of the pixel at offset (di, dj) = (serial, parallel)."""
        c = self.center
        if abs(di) > c or abs(dj) > c:
            raise IndexError(f"offset ({di}, {dj}) outside the {self.size}x{self.size} template")
        return float(self.moments(charge).area[dj + c, di + c])

    def summary(self):
        """Key numbers of the template (areas in px^2, see the CLI docs)."""
        m = self.moments()
        c = self.center
        a = m.area
        a01, a10 = a[c + 1, c], a[c, c + 1]
        ratio = np.log(a01) / np.log(a10) if a10 != 1.0 else float("nan")
        return {
            "A00": float(a[c, c]), "A01": float(a01), "A10": float(a10),
            "A11": float(a[c + 1, c + 1]),
            "ratio_01_10": float(ratio),
            "dlnA00_per_e": float(np.log(a[c, c]) / self.charge),
            "area_sum_error": float(a.sum() - self.size**2),
            "window_leak": window_leak(self),
            "aggressor_charge": self.charge,
            "size": self.size,
            "edge_samples": self.edge_samples,
            "schema_version": TEMPLATE_SCHEMA_VERSION,
            "source": self.meta.get("source", "unknown"),
        }

    # -- per-pixel, per-edge table (the paper's portable form) -------------
    def to_table(self):
        """Per pixel and edge: corner displacements and sampled displacements.

        Columns: ``di, dj`` (offset of the pixel), ``edge`` (left, top, right,
        bottom), ``c0x, c0y, c1x, c1y`` (displacements of the edge's first and
        last corner, in order of increasing coordinate along the edge),
        ``normal`` (displacement along +x for left/right edges, +y for
        top/bottom, at the sample fractions) and ``tangent`` (along the edge).
        """
        if self._pixel_table is not None:
            return Table(self._pixel_table, copy=True)
        n, c, ns = self.size, self.center, self.edge_samples
        vt = np.zeros(self.vedge_d.shape) if self.vedge_t is None else self.vedge_t
        ht = np.zeros(self.hedge_d.shape) if self.hedge_t is None else self.hedge_t
        cd = self.corner_d
        rows = {k: [] for k in ("di", "dj", "edge", "c0x", "c0y", "c1x", "c1y", "normal",
                                "tangent")}
        for J in range(n):
            for I in range(n):
                edges = {
                    "left": (cd[J, I], cd[J + 1, I], self.vedge_d[J, I], vt[J, I]),
                    "top": (cd[J + 1, I], cd[J + 1, I + 1], self.hedge_d[J + 1, I], ht[J + 1, I]),
                    "right": (cd[J, I + 1], cd[J + 1, I + 1], self.vedge_d[J, I + 1],
                              vt[J, I + 1]),
                    "bottom": (cd[J, I], cd[J, I + 1], self.hedge_d[J, I], ht[J, I]),
                }
                for name in _EDGES:
                    c0, c1, nrm, tan = edges[name]
                    rows["di"].append(I - c)
                    rows["dj"].append(J - c)
                    rows["edge"].append(name)
                    rows["c0x"].append(c0[0])
                    rows["c0y"].append(c0[1])
                    rows["c1x"].append(c1[0])
                    rows["c1y"].append(c1[1])
                    rows["normal"].append(np.array(nrm))
                    rows["tangent"].append(np.array(tan))
        t = Table()
        t["di"] = np.array(rows["di"], dtype=np.int32)
        t["dj"] = np.array(rows["dj"], dtype=np.int32)
        t["edge"] = np.array(rows["edge"], dtype="U6")
        for k in ("c0x", "c0y", "c1x", "c1y"):
            t[k] = np.array(rows[k], dtype=float)
            t[k].unit = "pix"
        t["normal"] = np.array(rows["normal"], dtype=float).reshape(-1, ns)
        t["tangent"] = np.array(rows["tangent"], dtype=float).reshape(-1, ns)
        t["normal"].unit = t["tangent"].unit = "pix"
        return t

    @classmethod
    def from_table(cls, table, fractions, charge, *, meta=None, max_mismatch=None,
                   merge="mean"):
        """Assemble the shared form from a per-pixel, per-edge table.

        Each corner and edge is seen by several pixels. ``merge='mean'``
        averages their values; ``merge='nearest'`` takes each edge from the
        pixel nearer the aggressor along the edge normal (GalSim's rule) and
        each corner from the pixel(s) nearest the aggressor (Chebyshev
        distance). With GalSim's files this reproduces GalSim's central pixel
        area exactly; GalSim keeps separate corner copies per edge, so its
        neighbours' areas differ from any tiling by up to ~2e-3 px^2 at 1e5 e.
        ``meta['shared_mismatch']`` records the largest difference between
        pixels; if ``max_mismatch`` is given and exceeded,
        :class:`TemplateFileError`.
        """
        if merge not in ("mean", "nearest"):
            raise InputError(f"merge must be 'mean' or 'nearest', got {merge!r}")
        di = np.asarray(table["di"], dtype=int)
        dj = np.asarray(table["dj"], dtype=int)
        c = int(max(np.abs(di).max(), np.abs(dj).max()))
        n = 2 * c + 1
        if len(table) != 4 * n * n:
            raise TemplateFileError(f"template table has {len(table)} rows, expected "
                                    f"{4 * n * n} for a {n}x{n} neighbourhood")
        ns = np.asarray(fractions).size
        seen = {"corner": [[[] for _ in range(n + 1)] for _ in range(n + 1)]}
        edge_vals = {}
        normal = np.asarray(table["normal"], dtype=float).reshape(len(table), -1)
        tangent = np.asarray(table["tangent"], dtype=float).reshape(len(table), -1)
        if normal.shape[1] != ns:
            raise TemplateFileError(f"template table has {normal.shape[1]} samples per edge, "
                                    f"header says {ns}")
        for k in range(len(table)):
            I, J = di[k] + c, dj[k] + c
            name = str(table["edge"][k]).strip()
            if name == "left":
                kind, idx, ca, cb = "v", (J, I), (J, I), (J + 1, I)
            elif name == "right":
                kind, idx, ca, cb = "v", (J, I + 1), (J, I + 1), (J + 1, I + 1)
            elif name == "top":
                kind, idx, ca, cb = "h", (J + 1, I), (J + 1, I), (J + 1, I + 1)
            elif name == "bottom":
                kind, idx, ca, cb = "h", (J, I), (J, I), (J, I + 1)
            else:
                raise TemplateFileError(f"unknown edge name {name!r} in template table")
            dist = abs(di[k]) if kind == "v" else abs(dj[k])
            for corner, (vx, vy) in ((ca, (table["c0x"][k], table["c0y"][k])),
                                     (cb, (table["c1x"][k], table["c1y"][k]))):
                seen["corner"][corner[0]][corner[1]].append(
                    (float(vx), float(vy), max(abs(di[k]), abs(dj[k]))))
            edge_vals.setdefault((kind,) + idx, []).append((normal[k], tangent[k], dist))
        mismatch = 0.0
        corner_d = np.zeros((n + 1, n + 1, 2))
        for a in range(n + 1):
            for b in range(n + 1):
                vals = np.array(seen["corner"][a][b])
                mismatch = max(mismatch, float(np.ptp(vals[:, :2], axis=0).max()))
                if merge == "nearest":
                    vals = vals[vals[:, 2] == vals[:, 2].min()]
                # equal values are taken as they are: a mean of 3 or 5 equal numbers
                # can round away from them (and the file's SHA-256 would not match)
                corner_d[a, b] = vals[0, :2] if not np.ptp(vals[:, :2], axis=0).any() \
                    else vals[:, :2].mean(axis=0)
        vedge = np.zeros((n, n + 1, ns))
        hedge = np.zeros((n + 1, n, ns))
        vt = np.zeros(vedge.shape)
        ht = np.zeros(hedge.shape)
        for (kind, a, b), vals in edge_vals.items():
            nv = np.array([v[0] for v in vals])
            tv = np.array([v[1] for v in vals])
            mismatch = max(mismatch, float(np.ptp(nv, axis=0).max()),
                           float(np.ptp(tv, axis=0).max()))
            if merge == "nearest":
                dist = np.array([v[2] for v in vals])
                near = dist == dist.min()
                nv, tv = nv[near], tv[near]
            nm = nv[0] if not np.ptp(nv, axis=0).any() else nv.mean(axis=0)
            tm = tv[0] if not np.ptp(tv, axis=0).any() else tv.mean(axis=0)
            if kind == "v":
                vedge[a, b], vt[a, b] = nm, tm
            else:
                hedge[a, b], ht[a, b] = nm, tm
        if max_mismatch is not None and mismatch > max_mismatch:
            raise TemplateFileError(
                f"template table is inconsistent: shared corners/edges differ by up to "
                f"{mismatch:.3g} px between neighbouring pixels (allowed {max_mismatch:.3g})")
        meta = dict(meta or {})
        meta["shared_mismatch"] = mismatch
        has_t = np.any(vt != 0) or np.any(ht != 0)
        keep = Table(table)[["di", "dj", "edge", "c0x", "c0y", "c1x", "c1y", "normal",
                             "tangent"]] if mismatch > 0 else None
        return cls(corner_d, vedge, hedge, fractions, charge,
                   vedge_t=vt if has_t else None, hedge_t=ht if has_t else None, meta=meta,
                   pixel_table=keep)

    # -- FITS I/O ------------------------------------------------------------
    def _digest(self):
        """SHA-256 of the per-pixel table (the stored form) and the charge."""
        t = self.to_table()
        h = hashlib.sha256()
        for name in ("di", "dj", "c0x", "c0y", "c1x", "c1y", "normal", "tangent"):
            h.update(np.ascontiguousarray(t[name], dtype="<f8").tobytes())
        h.update("".join(str(e).strip() for e in t["edge"]).encode())
        h.update(np.ascontiguousarray(self.fractions, dtype="<f8").tobytes())
        h.update(repr(float(self.charge)).encode())
        if self._pixel_table is not None:
            for arr in self._shared_arrays().values():
                h.update(np.ascontiguousarray(arr, dtype="<f8").tobytes())
        return h.hexdigest()

    def _shared_arrays(self):
        out = {"CORNER_D": self.corner_d, "VEDGE_D": self.vedge_d, "HEDGE_D": self.hedge_d}
        if self.vedge_t is not None:
            out.update(VEDGE_T=self.vedge_t, HEDGE_T=self.hedge_t)
        return out

    def to_hdus(self, *, suffix="", meta_here=False):
        """The FITS extensions of this template: its table and, if needed, the shared form.

        ``suffix`` is appended to the extension names (``TEMPLATE_R`` in a
        multi-band file); with ``meta_here`` the metadata JSON (``BFMETA``) is
        written in the table's header instead of the primary's.
        """
        hdu = fits.BinTableHDU(self.to_table(), name="TEMPLATE" + suffix)
        hdr = hdu.header
        hdr["BFSCHEMA"] = (TEMPLATE_SCHEMA_VERSION, "lsst_bfdrift template schema version")
        hdr["BFQAGG"] = (self.charge, "aggressor charge (e)")
        hdr["BFSIZE"] = (self.size, "neighbourhood side N")
        hdr["BFNSAMP"] = (self.edge_samples, "samples per edge")
        hdr["BFSHARED"] = (self._pixel_table is None,
                           "shared corners/edges identical between pixels")
        hdr["BFHASH"] = self._digest()
        for k, f in enumerate(self.fractions):
            hdr[f"BFFRAC{k}"] = (float(f), f"sample {k} fraction along edge")
        if meta_here:
            _set_meta(hdr, self.meta)
        hdus = [hdu]
        if self._pixel_table is not None:
            # the shared form is not derivable from a per-pixel table that
            # disagrees between neighbours (GalSim files): store it as well
            for name, arr in self._shared_arrays().items():
                hdus.append(fits.ImageHDU(np.asarray(arr, dtype=np.float64), name=name + suffix))
        return hdus

    def save(self, path, *, overwrite=False):
        """Write the template to a FITS file, atomically.

        HDU 1 (``TEMPLATE``) is the per-pixel, per-edge table; its header holds
        the schema version, aggressor charge, sample fractions, a SHA-256 of
        the arrays, and the model parameters and settings as JSON. FITS
        CHECKSUM/DATASUM cards are written on every HDU. (Several bands in
        one file: :class:`~lsst_bfdrift.templates.bands.MultiBandTemplate`.)
        """
        path = os.fspath(path)
        check_output(path, overwrite=overwrite)
        primary = fits.PrimaryHDU()
        primary.header["ORIGIN"] = "lsst_bfdrift"
        primary.header["BFSCHEMA"] = TEMPLATE_SCHEMA_VERSION
        _set_meta(primary.header, self.meta)
        hdul = fits.HDUList([primary] + self.to_hdus())
        with atomic_output(path) as tmp:
            hdul.writeto(tmp, overwrite=True, checksum=True)

    @classmethod
    def load(cls, path, *, band=None):
        """Read a template written by :meth:`save` (or one band of a multi-band file).

        Parameters
        ----------
        path : str or path-like
        band : str, optional
            The band to read from a multi-band file
            (:class:`~lsst_bfdrift.templates.bands.MultiBandTemplate`); a
            single-band file has no bands and refuses one.

        Raises
        ------
        TemplateFileError
            The file is not a FITS file, is truncated, fails its checksum or
            hash, is of another schema version, or is internally inconsistent;
            a multi-band file without ``band`` (or without that band).
        """
        path, hdus = read_template_fits(path)
        bands = template_file_bands(path, hdus)
        if not bands:
            if band is not None:
                raise TemplateFileError(f"{path}: a single-band template file (one template for "
                                        f"every band); band {band!r} cannot be chosen in it",
                                        path)
            return cls._from_hdus(path, hdus)
        if band is None:
            raise TemplateFileError(f"{path}: a multi-band template file (bands "
                                    f"{', '.join(bands)}): choose one with band=, or read "
                                    "them all with lsst_bfdrift.templates.load_templates", path)
        b = band_key(band)
        if b not in bands:
            raise TemplateFileError(f"{path}: no template for band {b!r}; the file holds bands "
                                    f"{', '.join(bands)}", path)
        return cls._from_hdus(path, hdus, suffix="_" + b.upper())

    @classmethod
    def _from_hdus(cls, path, hdus, *, suffix=""):
        """The template of the extensions named with ``suffix`` in :func:`read_template_fits`'s."""
        name = "TEMPLATE" + suffix
        if name not in hdus:
            raise TemplateFileError(f"{path}: no {name} extension")
        hdr, data = hdus[name]
        meta_str = hdr.get("BFMETA", hdus["PRIMARY"][0].get("BFMETA", "{}"))
        shared = {n: hdus[n + suffix][1] for n in ("CORNER_D", "VEDGE_D", "HEDGE_D", "VEDGE_T",
                                                   "HEDGE_T") if n + suffix in hdus}
        version = hdr.get("BFSCHEMA")
        if version is None or isinstance(version, (str, bool, float)):
            what = "missing" if version is None else \
                f"the {type(version).__name__} {version!r}, not an integer"
            raise TemplateFileError(f"{path}: template schema version (BFSCHEMA) is {what}; "
                                    f"this lsst_bfdrift reads the integer version "
                                    f"{TEMPLATE_SCHEMA_VERSION}")
        if version != TEMPLATE_SCHEMA_VERSION:
            raise TemplateFileError(f"{path}: template schema version {version}, this "
                                    f"lsst_bfdrift reads version {TEMPLATE_SCHEMA_VERSION}")
        try:
            ns = int(hdr["BFNSAMP"])
            fractions = np.array([hdr[f"BFFRAC{k}"] for k in range(ns)], dtype=float)
            charge = float(hdr["BFQAGG"])
            meta = json.loads(meta_str)
        except (KeyError, ValueError) as exc:
            raise TemplateFileError(f"{path}: template header incomplete ({exc})") from exc
        check_template_table(path, data, meta)
        tol = 0.0 if hdr.get("BFSHARED", False) else None
        merge = meta.get("merge", "mean")
        try:
            tpl = cls.from_table(data, fractions, charge, meta=meta, max_mismatch=tol,
                                 merge=merge)
        except TemplateFileError as exc:
            raise TemplateFileError(str(exc), path) from exc
        except (ValueError, IndexError, KeyError, TypeError) as exc:
            raise TemplateFileError(f"inconsistent {name} table ({exc})", path) from exc
        if shared:
            if not {"CORNER_D", "VEDGE_D", "HEDGE_D"} <= set(shared):
                raise TemplateFileError(f"{path}: incomplete shared-boundary extensions")
            try:
                tpl = cls(shared["CORNER_D"], shared["VEDGE_D"], shared["HEDGE_D"], fractions,
                          charge, vedge_t=shared.get("VEDGE_T"), hedge_t=shared.get("HEDGE_T"),
                          meta=tpl.meta, pixel_table=tpl._pixel_table)
            except ValueError as exc:
                raise TemplateFileError(f"{path}: {exc}") from exc
        if int(hdr.get("BFSIZE", -1)) != tpl.size:
            raise TemplateFileError(f"{path}: header size {hdr.get('BFSIZE')} does not match "
                                    f"table ({tpl.size})")
        if hdr.get("BFHASH") != tpl._digest():
            raise TemplateFileError(f"{path}: template arrays do not match their SHA-256 "
                                    "(file altered or corrupt)")
        return tpl


def _set_meta(header, meta):
    """Write ``meta`` as JSON in ``header['BFMETA']`` (long-string cards)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", fits.verify.VerifyWarning)
        header["BFMETA"] = json.dumps(dict(meta), sort_keys=True, default=_json_default)


def _json_default(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise InputTypeError(f"cannot serialise {type(obj).__name__}")


def build_template(params=None, settings=None, *, progress=False):
    """Compute a template from the electrostatic model.

    Parameters
    ----------
    params : SensorParameters, optional
        Sensor model parameters (default: the package defaults).
    settings : TemplateSettings, optional
        Template settings (default :class:`TemplateSettings`: 21 x 21, 1e4 e,
        32 samples, 1e-5 px, the settings of the bundled default template).
    progress : bool or callable, optional
        True: a progress bar on stderr (labelled ``template``); a callable:
        called as ``progress(fraction)`` (0 to 1) as the boundaries are
        found, e.g. to move the bar of a longer job.

    Returns
    -------
    DistortionTemplate
    """
    params = SensorParameters() if params is None else params
    settings = TemplateSettings() if settings is None else settings
    n, ns = settings.size, settings.edge_samples
    c = n // 2
    base = SensorModel(params)
    model = base.with_charge({(0, 0): settings.aggressor_charge})
    iters = int(np.ceil(np.log2(0.9 / settings.tol)))
    runs = 2 if settings.baseline == "computed" else 1
    total = runs * iters * 5
    kw = dict(edge_samples=ns, tol=settings.tol, z0=settings.conversion_height,
              drift_kwargs=settings.drift_kwargs(), workers=settings.workers,
              spacing=settings.spacing)
    if callable(progress):
        bar = _FractionReport(total, progress)
    else:
        bar = ProgressBar(total, "template", enabled=bool(progress))
    with bar:
        # a model symmetric about the aggressor's axes is traced on a quadrant
        grid = centred_boundaries(model, c, progress=bar, **kw)
        ref = None
        if settings.baseline == "computed":
            ref = centred_boundaries(base, c, progress=bar, **kw)
    corner_d, vedge_d, hedge_d = grid.displacements(ref)
    meta = {"source": "lsst_bfdrift.build_template", "params": params.to_dict(),
            "settings": settings.to_dict()}
    return DistortionTemplate(corner_d, vedge_d, hedge_d, grid.fractions,
                              settings.aggressor_charge, meta=meta)


class _FractionReport:
    """A ProgressBar-like counter that reports the fraction done to a callable."""

    def __init__(self, total, report):
        self.total, self.done, self.report = max(int(total), 1), 0, report

    def __call__(self, n=1):
        self.done = min(self.done + n, self.total)
        self.report(self.done / self.total)

    def __enter__(self):
        self.report(0.0)
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            self.report(1.0)
        return False


def window_leak(template):
    """Fraction of the aggressor pixel's area change that the template's window misses.

    The aggressor's pixel shrinks by ``1 - A00``; with every pixel in the
    window, its neighbours would grow by as much (pixel areas sum to a
    constant). The leak is the part of that growth that falls outside the
    window (or is lost to the bisection's noise on the window's outer
    boundary): ``-(sum of the window's areas - N^2) / (1 - A00)``, i.e.
    ``-area_sum_error / (1 - A00)`` of :meth:`DistortionTemplate.summary`.

    Parameters
    ----------
    template : DistortionTemplate

    Returns
    -------
    leak : float
        0 when the window holds the whole area change; about 0.027 for the
        bundled default (21 x 21 pixels, 32 samples, 1e-5 px), 0.20 for the
        same sensor built with 8 samples and a 1e-4 px tolerance. NaN for a
        template that does not change the aggressor's area.
    """
    a = template.moments().area
    c = template.center
    change = 1.0 - float(a[c, c])
    if change == 0.0:
        return float("nan")
    return float(-(a.sum() - a.size) / change)


def default_template_path():
    """Path of the template shipped with the package."""
    return data_path("default_template.fits")


def load_default_template():
    """The template shipped with the package (see ``docs/templates.rst``, "The default template").

    Examples
    --------
    A 21 x 21 pixel Green's function: the boundary displacements around one
    aggressor pixel holding 1e4 electrons (the pixel at ``center``):

    >>> from lsst_bfdrift import load_default_template
    >>> t = load_default_template()
    >>> t.size, t.center, t.charge
    (21, 10, 10000.0)
    """
    return DistortionTemplate.load(default_template_path())
