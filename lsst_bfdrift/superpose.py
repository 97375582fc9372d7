"""Superposition of a template over a charge image (the Green's-function step).

Boundaries for any charge pattern are the nominal grid plus, for every
aggressor, Q_agg / Q_template times the template shifted to the aggressor.
This is linear in charge, so every boundary sample's displacement field is a
2-d convolution of the charge image with a fixed kernel; the convolutions are
done by FFT, and the pixel polygons and their exact shoelace moments are
evaluated strip by strip so that a full 4k x 4k CCD fits in memory.

Image frame: ``charge[j, i]`` is pixel (i, j), centred on (i, j) in pixel units.
"""

import numpy as np
from scipy import fft as sp_fft

from .boundaries import BoundaryGrid
from .geometry import pixel_polygons, polygon_moments

__all__ = ["MomentMaps", "check_charge_image", "superpose_boundaries", "moment_maps"]


def check_charge_image(charge, *, mask=None, name="charge"):
    """Validate a charge image (e per pixel) and return a float64 copy.

    Parameters
    ----------
    charge : array_like, 2-d
        Collected charge per pixel (e). Negative values are allowed (the model
        is linear; they act as charge deficits).
    mask : array_like of bool, optional
        True where a pixel must not act as an aggressor; its charge is set to
        zero in the copy. NaN or inf are allowed only in masked pixels.
    name : str, optional
        Name used in error messages.

    Returns
    -------
    ndarray
        A new float64 array (the input is never modified).
    """
    arr = np.array(charge, dtype=np.float64, copy=True)
    if arr.ndim != 2:
        raise ValueError(f"{name} image must be 2-d, got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} image is empty")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != arr.shape:
            raise ValueError(f"mask shape {mask.shape} does not match {name} shape {arr.shape}")
        arr[mask] = 0.0
    bad = ~np.isfinite(arr)
    if np.any(bad):
        j, i = np.argwhere(bad)[0]
        raise ValueError(f"{name} image has {int(bad.sum())} non-finite pixel(s) "
                         f"(first at x={i}, y={j}); mask them")
    return arr


class _Convolver:
    """FFT convolution of one image block with the template's kernels."""

    def __init__(self, template):
        self.t = template
        k = [template.corner_d[..., 0], template.corner_d[..., 1]]
        k += [template.vedge_d[..., s] for s in range(template.edge_samples)]
        k += [template.hedge_d[..., s] for s in range(template.edge_samples)]
        if template.vedge_t is not None:
            k += [template.vedge_t[..., s] for s in range(template.edge_samples)]
            k += [template.hedge_t[..., s] for s in range(template.edge_samples)]
        self.kernels = k
        self._cache = {}

    def kernel_ffts(self, shape):
        if shape not in self._cache:
            self._cache = {shape: [sp_fft.rfft2(k, shape) for k in self.kernels]}
        return self._cache[shape]

    def convolve(self, block, workers=1):
        """Full convolutions of ``block`` with every kernel."""
        n1 = self.t.size + 1
        shape = (sp_fft.next_fast_len(block.shape[0] + n1 - 1, real=True),
                 sp_fft.next_fast_len(block.shape[1] + n1 - 1, real=True))
        fb = sp_fft.rfft2(block, shape, workers=workers)
        out = []
        for fk in self.kernel_ffts(shape):
            out.append(sp_fft.irfft2(fb * fk, shape, workers=workers))
        return out


def _block_displacements(conv, charge, r0, r1, workers=1):
    """Displacement arrays for pixel rows r0..r1-1 (and their corner rows)."""
    t = conv.t
    c, ns = t.center, t.edge_samples
    ny, nx = charge.shape
    # Aggressor rows that can reach corner rows r0..r1: ja in [r0 - c, r1 + c].
    a0 = max(r0 - c - 1, 0)
    a1 = min(r1 + c + 1, ny)
    block = charge[a0:a1]
    full = conv.convolve(block, workers=workers)
    # D[J] = F[J + c] in full-image rows; in block rows F_b[m] with m = J + c - a0.
    def rows(J0, J1):
        return slice(J0 + c - a0, J1 + c - a0)
    cols_c = slice(c, c + nx + 1)
    cols_h = slice(c, c + nx)
    cdx = full[0][rows(r0, r1 + 1), cols_c]
    cdy = full[1][rows(r0, r1 + 1), cols_c]
    v = np.stack([full[2 + s][rows(r0, r1), cols_c] for s in range(ns)], axis=-1)
    h = np.stack([full[2 + ns + s][rows(r0, r1 + 1), cols_h] for s in range(ns)], axis=-1)
    vt = ht = None
    if t.vedge_t is not None:
        o = 2 + 2 * ns
        vt = np.stack([full[o + s][rows(r0, r1), cols_c] for s in range(ns)], axis=-1)
        ht = np.stack([full[o + ns + s][rows(r0, r1 + 1), cols_h] for s in range(ns)], axis=-1)
    q = 1.0 / t.charge
    out = [np.stack([cdx, cdy], axis=-1) * q, v * q, h * q]
    out += [None if vt is None else vt * q, None if ht is None else ht * q]
    return out


def superpose_boundaries(template, charge, *, mask=None, workers=1):
    """Pixel boundaries of a whole charge image (absolute, pixel units).

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    charge : array_like, 2-d
        Collected charge (e), ``charge[j, i]`` for pixel (i, j).
    mask : array_like of bool, optional
        Pixels that do not act as aggressors.
    workers : int, optional
        FFT threads.

    Returns
    -------
    BoundaryGrid
        With ``vedge_t`` and ``hedge_t`` attributes (None if the template has
        no tangential displacements).
    """
    q = check_charge_image(charge, mask=mask)
    conv = _Convolver(template)
    cd, v, h, vt, ht = _block_displacements(conv, q, 0, q.shape[0], workers=workers)
    nominal = BoundaryGrid(0, 0, np.zeros(cd.shape), v, h, template.fractions).nominal()
    grid = BoundaryGrid(0, 0, nominal.corners + cd, nominal.vedge + v, nominal.hedge + h,
                        template.fractions)
    grid.vedge_t, grid.hedge_t = vt, ht
    return grid


class MomentMaps:
    """Per-pixel geometry of the final pixel boundaries.

    Attributes
    ----------
    area : ndarray
        Pixel area (px^2; nominal 1).
    dx, dy : ndarray
        Centroid shift from the nominal pixel centre (px).
    ixx, iyy, ixy : ndarray
        Central second moments (px^2; nominal 1/12, 1/12, 0).
    e1, e2 : ndarray
        Ellipticity of the pixel's second moments.
    """

    _names = ("area", "dx", "dy", "ixx", "iyy", "ixy", "e1", "e2")

    def __init__(self, shape):
        for k in self._names:
            setattr(self, k, np.empty(shape))

    def as_dict(self):
        """The maps by name."""
        return {k: getattr(self, k) for k in self._names}


def moment_maps(template, charge, *, mask=None, strip=256, workers=1, progress=None):
    """Area, centroid-shift and ellipticity maps of a charge image's pixels.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function.
    charge : array_like, 2-d
        Collected charge (e), ``charge[j, i]``.
    mask : array_like of bool, optional
        Pixels that do not act as aggressors (their geometry is still computed).
    strip : int, optional
        Rows per block (memory ~ 8 * strip * width * (4 + 2 ns) bytes). The
        moments are evaluated by a compiled kernel (:mod:`lsst_bfdrift._kernels`)
        that builds each pixel's polygon on the fly.
    workers : int, optional
        FFT threads.
    progress : callable, optional
        Called with the number of rows finished.

    Returns
    -------
    MomentMaps
    """
    from ._kernels import grid_moments

    q = check_charge_image(charge, mask=mask)
    ny, nx = q.shape
    strip = max(int(strip), 1)
    conv = _Convolver(template)
    out = MomentMaps(q.shape)
    fr = np.ascontiguousarray(template.fractions)
    for r0 in range(0, ny, strip):
        r1 = min(r0 + strip, ny)
        cd, v, h, vt, ht = _block_displacements(conv, q, r0, r1, workers=workers)
        nom = BoundaryGrid(0, r0, np.zeros(cd.shape), v, h, template.fractions).nominal()
        has_t = vt is not None
        res = np.empty((8, r1 - r0, nx))
        grid_moments(np.ascontiguousarray(nom.corners + cd), np.ascontiguousarray(nom.vedge + v),
                     np.ascontiguousarray(nom.hedge + h), fr,
                     vt if has_t else np.zeros((1, 1, 1)), ht if has_t else np.zeros((1, 1, 1)),
                     has_t, r0, res)
        for k, name in enumerate(MomentMaps._names):
            getattr(out, name)[r0:r1] = res[k]
        if progress is not None:
            progress(r1 - r0)
    return out
