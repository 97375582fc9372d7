"""Star simulations with moving pixel boundaries (Rasmussen 2015, section 4.4).

Photons of a GalSim PSF are shot by GalSim, converted at the entrance window
and assigned to the pixel whose current polygon contains them; every
``update_every`` conversions the boundaries are recomputed from the collected
charge with the template as Green's function. The same photons are also
binned on the undistorted grid, so that every statistic is available for the
image with and without the brighter-fatter effect (a paired, noise-free
difference).

Frame: a square stamp of ``stamp_size`` pixels; pixel (i, j) is centred on
(i, j); the star is centred at ``(c + center[0], c + center[1])`` with
c = stamp_size // 2.
"""

import numpy as np
from astropy.table import Table

from lsst_bfdrift.simulation._star_kernels import NEIGHBOUR_ORDER, accumulate, inner_boxes, locate
from lsst_bfdrift.physics.boundaries import BoundaryGrid
from lsst_bfdrift.templates.galsim_rules import (accumulate_galsim, add_templates_galsim,
                                                 edge_boxes, galsim_boxes, galsim_edge_templates,
                                                 locate_galsim, nominal_edges)
from lsst_bfdrift.utils.progress import ProgressBar
from lsst_bfdrift.geometry.superpose import check_charge_image, moment_maps, superpose_boundaries
from lsst_bfdrift.utils.errors import InputError

__all__ = ["make_psf", "shoot_photons", "image_moments", "StarSimulation", "simulate_star"]


def make_psf(kind, fwhm, *, e=0.0, beta=0.0, beta_moffat=3.5):
    """A GalSim PSF by name: 'gaussian', 'moffat' or 'kolmogorov' (FWHM arcsec),
    sheared to ellipticity ``e`` at position angle ``beta`` (degrees)."""
    import galsim  # galsim: heavy, imported only where GalSim runs
    if not fwhm > 0:
        raise InputError(f"--fwhm must be positive, got {fwhm}")
    if not 0 <= e < 1:
        raise InputError(f"--e must be in [0, 1), got {e}")
    makers = {"gaussian": lambda: galsim.Gaussian(fwhm=fwhm),
              "moffat": lambda: galsim.Moffat(beta=beta_moffat, fwhm=fwhm),
              "kolmogorov": lambda: galsim.Kolmogorov(fwhm=fwhm)}
    if kind not in makers:
        raise InputError(f"unknown PSF {kind!r}; choose from {sorted(makers)}")
    psf = makers[kind]()
    return psf.shear(e=e, beta=beta * galsim.degrees) if e > 0 else psf


def shoot_photons(psf, n_photons, *, pixel_scale=0.2, seed=None):
    """Photon positions of a GalSim profile, in pixels from its centre.

    Parameters
    ----------
    psf : galsim.GSObject
        The profile (its flux is irrelevant; ``n_photons`` are drawn).
    n_photons : int
        Number of conversions.
    pixel_scale : float, optional
        arcsec per pixel.
    seed : int, optional
        Seed of GalSim's random deviate.

    Returns
    -------
    x, y : ndarray
    """
    import galsim  # galsim: heavy, imported only where GalSim runs

    n = int(n_photons)
    if n < 1:
        raise InputError(f"n_photons must be positive, got {n_photons!r}")
    if not pixel_scale > 0:
        raise InputError(f"pixel_scale must be positive, got {pixel_scale!r}")
    photons = psf.shoot(n, galsim.BaseDeviate(0 if seed is None else int(seed)))
    return np.asarray(photons.x) / pixel_scale, np.asarray(photons.y) / pixel_scale


def image_moments(image, *, weight_sigma=None, center=None):
    """Centroid, second moments and ellipticity of an image.

    Parameters
    ----------
    image : ndarray
        Counts, ``image[j, i]``.
    weight_sigma : float, optional
        Gaussian weight (px) about ``center``; None gives unweighted moments.
    center : tuple, optional
        Weight centre (x, y); default the unweighted centroid.

    Returns
    -------
    dict
        ``x, y, ixx, iyy, ixy, T`` (= ixx + iyy), ``e1, e2``, ``theta``
        (orientation of the major axis, degrees from the serial axis).
    """
    img = np.asarray(image, float)
    jj, ii = np.mgrid[:img.shape[0], :img.shape[1]]
    w = img
    if weight_sigma is not None:
        if center is None:
            tot = img.sum()
            center = ((img * ii).sum() / tot, (img * jj).sum() / tot)
        w = img * np.exp(-0.5 * ((ii - center[0])**2 + (jj - center[1])**2) / weight_sigma**2)
    tot = w.sum()
    x = (w * ii).sum() / tot
    y = (w * jj).sum() / tot
    ixx = (w * (ii - x)**2).sum() / tot
    iyy = (w * (jj - y)**2).sum() / tot
    ixy = (w * (ii - x) * (jj - y)).sum() / tot
    t = ixx + iyy
    e1, e2 = (ixx - iyy) / t, 2 * ixy / t
    return {"x": x, "y": y, "ixx": ixx, "iyy": iyy, "ixy": ixy, "T": t, "e1": e1, "e2": e2,
            "theta": 0.5 * np.degrees(np.arctan2(e2, e1))}


class StarSimulation:
    """Accumulate conversions into a stamp whose pixel boundaries move.

    The boundaries are kept as absolute arrays (the layout of
    :class:`~lsst_bfdrift.physics.boundaries.BoundaryGrid`) and updated incrementally:
    after each batch of ``update_every`` conversions, every pixel that
    received dq electrons adds dq / Q times the template centred on it
    (compiled direct sum, :mod:`lsst_bfdrift.simulation._star_kernels`). This equals the
    FFT superposition of the whole charge image to rounding (tested).

    Parameters
    ----------
    template : DistortionTemplate
        Green's function.
    stamp_size : int, optional
        Side of the stamp (pixels).
    update_every : int, optional
        Conversions between boundary updates (paper: 1000).
    layout : {'shared', 'galsim'}, optional
        'shared' (default): the template's shared boundaries, pixels tile
        the stamp. 'galsim': galsim.SiliconSensor's layout and assignment
        rule (every edge a polyline with its own corners, taken from the
        file pixel nearest the aggressor; nominal pixel first, then the
        neighbours; unassigned conversions to the nominal pixel or the first
        neighbour at random), for photon-by-photon comparisons with GalSim
        (:mod:`lsst_bfdrift.templates.galsim_rules`). Needs a template with its
        per-pixel table (:func:`~lsst_bfdrift.templates.galsim_io.import_galsim_sensor`).
    seed : int, optional
        Seed of the random choices of the 'galsim' layout.
    qdist : int, optional
        With ``layout='galsim'``: GalSim's ``qdist`` truncation of each
        aggressor's reach (GalSim's default is 3; None keeps the whole
        template, as GalSim does with ``qdist`` = template half size).
    galsim_box : bool, optional
        With ``layout='galsim'``: accept a conversion in GalSim's own
        "trivially inside" box of its nominal pixel without the polygon test,
        as GalSim does (default True); False uses a box proven to lie inside
        the polygon, i.e. the exact polygon rule.
    """

    def __init__(self, template, *, stamp_size=31, update_every=1000, layout="shared",
                 seed=None, qdist=None, galsim_box=True):
        if int(stamp_size) != stamp_size or stamp_size < 3:
            raise InputError(f"stamp_size must be an integer >= 3, got {stamp_size!r}")
        if int(update_every) != update_every or update_every < 1:
            raise InputError(f"update_every must be a positive integer, got {update_every!r}")
        if layout not in ("shared", "galsim"):
            raise InputError(f"layout must be 'shared' or 'galsim', got {layout!r}")
        self.t = template
        self.n = int(stamp_size)
        self.update_every = int(update_every)
        self.layout = layout
        self.galsim_box = bool(galsim_box)
        self._rng = np.random.default_rng(seed)
        if layout == "galsim":
            self._tv, self._th = galsim_edge_templates(template, qdist=qdist)
        self.nominal_image = np.zeros((self.n, self.n))
        self.lost = 0
        self._has_t = template.vedge_t is not None
        dummy = np.zeros((1, 1, 1))
        self._kernels = (np.ascontiguousarray(template.corner_d),
                         np.ascontiguousarray(template.vedge_d),
                         np.ascontiguousarray(template.hedge_d),
                         np.ascontiguousarray(template.vedge_t) if self._has_t else dummy,
                         np.ascontiguousarray(template.hedge_t) if self._has_t else dummy)
        self._fr = np.ascontiguousarray(template.fractions, dtype=float)
        self.reset(np.zeros((self.n, self.n)))

    def reset(self, charge):
        """Set the collected charge (e) and recompute the boundaries in full
        (FFT superposition; a direct sum for the 'galsim' layout).

        Parameters
        ----------
        charge : array_like, shape (stamp_size, stamp_size)
            Charge per pixel, ``charge[j, i]``; copied.
        """
        q = check_charge_image(charge)
        if q.shape != (self.n, self.n):
            raise InputError(f"charge must have shape {(self.n, self.n)}, got {q.shape}")
        self.image = q
        if self.layout == "galsim":
            self._V, self._H = nominal_edges(self.n, self.n, self._fr)
            add_templates_galsim(q, 1.0 / self.t.charge, self.t.center, self._V, self._H,
                                 self._tv, self._th)
            self._box = np.empty((self.n, self.n, 4))
            (galsim_boxes if self.galsim_box else edge_boxes)(self._V, self._H, 0, self.n, 0,
                                                              self.n, self._box)
            return
        g = superpose_boundaries(self.t, q)
        self._corners = np.ascontiguousarray(g.corners)
        self._vedge = np.ascontiguousarray(g.vedge)
        self._hedge = np.ascontiguousarray(g.hedge)
        dummy = np.zeros((1, 1, 1))
        self._vt = np.ascontiguousarray(g.vedge_t) if self._has_t else dummy
        self._ht = np.ascontiguousarray(g.hedge_t) if self._has_t else dummy
        self._box = np.empty((self.n, self.n, 4))
        inner_boxes(self._corners, self._vedge, self._hedge, self._fr, self._vt, self._ht,
                    self._has_t, 0, self.n, 0, self.n, self._box)

    def boundaries(self):
        """Copy of the current boundaries as a
        :class:`~lsst_bfdrift.physics.boundaries.BoundaryGrid` (absolute positions,
        pixel units; ``vedge_t``/``hedge_t`` attributes)."""
        if self.layout != "shared":
            raise InputError("boundaries() needs layout='shared'; the 'galsim' layout keeps "
                             "edge polylines (attributes _V, _H)")
        g = BoundaryGrid(0, 0, self._corners.copy(), self._vedge.copy(), self._hedge.copy(),
                         self._fr.copy())
        g.vedge_t = self._vt.copy() if self._has_t else None
        g.hedge_t = self._ht.copy() if self._has_t else None
        return g

    def assign(self, px, py):
        """Pixel indices (i, j) of conversions at (px, py) for the current
        boundaries; -1 (both) for points in no pixel of the stamp."""
        px, py = _check_points(px, py)
        oi = np.empty(px.size, dtype=np.int64)
        oj = np.empty(px.size, dtype=np.int64)
        if self.layout == "galsim":
            locate_galsim(px, py, self._rng.uniform(size=px.size), self._V, self._H, self._box,
                          oi, oj)
            off = (oi < 0) | (oi >= self.n) | (oj < 0) | (oj >= self.n)
            oi[off] = oj[off] = -1
            return oi, oj
        locate(px, py, self._corners, self._vedge, self._hedge, self._fr, self._vt, self._ht,
               self._has_t, NEIGHBOUR_ORDER, self._box, oi, oj)
        return oi, oj

    def add(self, px, py):
        """Convert photons at (px, py) (pixel units, stamp frame), in order.

        The boundaries are updated after every ``update_every`` conversions
        (counted from the start of this call) and after the last one.
        """
        px, py = _check_points(px, py)
        if self.layout == "galsim":
            self.lost += int(accumulate_galsim(px, py, self._rng.uniform(size=px.size),
                                               self.update_every, self.image,
                                               self.nominal_image, self._V, self._H, self._box,
                                               1.0 / self.t.charge, self.t.center, self._tv,
                                               self._th, self.galsim_box))
            return
        kc, kv, kh, kvt, kht = self._kernels
        self.lost += int(accumulate(px, py, self.update_every, self.image, self.nominal_image,
                                    self._corners, self._vedge, self._hedge, self._fr, self._vt,
                                    self._ht, self._has_t, NEIGHBOUR_ORDER, self._box,
                                    1.0 / self.t.charge, self.t.center, kc, kv, kh, kvt, kht))

    def geometry(self):
        """:class:`~lsst_bfdrift.geometry.superpose.MomentMaps` of the current pixels
        (of the template's shared boundaries, whatever the layout)."""
        return moment_maps(self.t, self.image)


def _check_points(px, py):
    px = np.ascontiguousarray(px, dtype=float).ravel()
    py = np.ascontiguousarray(py, dtype=float).ravel()
    if px.shape != py.shape:
        raise InputError(f"px and py must have the same size, got {px.size} and {py.size}")
    if not (np.all(np.isfinite(px)) and np.all(np.isfinite(py))):
        raise InputError("photon positions must be finite")
    return px, py


def simulate_star(template, psf, flux, *, stamp_size=31, update_every=1000, pixel_scale=0.2,
                  center=(0.25, 0.25), record_every=None, track_pixels=None, weight_sigma=None,
                  seed=None, progress=False):
    """Simulate a star's image formation with moving boundaries.

    Parameters
    ----------
    template : DistortionTemplate
        Green's function.
    psf : galsim.GSObject
        PSF (e.g. ``galsim.Gaussian(fwhm=0.6).shear(e=0.05, beta=30 * galsim.degrees)``).
    flux : float
        Total conversions (e).
    stamp_size, update_every : int, optional
        See :class:`StarSimulation`.
    pixel_scale : float, optional
        arcsec per pixel.
    center : tuple, optional
        Offset of the star from the central pixel's centre (px).
    record_every : int, optional
        Conversions between recorded rows (default: 50 rows).
    track_pixels : sequence of (di, dj), optional
        Pixels (offsets from the central pixel) whose arrival rates are
        recorded; default the central pixel and its 8 neighbours.
    weight_sigma : float, optional
        Gaussian weight of the recorded moments (px); None: unweighted.
    seed : int, optional
        GalSim seed of the photons.
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    history : astropy.table.Table
        Per recorded step: ``counts``, ``central`` (central pixel counts),
        ``T``, ``T_nominal`` (ixx + iyy, px^2, with and without BF), ``e1``,
        ``e2``, ``theta`` and their nominal twins, ``rate_<di>_<dj>``
        (arrivals per conversion into tracked pixels since the last row).
    final : dict
        ``image``, ``nominal_image``, ``maps`` (MomentMaps), ``lost``.
    """
    n = int(round(float(flux)))
    if n < 1:
        raise InputError(f"flux must be at least 1 conversion, got {flux!r}")
    sim = StarSimulation(template, stamp_size=stamp_size, update_every=update_every)
    c = sim.n // 2
    px, py = shoot_photons(psf, n, pixel_scale=pixel_scale, seed=seed)
    px = px + c + center[0]
    py = py + c + center[1]
    rec = max(update_every, (n // 50) // update_every * update_every) if record_every is None \
        else int(record_every)
    track = [(di, dj) for dj in (-1, 0, 1) for di in (-1, 0, 1)] if track_pixels is None \
        else [tuple(t) for t in track_pixels]
    rows = []
    prev = {t: 0.0 for t in track}
    done = 0
    with ProgressBar(n, "star-sim", enabled=progress) as bar:
        while done < n:
            k = min(rec, n - done)
            sim.add(px[done:done + k], py[done:done + k])
            done += k
            m = image_moments(sim.image, weight_sigma=weight_sigma)
            m0 = image_moments(sim.nominal_image, weight_sigma=weight_sigma)
            row = {"counts": float(done), "central": float(sim.image[c, c]),
                   "T": m["T"], "T_nominal": m0["T"], "e1": m["e1"], "e2": m["e2"],
                   "theta": m["theta"], "e1_nominal": m0["e1"], "e2_nominal": m0["e2"],
                   "theta_nominal": m0["theta"]}
            for (di, dj) in track:
                now = sim.image[c + dj, c + di]
                row[f"rate_{di}_{dj}"] = (now - prev[(di, dj)]) / k
                prev[(di, dj)] = now
            rows.append(row)
            bar(k)
    history = Table(rows=rows)
    final = {"image": sim.image, "nominal_image": sim.nominal_image, "maps": sim.geometry(),
             "lost": sim.lost}
    return history, final

