"""Flux-redistribution correction with the template as Green's function.

Model of image formation (flux F per pixel with square pixels, recorded
image I): while charge Q collects, every pixel edge has swept an area
S_e = L_e[Q] (linear in Q: a convolution of the charge with the template's
swept-area kernel, :func:`~lsst_bfdrift.templates.swept.swept_area_kernels`),
and the collection rate of a pixel is its flux plus, for each edge, the flux
density f_e at that edge times the area the edge has swept outward. With tau
the exposure fraction,

    dQ/dtau = F + G(Q; F),   G(Q; F)_p = sum_e +-f_e(F) L_e[Q],

which is linear in Q for a given F, so the recorded image is the series

    I = R(F) = F + G(F)/2 + G(G(F))/6 + G(G(G(F)))/24 + ...

The first correction term alone is the usual "half the final shift"
approximation; keeping ``order`` terms accounts for the time history of the
boundaries (the collecting rates change while charge accumulates). F is found
by iterating F <- F + (1 - G/2)(I - R(F)) (a Newton-like step with the
first-order inverse of dR/dF), or, much faster, from the inverse series
(:func:`correct_series`): writing G(F) = B(F, F) with B(f, Q) bilinear
(densities from f, swept areas from Q) and b = B(I, I),

    F = I - b/2 + B(b, I)/4 + (1/4 - 1/6) B(I, b) + O(B^3),

which needs only two applications of the swept-area operator (the
astier23 baseline needs one) and is exact to second order in the
brighter-fatter strength. The third-order term (``docs/correction.rst``),
with x2 = c/4 + (1/4 - a3) d, c = B(b, I), d = B(I, b), a3 = 1/6 (order >= 3),
a4 = 1/24 (order >= 4), is

    x3 = -B(x2, I)/2 + (a3/2 - 1/8) B(b, b) + B(I, y),
    y = (a3/2 - 1/8) c + (a3 - a4 - 1/8) d,

one more operator application (for y). :func:`correct_image` with
``start='series'`` uses F = I - b/2 + x2 + x3 directly when an a-priori
estimate of the fourth-order term is below the tolerance, and otherwise
iterates from it. Every edge transfer is added
to one pixel and subtracted from its neighbour, so the correction conserves
flux exactly.

The flux density at an edge is the mean of the two pixels beside it
(``'mean2'``) or a four-point interpolation along the edge normal,
(-F_{-2} + 9 F_{-1} + 9 F_{+1} - F_{+2}) / 16 (``'cubic4'``, the interpolation
of point values), or the fourth-order finite-volume reconstruction from
pixel averages, (-F_{-2} + 7 F_{-1} + 7 F_{+1} - F_{+2}) / 12 (``'fv4'``,
exact for a cubic profile), which follow the curvature of a star's profile.
Edges touching masked pixels or the image border carry no flux.
"""

import numpy as np
from scipy import fft as sp_fft

from lsst_bfdrift.correction._edge_kernels import density_weight, fused_transfer
from lsst_bfdrift.correction.series import apriori_ok, first_order_terms, sparse_series, tolerance
from lsst_bfdrift.correction.settings import RECOMMENDED
from lsst_bfdrift.templates.swept import (MAX_SWEEP, OperatorCache, SweptAreas,  # noqa: F401
                                         refuse_out_of_range, swept_area_kernels)
from lsst_bfdrift.utils.errors import InputError

__all__ = ["edge_flux_density", "edge_transfer",
           "recorded_image", "correct_image", "correct_series", "correct_half_shift",
           "area_coefficients", "coulton18_kernel", "correct_coulton18", "MAX_SWEEP",
           "refuse_out_of_range"]


def edge_flux_density(flux, *, mode="cubic4", blocked=None):
    """Flux density (e / px^2) at every interior edge.

    Parameters
    ----------
    flux : ndarray, shape (ny, nx)
        Flux per pixel (e).
    mode : {'mean2', 'cubic4', 'fv4'}
        Two-pixel mean or four-point interpolation along the edge normal
        (falls back to the mean where the outer pixels are missing).
    blocked : ndarray of bool, optional
        Pixels that neither give nor receive flux.

    Returns
    -------
    fv : ndarray, shape (ny, nx + 1)
        Density at the left edge of each pixel column (0 on the border).
    fh : ndarray, shape (ny + 1, nx)
        Density at the bottom edge of each pixel row (0 on the border).
    """
    wo = density_weight(mode)
    f = np.asarray(flux, float)
    ny, nx = f.shape
    blk = np.zeros(f.shape, bool) if blocked is None else np.asarray(blocked, bool)

    def along(a, b):
        """Densities between a[..., k-1] and a[..., k] for k = 1..n-1, axis last."""
        mean = 0.5 * (a[..., :-1] + a[..., 1:])
        ok = ~(b[..., :-1] | b[..., 1:])
        out = np.where(ok, mean, 0.0)
        if wo != 0.0 and a.shape[-1] >= 4:
            cub = wo * (a[..., :-3] + a[..., 3:]) + (0.5 - wo) * (a[..., 1:-2] + a[..., 2:-1])
            okc = ok[..., 1:-1] & ~(b[..., :-3] | b[..., 3:])
            out[..., 1:-1] = np.where(okc, cub, out[..., 1:-1])
        return out

    fv = np.zeros((ny, nx + 1))
    fh = np.zeros((ny + 1, nx))
    fv[:, 1:-1] = along(f, blk)
    fh[1:-1, :] = along(f.T, blk.T).T
    return fv, fh


def edge_transfer(sv, sh, fv, fh):
    """Charge gained by every pixel from its edges' swept areas (e).

    An edge that moved towards +x by area S gives the pixel on its left
    ``f S`` and takes the same from the pixel on its right (likewise +y).
    The result sums to zero exactly.
    """
    tv = fv * sv
    th = fh * sh
    return (tv[:, 1:] - tv[:, :-1]) + (th[1:, :] - th[:-1, :])


def recorded_image(flux, swept, *, order=3, density="cubic4", blocked=None, densities=None):
    """Image recorded for a flux ``flux`` with moving boundaries (series to ``order``).

    Parameters
    ----------
    flux : ndarray
        Flux per pixel with square pixels (e).
    swept : SweptAreas
        Operator of the template on this image shape.
    order : int, optional
        Number of terms of R(F) = F + G(F)/2 + G(G(F))/6 + ...; 2 is the
        half-final-shift approximation.
    density, blocked
        See :func:`edge_flux_density`.
    densities : tuple, optional
        (fv, fh) already computed for ``flux``; by default the densities are
        evaluated on the fly by a compiled kernel
        (:func:`lsst_bfdrift.correction._edge_kernels.fused_transfer`).

    Returns
    -------
    ndarray
    """
    density_weight(density)  # checks the name
    blk = np.zeros(np.shape(flux), bool) if blocked is None else np.asarray(blocked, bool)
    out = np.array(flux, float, copy=True)
    src = out.copy()
    term = out
    fact = 1.0
    for k in range(1, int(order)):
        fact *= k + 1
        sv, sh = swept(term)
        if densities is not None:
            term = edge_transfer(sv, sh, *densities)
        else:
            term = fused_transfer(sv, sh, src, blk, cubic=density)
        del sv, sh
        out += term / fact  # term k of the series carries 1 / (k + 1)!
    return out


def correct_image(image, template, *, order=RECOMMENDED.order, density=RECOMMENDED.density,
                  blocked=None, max_iter=RECOMMENDED.max_iter, rtol=RECOMMENDED.rtol,
                  noise_tol=RECOMMENDED.noise_tol, start=RECOMMENDED.start,
                  workers=RECOMMENDED.workers, dtype=RECOMMENDED.dtype,
                  strip=RECOMMENDED.strip, sparse=RECOMMENDED.sparse, cache=None, info=None,
                  check_range=True, maps=None, progress=None):
    """Flux that square pixels would have collected, from a recorded image.

    The defaults are the recommended settings
    (:data:`~lsst_bfdrift.correction.settings.RECOMMENDED`), which the Task
    and ``bfdrift correct`` use too.

    Parameters
    ----------
    image : ndarray
        Recorded image (e); not modified.
    template : DistortionTemplate
        Green's function.
    order : int, optional
        Terms of the time-history series (2 = half final shift).
    density : {'mean2', 'cubic4', 'fv4'}, optional
        Flux density at the edges.
    blocked : ndarray of bool, optional
        Pixels that neither give nor receive flux (masked, saturated, NaN);
        their values are left unchanged. Finite blocked pixels still act as
        aggressors (a saturated pixel holds its charge); non-finite ones count
        as empty.
    max_iter : int, optional
        Fixed-point iterations.
    rtol : float, optional
        Convergence: ``max |I - R(F)| <= rtol * max |I|``.
    noise_tol : float or None, optional
        Convergence used when not None: ``|I - R(F)| <=
        noise_tol * sqrt(max(I, 1))`` in every pixel, i.e. the model residual
        is a small fraction of each pixel's Poisson noise (e).
    start : {'image', 'series'}, optional
        First guess: the recorded image, or the third-order inverse series
        (three operator applications). With 'series' no forward-model check
        is made (``iterations`` = 0) when the neglected fourth-order term,
        estimated as 4 r max|x3| over 5 x 5 pixels with r = max|x3| / max|x2|,
        is below the tolerance in every pixel; otherwise the iteration
        starts from the series.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float64, numpy.float32}, optional
        FFT precision (:class:`~lsst_bfdrift.templates.swept.SweptAreas`).
    strip : int, optional
        Rows per block, each solved with a halo of ``3 ((N + 1) // 2 + 2)``
        rows (N = template size; the reach of the third-order series, so the
        series is exact) or ``4 (N + 3)`` rows (blocks that need the
        iteration, solved again) to bound memory. The solution's dependence on rows
        beyond the halo is of third order in the BF strength (measured in
        ``docs/benchmarks.rst``). None: whole image.
    sparse : bool, optional
        With ``start='series'``: compute the second- and third-order terms
        only in windows around the sources that need them
        (:func:`lsst_bfdrift.correction.series.sparse_series`, one full operator
        application instead of three, with a bound on what is left out);
        falls back to the dense series when its checks fail.
    cache : OperatorCache, optional
        Operators to reuse (kernel transforms kept between calls); must have
        been made for ``template``, ``workers`` and ``dtype``.
    info : dict, optional
        Filled with ``solver`` ('sparse' or 'dense') and, for the sparse
        solver, its window statistics.

    check_range : bool, optional
        Refuse images the model cannot describe
        (:func:`refuse_out_of_range`); the Task checks before it calls.
    maps : FirstOrderPass, optional
        First-order geometry maps of the image, computed from the sparse
        series' first operator application
        (:func:`lsst_bfdrift.correction.series.first_order_terms`); left
        incomplete by the other solvers (the caller checks
        ``maps.complete``).
    progress : callable, optional
        Called with the fraction (0 to 1, never decreasing) of the solution
        done: after each block of ``strip`` rows and each iteration (as a
        share of ``max_iter``); 1 at the end. It does not change the result.

    Returns
    -------
    flux : ndarray
        Corrected image (e).
    iterations : int
        Largest over the blocks (0: the series needed no check).
    converged : bool
        All blocks converged.
    """
    if start not in ("image", "series"):
        raise InputError(f"start must be 'image' or 'series', got {start!r}")
    kw = dict(order=order, density=density, max_iter=max_iter, rtol=rtol, noise_tol=noise_tol,
              start=start, workers=workers, dtype=dtype)
    img, blk = _checked(image, blocked, strip)
    ops = _operators(cache, template, workers, dtype)
    if check_range:
        refuse_out_of_range(_finite(img, blk)[0], ops.kernel_abs_sum)
    info = {} if info is None else info
    info["solver"] = "dense"
    report = (lambda f: None) if progress is None else progress
    if sparse and start == "series":
        eff, full_blk = _finite(img, blk)
        flux = sparse_series(eff, full_blk, ops, noise_tol=noise_tol, rtol=rtol, order=order,
                             density=density, strip=None if strip is None else int(strip),
                             info=info, maps=maps)
        if flux is not None:
            info["solver"] = "sparse"
            if full_blk.any():
                flux[full_blk] = img[full_blk]
            report(1.0)
            return flux, 0, True
    ny = img.shape[0]
    budget = max(int(max_iter), 1)
    if strip is None or int(strip) >= ny:
        out = _solve_block(img, template, blk, swept=ops(img.shape),
                           on_iteration=lambda it: report(it / budget), **kw)
        report(1.0)
        return out
    strip = int(strip)
    nblocks = -(-ny // strip)
    # One application of B reaches (N + 1) / 2 rows (swept areas) plus 2
    # (edge densities); the third-order series nests three, so a halo of
    # 3 ((N + 1) // 2 + 2) rows gives the whole-image result exactly. A block
    # that needs the iteration is solved again with 4 (N + 3) rows.
    halos = (3 * ((template.size + 1) // 2 + 2), 4 * (template.size + 3))
    if start != "series":
        halos = halos[1:]
    flux = np.empty_like(img)
    its, conv = 0, True
    for b, r0 in enumerate(range(0, ny, strip)):
        r1 = min(r0 + strip, ny)
        for k, halo in enumerate(halos):
            a, z = max(r0 - halo, 0), min(r1 + halo, ny)
            last = k == len(halos) - 1
            out, it, cv = _solve_block(
                img[a:z], template, blk[a:z], swept=ops((z - a, img.shape[1])),
                series_only=not last,
                on_iteration=lambda i, b=b: report((b + i / budget) / nblocks), **kw)
            if out is not None:
                break
        flux[r0:r1] = out[r0 - a:r1 - a]
        its, conv = max(its, it), conv and cv
        report((b + 1) / nblocks)
    return flux, its, conv


def _operators(cache, template, workers, dtype):
    """``cache`` if it serves these settings, else a new :class:`OperatorCache`."""
    if cache is not None:
        if not isinstance(cache, OperatorCache) or not cache.matches(template, workers, dtype):
            raise InputError("cache must be an OperatorCache made for this template, "
                             "workers and dtype")
        return cache
    return OperatorCache(template, workers=workers, dtype=dtype)


def _limit(img_eff, noise_tol, rtol):
    """Tolerance per pixel (e): noise-based array or rtol x max |I| (scalar)."""
    if noise_tol is not None:
        return tolerance(img_eff, noise_tol)
    return rtol * max(np.abs(img_eff).max(), 1e-300)



def _checked(image, blocked, strip):
    """The image as float64 (no copy when it is one: the solvers only read it)
    and the blocked mask, checked with the strip height."""
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise InputError(f"image must be 2-d, got shape {img.shape}")
    blk = np.zeros(img.shape, bool) if blocked is None else np.asarray(blocked, bool)
    if blk.shape != img.shape:
        raise InputError(f"blocked shape {blk.shape} does not match image {img.shape}")
    if strip is not None and int(strip) < 1:
        raise InputError(f"strip must be positive, got {strip}")
    return img, blk


def _finite(img, blocked):
    """Image with non-finite pixels set to 0 and the blocked mask including
    them; ``img`` and ``blocked`` themselves (no copies) when all are finite."""
    finite = np.isfinite(img)
    if finite.all():
        return img, blocked
    return np.where(finite, img, 0.0), blocked | ~finite


def _solve_block(img, template, blocked, *, order, density, max_iter, rtol, noise_tol, start,
                 workers, dtype, swept=None, series_only=False, on_iteration=None):
    """Iterative solution of I = R(F) on one block (see :func:`correct_image`).

    With ``series_only``, returns (None, 0, False) when the series alone is
    not accurate enough instead of iterating. ``on_iteration`` is called with the
    number of each iteration done.
    """
    img_eff, blk = _finite(img, blocked)
    if swept is None:
        swept = SweptAreas(template, img.shape, workers=workers, dtype=dtype)
    limit = _limit(img_eff, noise_tol, rtol)
    if start == "series":
        flux, (x2, x3) = _series_block(img_eff, blk, swept, order, density, terms=3)
        ok = apriori_ok(x2, x3, limit)
        del x2, x3
        if ok:  # the neglected terms are far below the tolerance: no check needed
            flux[blk] = img[blk]
            return flux, 0, True
        if series_only:
            return None, 0, False
    else:
        flux = img_eff.copy()
    converged = False
    it = 0
    cubic = density
    for it in range(1, int(max_iter) + 1):
        resid = recorded_image(flux, swept, order=order, density=density, blocked=blk)
        np.subtract(img_eff, resid, out=resid)
        resid[blk] = 0.0
        if np.all(np.abs(resid) <= limit):
            converged = True  # F already solves I = R(F) to the tolerance
            break
        # Newton-like step: (dR/dF)^-1 ~ 1 - G/2 to first order, which makes
        # the iteration converge much faster than F <- F + r where BF is strong.
        sv, sh = swept(resid)
        step = fused_transfer(sv, sh, flux, blk, cubic=cubic)
        del sv, sh
        step *= -0.5
        step += resid
        flux += step
        del step, resid
        if on_iteration is not None:
            on_iteration(it)
    flux[blk] = img[blk]
    return flux, it, converged


def _series_block(img, blk, swept, order, density, *, terms=2):
    """Inverse series on one block (see :func:`correct_series`).

    ``terms=2``: F = I + x1 + x2 (two operator applications); ``terms=3``
    adds the third-order term x3 (three applications). Returns F and, for
    ``terms=3``, (x2, x3) for the a-priori error estimate.
    """
    cubic = density
    a3 = 1.0 / 6.0 if order >= 3 else 0.0
    a4 = 1.0 / 24.0 if order >= 4 else 0.0
    sv, sh = swept(img)
    b = fused_transfer(sv, sh, img, blk, cubic=cubic)      # B(I, I)
    out = b * -0.5
    out += img
    c = fused_transfer(sv, sh, b, blk, cubic=cubic)        # B(b, I)
    svb, shb = swept(b)
    d = fused_transfer(svb, shb, img, blk, cubic=cubic)    # B(I, b)
    if terms < 3:
        del sv, sh, svb, shb
        c *= 0.25
        out += c
        d *= 0.25 - a3
        out += d
        return out, None
    # x2 = c/4 + (1/4 - a3) d; third order (module docstring):
    # x3 = -B(x2, I)/2 + (a3/2 - 1/8) B(b, b) + B(I, y),
    # y = -x2/2 + (a3/2) (c + d) - a4 d = (a3/2 - 1/8) c + (a3 - a4 - 1/8) d.
    x2 = c * 0.25
    x2 += (0.25 - a3) * d
    out += x2
    x3 = fused_transfer(svb, shb, b, blk, cubic=cubic)     # B(b, b)
    del svb, shb, b
    x3 *= 0.5 * a3 - 0.125
    tmp = fused_transfer(sv, sh, x2, blk, cubic=cubic)     # B(x2, I)
    del sv, sh
    tmp *= -0.5
    x3 += tmp
    c *= 0.5 * a3 - 0.125
    d *= a3 - a4 - 0.125
    c += d                                                 # y
    del d
    svy, shy = swept(c)
    del c
    fused_transfer(svy, shy, img, blk, cubic=cubic, out=tmp)  # B(I, y)
    del svy, shy
    x3 += tmp
    del tmp
    out += x3
    return out, (x2, x3)


def correct_series(image, template, *, order=3, density="mean2", blocked=None, workers=1,
                   dtype=np.float64, strip=None, check_range=True):
    """Flux that square pixels would have collected, by the inverse series.

    Solves I = R(F) (the time-history model of :func:`recorded_image`) to
    second order in the brighter-fatter strength without iterating:
    F = I - b/2 + B(b, I)/4 + (1/4 - 1/6) B(I, b), b = B(I, I) (module
    docstring). Two applications of the swept-area operator.

    Parameters
    ----------
    image : ndarray
        Recorded image (e); not modified.
    template : DistortionTemplate
        Green's function.
    order : int, optional
        Terms of the forward series (2: half final shift; >= 3: with the
        time history; terms beyond 3 are third order and dropped).
    density : {'mean2', 'cubic4', 'fv4'}, optional
        Flux density at the edges.
    blocked : ndarray of bool, optional
        As for :func:`correct_image`.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float64, numpy.float32}, optional
        FFT precision (:class:`~lsst_bfdrift.templates.swept.SweptAreas`); the
        image arithmetic stays float64.
    strip : int, optional
        Rows per block. The result at a pixel depends on the image within
        ``2 (N + 3)`` rows (N = template size), so blocks overlapping by that
        halo give the full-frame result (to rounding) with memory bounded by
        the block size. None: the whole image at once.

    check_range : bool, optional
        Refuse images the model cannot describe
        (:func:`refuse_out_of_range`); the Task checks before it calls.

    Returns
    -------
    flux : ndarray
        Corrected image (e).
    iterations : int
        1.
    converged : bool
        True (no iteration).
    """
    img, blk = _checked(image, blocked, strip)
    img_eff, blk = _finite(img, blk)
    ny, nx = img.shape
    ops = _operators(None, template, workers, dtype)
    if check_range:
        refuse_out_of_range(img_eff, ops.kernel_abs_sum)
    if strip is None or int(strip) >= ny:
        flux, _ = _series_block(img_eff, blk, ops(img.shape), order, density)
    else:
        strip = int(strip)
        halo = 2 * (template.size + 3)
        flux = np.empty_like(img_eff)
        for r0 in range(0, ny, strip):
            r1 = min(r0 + strip, ny)
            a, z = max(r0 - halo, 0), min(r1 + halo, ny)
            out, _ = _series_block(img_eff[a:z], blk[a:z], ops((z - a, nx)), order, density)
            flux[r0:r1] = out[r0 - a:r1 - a]
    flux[blk] = img[blk]
    return flux, 1, True


def correct_half_shift(image, template, *, blocked=None, workers=1, dtype=np.float64,
                       strip=None, cache=None, check_range=True, maps=None):
    """One flux-conserving pass with half the final shift (Astier & Regnault 2023).

    F = I - G(I; I) / 2: swept areas and edge flux densities (two-pixel mean)
    both from the recorded image; no iteration, as in the paper. ``dtype``
    as for :class:`~lsst_bfdrift.templates.swept.SweptAreas`. ``strip`` (rows
    per block, overlapping by ``(N + 1) // 2 + 2`` rows, which gives the
    whole-image result exactly) and ``cache`` as for :func:`correct_image`;
    ``check_range`` refuses images the model cannot describe
    (:func:`refuse_out_of_range`); ``maps``
    (:class:`~lsst_bfdrift.geometry.first_order.FirstOrderPass`) gets the
    first-order geometry maps from the same transforms.

    Returns
    -------
    flux, iterations (1), converged (True)
    """
    img, blk = _checked(image, blocked, strip)
    img_eff, blk = _finite(img, blk)
    ops = _operators(cache, template, workers, dtype)
    if check_range:
        refuse_out_of_range(img_eff, ops.kernel_abs_sum)
    # the first-order pass of the windowed series is exactly this pass
    flux = first_order_terms(img_eff, blk, ops, strip=strip, cubic="mean2",
                             keep_swept=False, maps=maps)[0]
    flux[blk] = img[blk]
    return flux, 1, True


def area_coefficients(template):
    """a_ij = d ln A_ij / dQ (per electron) of the template, indexed [dj, di].

    The area sum rule (sum of all a_ij = 0) is imposed on the central value,
    as for measured coefficients: a_00 = -(sum of the others).
    """
    a = np.log(template.moments().area) / template.charge
    c = template.center
    a[c, c] = 0.0
    a[c, c] = -a.sum()
    return a


def coulton18_kernel(a, *, pad=4):
    """Kernel K with discrete Laplacian equal to ``a`` (Coulton et al. 2018).

    Solved by FFT on a grid ``pad`` times the size of ``a`` (periodic), which
    requires sum(a) = 0 (see :func:`area_coefficients`); the result is cut
    back to the size of ``a``.
    """
    a = np.asarray(a, float)
    n = a.shape[0]
    if a.shape != (n, n) or n % 2 != 1:
        raise InputError(f"a must be square with odd size, got {a.shape}")
    if abs(a.sum()) > 1e-9 * np.abs(a).sum():
        raise InputError("the area coefficients must sum to zero (sum rule)")
    m = pad * n
    big = np.zeros((m, m))
    c = n // 2
    idx = (np.arange(n) - c) % m
    big[np.ix_(idx, idx)] = a
    ky = 2 * np.pi * np.fft.fftfreq(m)
    lap = (2 * np.cos(ky)[:, None] - 2) + (2 * np.cos(ky)[None, :] - 2)
    fa = np.fft.fft2(big)
    lap[0, 0] = 1.0
    fk = fa / lap
    fk[0, 0] = 0.0
    k = np.real(np.fft.ifft2(fk))
    return k[np.ix_(idx, idx)]


def _edge_divergence(flux, phi, blocked):
    """sum over the 4 neighbours q of (F_p + F_q)/2 (phi_q - phi_p); no flux
    through blocked pixels or the border. Sums to zero."""
    out = np.zeros_like(flux)
    ok_x = ~(blocked[:, 1:] | blocked[:, :-1])
    tx = np.where(ok_x, 0.5 * (flux[:, 1:] + flux[:, :-1]) * (phi[:, 1:] - phi[:, :-1]), 0.0)
    ok_y = ~(blocked[1:] | blocked[:-1])
    ty = np.where(ok_y, 0.5 * (flux[1:] + flux[:-1]) * (phi[1:] - phi[:-1]), 0.0)
    out[:, :-1] += tx
    out[:, 1:] -= tx
    out[:-1] += ty
    out[1:] -= ty
    return out


def correct_coulton18(image, kernel, *, blocked=None, max_iter=10, rtol=1e-7, workers=1,
                      progress=None):
    """Kernel correction of Coulton et al. 2018: F = I - 1/2 div(F grad(K * F)), iterated.

    Parameters
    ----------
    image : ndarray
        Recorded image (e); not modified.
    kernel : ndarray
        From :func:`coulton18_kernel` (per electron).
    blocked, max_iter, rtol, workers
        As for :func:`correct_image`.
    progress : callable, optional
        Called with the fraction of ``max_iter`` done after each iteration
        (1 when converged).

    Returns
    -------
    flux, iterations, converged
    """
    img = np.array(image, dtype=np.float64, copy=True)
    blk = np.zeros(img.shape, bool) if blocked is None else np.asarray(blocked, bool)
    blk = blk | ~np.isfinite(img)
    img_eff = np.where(np.isfinite(img), img, 0.0)
    k = np.asarray(kernel, float)
    c = k.shape[0] // 2
    fshape = (sp_fft.next_fast_len(img.shape[0] + k.shape[0] - 1, real=True),
              sp_fft.next_fast_len(img.shape[1] + k.shape[1] - 1, real=True))
    fk = sp_fft.rfft2(k, fshape, workers=workers)
    ny, nx = img.shape
    flux = img_eff.copy()
    scale = max(np.abs(img_eff).max(), 1e-300)
    converged = False
    it = 0
    for it in range(1, int(max_iter) + 1):
        phi = sp_fft.irfft2(sp_fft.rfft2(flux, fshape, workers=workers) * fk, fshape,
                            workers=workers)[c:c + ny, c:c + nx]
        new = img_eff - 0.5 * _edge_divergence(flux, phi, blk)
        change = np.abs(new - flux).max()
        flux = new
        if change <= rtol * scale:
            converged = True
            break
        if progress is not None:
            progress(it / int(max_iter))
    if progress is not None:
        progress(1.0)
    flux[blk] = img[blk]
    return flux, it, converged
