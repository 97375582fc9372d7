r"""Catalog-level brighter-fatter correction of star moments with pixel-geometry maps.

An alternative to (and a cross-check of) the pixel-level flux redistribution
of :class:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask`: the image is left as
recorded and each star's moments are recomputed on the true pixel grid.

Derivation
----------
Pixel p (nominal centre :math:`\mathbf{x}_p`) collected the light that fell
on its *distorted* footprint :math:`P_p`: :math:`I_p = \int_{P_p} f`, where
:math:`f` is the surface brightness (e per px^2). The footprint has area
:math:`A_p`, centroid :math:`\mathbf{x}_p + \mathbf{d}_p` and central second
moments :math:`S_p` (2 x 2; :math:`S_0 = \mathrm{diag}(1/12, 1/12)` for a
square pixel). Taking the light density as uniform over the footprint,
:math:`f \approx I_p / A_p` on :math:`P_p` (the area only normalises and
drops out of every moment), any moment of the light is a sum over pixels,

.. math::

    \int f\, g(\mathbf{x})\, d^2x \approx \sum_p I_p \left[g(\mathbf{x}_p + \mathbf{d}_p)
        + \tfrac12 \mathrm{tr}\left(S_p \nabla\nabla^{\mathsf T} g\right)\right],

so that, with the light of every pixel put at its displaced centroid and
spread like its footprint,

* flux: :math:`F = \sum_p I_p` (the distorted pixels still tile the plane:
  every electron is counted once, the flux is unchanged);
* centroid: :math:`\bar{\mathbf{x}} = \sum_p I_p (\mathbf{x}_p + \mathbf{d}_p) / F`;
* second moments: :math:`M = \sum_p I_p [(\mathbf{x}_p + \mathbf{d}_p - \bar{\mathbf{x}})
  (\ldots)^{\mathsf T} + S_p - S_0] / F`. Subtracting :math:`S_0` keeps the
  convention of moments measured at pixel centres on square pixels
  (the same sum on an undistorted image gives the usual moments), so the
  result estimates what the square-pixel moments would have been without BF.

Weighted (adaptive) moments use the same expansion with
:math:`g = W, W\mathbf{d}, W\mathbf{d}\mathbf{d}^{\mathsf T}` (W the Gaussian
weight of covariance M, :math:`\mathbf{d} = \mathbf{x} - \boldsymbol{\mu}`):
with :math:`\mathbf{u} = M^{-1}\mathbf{d}`, :math:`\mathbf{v} = S\mathbf{u}`
and :math:`k = 1 + \tfrac12(\mathbf{u}\cdot\mathbf{v} - \mathrm{tr}\,M^{-1}S)`,
a footprint contributes :math:`W k`, :math:`W(k\mathbf{d} - \mathbf{v})` and
:math:`W(k\mathbf{d}\mathbf{d}^{\mathsf T} - \mathbf{v}\mathbf{d}^{\mathsf T}
- \mathbf{d}\mathbf{v}^{\mathsf T} + S)`, all at the displaced centroid
(S here is the footprint's moment minus the square pixel's, so the nominal
grid gives the usual sums at pixel centres). The weight's variation across
the footprint matters at the same order as S itself: without it a uniform
extra S would change Gaussian adaptive moments by 4 S instead of S.
:func:`adaptive_moments` iterates to the elliptical Gaussian whose weighted
moments reproduce it, M = 2 x (weighted covariance) (Bernstein & Jarvis
2002; the fixed point of ``galsim.hsm.FindAdaptiveMom``, against which it is
tested).

Time history: pixel boundaries move while the exposure builds up, in
proportion to the charge collected so far (the template is linear). For a
steady source the light arriving at time t sees the fraction t / T_exp of
the final distortion, so the exposure-averaged footprint is the nominal one
plus ``history`` = 1/2 of the final shift (the half-shift of Astier &
Regnault 2023). The final geometry maps (from the recorded image, as the
Task computes them) are therefore applied with ``d -> history * d`` and
``S_p - S_0 -> history * (S_p - S_0)``.

Neglected, second order in the distortion: the gradient of ``f`` across a
footprint (a square pixel has the same term), the BF difference between the
recorded and the true image used to predict the maps, and light crossing
the aperture edge (the aperture flux is left unchanged).

The correction is applied as a difference: ``M_corrected = M_catalog +
(M_adaptive(distorted) - M_adaptive(nominal))`` with both adaptive moments
computed here by the same algorithm on the same cutout (each iterated to its
own weight), so any small difference between this implementation and HSM
cancels.
"""

import numpy as np
from astropy import units as u

from lsst_bfdrift.catalogs.catalog import FLAG_EDGE, FLAG_MOMENTS
from lsst_bfdrift.geometry.superpose import moment_maps
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.utils.errors import ComputationError, InputError

__all__ = ["adaptive_moments", "footprint_moments", "correct_star_moments", "correct_catalog"]

_S0 = 1.0 / 12.0


def adaptive_moments(x, y, counts, *, sxx=None, syy=None, sxy=None, guess=None,
                     guess_sigma=2.0, max_iter=200, tol=1e-9):
    """Adaptive second moments of light at arbitrary points with finite footprints.

    Parameters
    ----------
    x, y : ndarray
        Positions of the light (px): pixel centres, or displaced centroids.
    counts : ndarray
        Light at each point (e; background subtracted, may be negative).
    sxx, syy, sxy : ndarray, optional
        Second moments of each point's footprint relative to a square pixel
        (px^2; ``S_p - S_0``), added inside the weighted sums; default 0.
    guess : tuple, optional
        Starting centroid (x, y) px; default the brightest point.
    guess_sigma : float, optional
        Starting Gaussian sigma (px).
    max_iter : int, optional
        Iteration limit.
    tol : float, optional
        Convergence: largest change of a moment (px^2) or centroid (px).

    Returns
    -------
    dict
        ``x``, ``y`` (px), ``ixx``, ``iyy``, ``ixy`` (px^2, the adaptive
        moments = covariance of the matched Gaussian), ``T``, ``e1``, ``e2``,
        ``iterations``.

    Raises
    ------
    RuntimeError
        If the iteration does not converge or the weighted flux is not positive.
    """
    x = np.asarray(x, float).ravel()
    y = np.asarray(y, float).ravel()
    c = np.asarray(counts, float).ravel()
    z = np.zeros_like(c)
    sxx = z if sxx is None else np.asarray(sxx, float).ravel()
    syy = z if syy is None else np.asarray(syy, float).ravel()
    sxy = z if sxy is None else np.asarray(sxy, float).ravel()
    if guess is None:
        k = int(np.argmax(c))
        mx, my = x[k], y[k]
    else:
        mx, my = float(guess[0]), float(guess[1])
    a = b = float(guess_sigma) ** 2
    h = 0.0
    has_s = bool(np.any(sxx) or np.any(syy) or np.any(sxy))
    for it in range(1, max_iter + 1):
        det = a * b - h * h
        if not det > 0:
            raise ComputationError("adaptive moments: weight became degenerate")
        ia, ib, ih = b / det, a / det, -h / det  # M^-1
        dx, dy = x - mx, y - my
        q = ia * dx * dx + 2 * ih * dx * dy + ib * dy * dy
        w = c * np.exp(-0.5 * q)
        if has_s:
            # light spread over a footprint with moments S about (x, y): second-order
            # Taylor expansion of the weighted integrands w, w d, w d d^T over the footprint
            ux, uy = ia * dx + ih * dy, ih * dx + ib * dy          # M^-1 d
            vx, vy = sxx * ux + sxy * uy, sxy * ux + syy * uy      # S M^-1 d
            k = 1.0 + 0.5 * (ux * vx + uy * vy - (ia * sxx + 2 * ih * sxy + ib * syy))
        else:
            vx = vy = 0.0
            k = 1.0
        s0 = (w * k).sum()
        if not s0 > 0:
            raise ComputationError("adaptive moments: weighted flux is not positive")
        ddx = (w * (dx * k - vx)).sum() / s0
        ddy = (w * (dy * k - vy)).sum() / s0
        mxx = (w * (dx * dx * k - 2 * vx * dx + sxx)).sum() / s0 - ddx * ddx
        myy = (w * (dy * dy * k - 2 * vy * dy + syy)).sum() / s0 - ddy * ddy
        mxy = (w * (dx * dy * k - vx * dy - dx * vy + sxy)).sum() / s0 - ddx * ddy
        na, nb, nh = 2 * mxx, 2 * myy, 2 * mxy
        change = max(abs(na - a), abs(nb - b), abs(nh - h), abs(ddx), abs(ddy))
        if it > 3 and change < 0.05 * min(a, b):
            # near the fixed point the plain update halves the error (exactly so for
            # Gaussian light and weight): extrapolate, M <- 2 M' - M, unless that loses
            # positivity
            ea, eb, eh = 2 * na - a, 2 * nb - b, 2 * nh - h
            if ea > 0 and eb > 0 and ea * eb > eh * eh:
                na, nb, nh = ea, eb, eh
                ddx, ddy = 2 * ddx, 2 * ddy  # the weighted centroid also moves halfway
        mx, my, a, b, h = mx + ddx, my + ddy, na, nb, nh
        if not (a > 0 and b > 0):
            raise ComputationError("adaptive moments: negative second moment")
        if change < tol:
            t = a + b
            return {"x": mx, "y": my, "ixx": a, "iyy": b, "ixy": h, "T": t,
                    "e1": (a - b) / t, "e2": 2 * h / t, "iterations": it}
    raise ComputationError(f"adaptive moments did not converge in {max_iter} iterations")


def footprint_moments(maps):
    """Per-pixel centroid shift and footprint second moments from geometry maps.

    Parameters
    ----------
    maps : MomentMaps, Struct or dict
        Either :class:`~lsst_bfdrift.geometry.superpose.MomentMaps` (``area, dx, dy,
        ixx, iyy, ixy``) or the Task's result / a dict with ``area``,
        ``centroid_x``, ``centroid_y``, ``e1``, ``e2``. In the latter case the
        footprint moments are rebuilt as ``T_p = A_p / 6`` (exact for a
        square; for a near-square quadrilateral the error is second order in
        the distortion), ``ixx = T_p (1 + e1) / 2``, ``iyy = T_p (1 - e1) / 2``,
        ``ixy = T_p e2 / 2``.

    Returns
    -------
    dict of ndarray
        ``dx``, ``dy`` (px), ``sxx``, ``syy``, ``sxy`` (px^2, footprint
        moments minus the square pixel's 1/12, 1/12, 0).
    """
    def get(name):
        if isinstance(maps, dict):
            return maps.get(name)
        return getattr(maps, name, None)

    if get("ixx") is not None and get("dx") is not None:
        dx, dy = get("dx"), get("dy")
        ixx, iyy, ixy = get("ixx"), get("iyy"), get("ixy")
    else:
        area, e1, e2 = get("area"), get("e1"), get("e2")
        dx, dy = get("centroid_x"), get("centroid_y")
        if any(v is None for v in (area, e1, e2, dx, dy)):
            raise InputError("geometry maps need area, centroid_x, centroid_y, e1, e2 (run the "
                             "Task with compute_geometry=True) or a MomentMaps")
        t = np.asarray(area, float) / 6.0
        ixx, iyy, ixy = 0.5 * t * (1 + e1), 0.5 * t * (1 - e1), 0.5 * t * np.asarray(e2)
    out = {"dx": np.asarray(dx, float), "dy": np.asarray(dy, float),
           "sxx": np.asarray(ixx, float) - _S0, "syy": np.asarray(iyy, float) - _S0,
           "sxy": np.asarray(ixy, float)}
    shape = out["dx"].shape
    if any(v.shape != shape for v in out.values()) or len(shape) != 2:
        raise InputError("geometry maps must be 2-d arrays of one shape")
    return out


def correct_star_moments(stamp, x0, y0, foot, *, guess=None, history=0.5, valid=None):
    """Change of a star's adaptive moments when computed on the distorted pixels.

    Parameters
    ----------
    stamp : ndarray
        Background-subtracted cutout (e), ``stamp[j, i]`` is image pixel
        (x0 + i, y0 + j).
    x0, y0 : int
        Image coordinates of the cutout's first pixel.
    foot : dict
        :func:`footprint_moments` of the whole image.
    guess : tuple, optional
        Starting centroid (image px).
    history : float, optional
        Fraction of the final distortion seen on average during the exposure.
    valid : ndarray of bool, optional
        Pixels of the cutout to use (default all).

    Returns
    -------
    dict
        ``dx``, ``dy`` (px), ``dixx``, ``diyy``, ``dixy`` (px^2):
        distorted-grid minus nominal-grid adaptive moments.
    """
    ny, nx = stamp.shape
    jj, ii = np.mgrid[y0:y0 + ny, x0:x0 + nx]
    sl = (slice(y0, y0 + ny), slice(x0, x0 + nx))
    ok = np.ones(stamp.shape, bool) if valid is None else np.asarray(valid, bool)
    xs, ys, cs = ii[ok].astype(float), jj[ok].astype(float), stamp[ok]
    m0 = adaptive_moments(xs, ys, cs, guess=guess)
    h = float(history)
    m1 = adaptive_moments(xs + h * foot["dx"][sl][ok], ys + h * foot["dy"][sl][ok], cs,
                          sxx=h * foot["sxx"][sl][ok], syy=h * foot["syy"][sl][ok],
                          sxy=h * foot["sxy"][sl][ok], guess=(m0["x"], m0["y"]))
    return {"dx": m1["x"] - m0["x"], "dy": m1["y"] - m0["y"], "dixx": m1["ixx"] - m0["ixx"],
            "diyy": m1["iyy"] - m0["iyy"], "dixy": m1["ixy"] - m0["ixy"]}


def correct_catalog(catalog, exposure, *, maps=None, template=None, gain=None, mask=None,
                    history=0.5, workers=2):
    """Brighter-fatter correction of a star catalog's moments (catalog level).

    Parameters
    ----------
    catalog : QTable
        From :func:`~lsst_bfdrift.catalogs.catalog.measure_stars` on ``exposure``.
    exposure : ndarray, CCDData, NDData or path
        The recorded image (electrons, or ADU with ``gain``).
    maps : MomentMaps, Struct or dict, optional
        Final pixel-geometry maps of the image (see :func:`footprint_moments`);
        computed from ``template`` when not given.
    template : DistortionTemplate, optional
        Green's function used to compute ``maps``.
    gain : float, optional
        e/ADU for images in ADU.
    mask : array_like of bool, optional
        Bad pixels (no aggressors, not used in the moments).
    history : float, optional
        Exposure-averaged fraction of the final distortion (1/2 for steady
        sources; see the module docstring).
    workers : int, optional
        FFT threads for the maps.

    Returns
    -------
    QTable
        A copy with ``x``, ``y``, ``ixx``, ``iyy``, ``ixy``, ``T``, ``e1``,
        ``e2`` corrected, the measured values kept as ``*_meas`` and the
        corrections ``dT`` (px^2), ``de1``, ``de2``. Stars flagged
        FLAG_EDGE/FLAG_MOMENTS or whose correction fails are left
        unchanged with ``bf_corrected`` False.
    """
    image = to_electrons(exposure, gain=gain, mask=mask)
    image.warn()
    data, bad = image.data, image.bad
    if maps is None:
        if template is None:
            raise InputError("give the geometry maps or a template to compute them")
        maps = moment_maps(template, np.where(bad, 0.0, data), mask=bad, workers=workers)
    foot = footprint_moments(maps)
    if foot["dx"].shape != data.shape:
        raise InputError(f"maps shape {foot['dx'].shape} does not match image {data.shape}")
    if not 0 <= float(history) <= 1:
        raise InputError(f"history must be in [0, 1], got {history}")
    out = catalog.copy()
    n = len(out)
    stamp = int(out.meta.get("stamp", 25))
    half = stamp // 2
    ny, nx = data.shape
    delta = np.zeros((n, 5))
    done = np.zeros(n, bool)
    for k in range(n):
        if int(out["flags"][k]) & (FLAG_EDGE | FLAG_MOMENTS):
            continue
        cx, cy = float(out["x"][k].value), float(out["y"][k].value)
        ix, iy = int(np.floor(cx + 0.5)), int(np.floor(cy + 0.5))
        x0, y0 = ix - half, iy - half
        if x0 < 0 or y0 < 0 or ix + half >= nx or iy + half >= ny:
            continue
        sl = (slice(y0, y0 + stamp), slice(x0, x0 + stamp))
        st = data[sl] - float(out["background"][k].value)
        try:
            d = correct_star_moments(np.where(bad[sl], 0.0, st), x0, y0, foot, guess=(cx, cy),
                                     history=history, valid=~bad[sl])
        except RuntimeError:
            continue
        delta[k] = d["dx"], d["dy"], d["dixx"], d["diyy"], d["dixy"]
        done[k] = True
    px2 = u.pix ** 2
    for name in ("x", "y", "ixx", "iyy", "ixy", "T", "e1", "e2"):
        out[name + "_meas"] = out[name]
    out["x"] = out["x"] + delta[:, 0] * u.pix
    out["y"] = out["y"] + delta[:, 1] * u.pix
    ixx = out["ixx"].value + delta[:, 2]
    iyy = out["iyy"].value + delta[:, 3]
    ixy = out["ixy"].value + delta[:, 4]
    t = ixx + iyy
    out["ixx"], out["iyy"], out["ixy"], out["T"] = ixx * px2, iyy * px2, ixy * px2, t * px2
    with np.errstate(invalid="ignore", divide="ignore"):
        out["e1"] = (ixx - iyy) / t
        out["e2"] = 2 * ixy / t
    out["dT"] = out["T"] - out["T_meas"]
    out["de1"] = out["e1"] - out["e1_meas"]
    out["de2"] = out["e2"] - out["e2_meas"]
    out["bf_corrected"] = done
    out.meta["bf_correction"] = f"catalog level, history factor {float(history):g}"
    return out
