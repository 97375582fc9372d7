"""Compiled (numba) shoelace-moment kernel of :func:`lsst_bfdrift.geometry.superpose.moment_maps`.

numba is used here because the benchmark showed numpy cannot reach the
needed speed: the exact shoelace moments of a 4k x 4k CCD's 36-vertex pixels
took 55-100 s with numpy temporaries (4-6 us per pixel) against a few
seconds compiled. The numpy implementation in :mod:`lsst_bfdrift.physics.polygons`
remains the reference the tests compare against.
"""

import types

import numba
import numpy as np

__all__ = ["stack_moments", "stack_moments_serial", "moment_kernel", "SERIAL_PIXELS"]


_THIRD = 1.0 / 3.0
_TWELFTH = 1.0 / 12.0


@numba.njit(cache=True, inline="always")
def _chain(xa, ya, xb, yb, c):
    """Add segment (a -> b) to a chain's line integrals c[0..7].

    c = [int x dy, int x^2 dy, int x^3 dy, int y dx, int y^2 dx, int y^3 dx,
    int x y^2 dx, int x y dx], exact along the straight segment.
    """
    dx = xb - xa
    dy = yb - ya
    yy = ya * ya + ya * yb + yb * yb
    c[0] += 0.5 * dy * (xa + xb)
    c[1] += _THIRD * dy * (xa * xa + xa * xb + xb * xb)
    c[2] += 0.25 * dy * (xa * xa + xb * xb) * (xa + xb)
    c[3] += 0.5 * dx * (ya + yb)
    c[4] += _THIRD * dx * yy
    c[5] += 0.25 * dx * (ya * ya + yb * yb) * (ya + yb)
    c[6] += dx * (_THIRD * xa * yy
                   + _TWELFTH * dx * (ya * ya + 2.0 * ya * yb + 3.0 * yb * yb))
    c[7] += dx * (xa * ya + 0.5 * (xa * dy + ya * dx) + _THIRD * dx * dy)


@numba.njit(cache=True, inline="always")
def _add_shifted(c, sgn, h, k, x0, y0, x1, y1, s):
    """Add a chain's shoelace sums (paper eqs. 3.12-3.17) to s[0..5].

    The chain's integrals ``c`` are about local coordinates; the pixel sees
    it at (x + h, y + k) (one of h, k is zero), traversed forwards
    (``sgn`` = 1) or backwards (-1). (x0, y0), (x1, y1): the chain's ends
    in local coordinates.
    """
    ddx = x1 - x0
    ddy = y1 - y0
    X1 = c[0] + h * ddy
    X2 = c[1] + 2.0 * h * c[0] + h * h * ddy
    X3 = c[2] + 3.0 * h * c[1] + 3.0 * h * h * c[0] + h * h * h * ddy
    Y1 = c[3] + k * ddx
    Y2 = c[4] + 2.0 * k * c[3] + k * k * ddx
    Y3 = c[5] + 3.0 * k * c[4] + 3.0 * k * k * c[3] + k * k * k * ddx
    # int (x + h)(y + k)^2 d(x + h) with int x dx = (x1^2 - x0^2) / 2
    Z = (c[6] + 2.0 * k * c[7] + k * k * 0.5 * (x1 * x1 - x0 * x0)
         + h * (c[4] + 2.0 * k * c[3] + k * k * ddx))
    s[0] += sgn * -0.5 * (X1 - Y1)
    s[1] -= sgn * _THIRD * X3
    s[2] += sgn * _THIRD * Y3
    s[3] += sgn * 0.5 * Z
    s[4] += sgn * -0.5 * X2
    s[5] += sgn * 0.5 * Y2


def _row_chains_py(st, ns, has_t, ro, co, fr, nr, nx, hc, he):
    """Line integrals of every row boundary's chain (left corner -> samples -> right corner).

    Local coordinates: x from the centre of the pixel above/below, y from
    the nominal boundary. hc[r, I] = integrals, he[r, I] = (x0, y0, x1, y1).
    """
    oh = 2 + ns
    oht = 2 + 3 * ns
    for r in numba.prange(nr):
        a = r + ro
        c = np.empty(8)
        for I in range(nx):
            L = I + co
            c[:] = 0.0
            px = -0.5 + st[0, a, L]
            py = np.float64(st[1, a, L])
            he[r, I, 0] = px
            he[r, I, 1] = py
            for k in range(ns):
                qx = -0.5 + fr[k] + (st[oht + k, a, L] if has_t else 0.0)
                qy = np.float64(st[oh + k, a, L])
                _chain(px, py, qx, qy, c)
                px, py = qx, qy
            qx = 0.5 + st[0, a, L + 1]
            qy = np.float64(st[1, a, L + 1])
            _chain(px, py, qx, qy, c)
            he[r, I, 2] = qx
            he[r, I, 3] = qy
            hc[r, I, :] = c


def _stack_moments_py(st, ns, has_t, ro, co, fr, out):
    """Moments of every pixel of a block from its superposed boundary channels.

    Parameters
    ----------
    st : (nch, rows, cols) displacement channels (pixel units), float32 or
        float64: corner dx, corner dy, ns column-boundary samples (x),
        ns row-boundary samples (y), then (if ``has_t``) ns tangential
        column-boundary and ns tangential row-boundary samples. Corner
        (J, I) of the block and the edges of pixel (J, I) are read at
        ``st[:, J + ro, I + co]``.
    ns : int, samples per edge
    has_t : bool, whether the tangential channels are present
    ro, co : int, row and column offsets of the block's first corner in ``st``
    fr : (ns,) sample fractions
    out : (8, ny, nx) output: area, dx, dy, ixx, iyy, ixy, e1, e2

    Each pixel's polygon (clockwise: lower-left corner, up the left edge,
    along the top, down the right edge, back along the bottom) is the union
    of four boundary chains, each shared with a neighbour. Every chain's
    exact line integrals (:func:`_chain`) are computed once, about
    coordinates local to the chain (displacements plus sample fractions, so
    no precision is lost to the pixel's position), and moved to each of its
    two pixels' centres by the binomial shift of the integrands
    (:func:`_add_shifted`): the paper's shoelace sums, half the work of
    building every pixel's polygon separately.
    """
    ny = out.shape[1]
    nx = out.shape[2]
    hc = np.empty((ny + 1, nx, 8))
    he = np.empty((ny + 1, nx, 4))
    _row_chains(st, ns, has_t, ro, co, fr, ny + 1, nx, hc, he)
    ov = 2
    ovt = 2 + 2 * ns
    for J in numba.prange(ny):
        a = J + ro
        b = J + 1 + ro
        s = np.empty(6)
        cl = np.empty(8)
        cr = np.empty(8)
        lx0 = ly0 = lx1 = ly1 = 0.0
        for I in range(nx + 1):
            # column boundary I (left of pixel I, right of pixel I - 1), upwards
            C = I + co
            cr[:] = 0.0
            px = np.float64(st[0, a, C])
            py = -0.5 + st[1, a, C]
            x0, y0 = px, py
            for k in range(ns):
                qx = np.float64(st[ov + k, a, C])
                qy = -0.5 + fr[k] + (st[ovt + k, a, C] if has_t else 0.0)
                _chain(px, py, qx, qy, cr)
                px, py = qx, qy
            qx = np.float64(st[0, b, C])
            qy = 0.5 + st[1, b, C]
            _chain(px, py, qx, qy, cr)
            if I > 0:
                P = I - 1
                s[:] = 0.0
                _add_shifted(cl, 1.0, -0.5, 0.0, lx0, ly0, lx1, ly1, s)
                _add_shifted(hc[J + 1, P], 1.0, 0.0, 0.5, he[J + 1, P, 0], he[J + 1, P, 1],
                             he[J + 1, P, 2], he[J + 1, P, 3], s)
                _add_shifted(cr, -1.0, 0.5, 0.0, x0, y0, qx, qy, s)
                _add_shifted(hc[J, P], -1.0, 0.0, -0.5, he[J, P, 0], he[J, P, 1],
                             he[J, P, 2], he[J, P, 3], s)
                ar = s[0]
                cx = s[4] / ar
                cy = s[5] / ar
                ixx = s[1] / ar - cx * cx
                iyy = s[2] / ar - cy * cy
                ixy = s[3] / ar - cx * cy
                out[0, J, P] = ar
                out[1, J, P] = cx
                out[2, J, P] = cy
                out[3, J, P] = ixx
                out[4, J, P] = iyy
                out[5, J, P] = ixy
                out[6, J, P] = (ixx - iyy) / (ixx + iyy)
                out[7, J, P] = 2.0 * ixy / (ixx + iyy)
            cl[:] = cr
            lx0, ly0, lx1, ly1 = x0, y0, qx, qy


def _named(fn, name, **globals_):
    """A copy of ``fn`` under another name (numba's on-disk cache is keyed by
    the qualified name), with some of its globals replaced."""
    g = types.FunctionType(fn.__code__, {**fn.__globals__, **globals_}, name, fn.__defaults__,
                           fn.__closure__)
    g.__qualname__ = name
    g.__doc__ = fn.__doc__
    return g


_row_chains = numba.njit(parallel=True, cache=True)(_named(_row_chains_py, "_row_chains"))
_row_chains_serial = numba.njit(cache=True)(_named(_row_chains_py, "_row_chains_serial"))
stack_moments = numba.njit(parallel=True, cache=True)(
    _named(_stack_moments_py, "stack_moments", _row_chains=_row_chains))
# One thread, for the small boxes of the linearised maps' exact fallback: a
# parallel region needs the other thread awake, which on a busy machine can
# take a scheduler time slice, far more than a small box's work.
stack_moments_serial = numba.njit(cache=True)(
    _named(_stack_moments_py, "stack_moments_serial", _row_chains=_row_chains_serial))

#: Pixels of a block at or below which the moments run on one thread.
SERIAL_PIXELS = 16384


def moment_kernel(pixels):
    """The moment kernel for a block of ``pixels``: the parallel one for large
    blocks when numba has more than one thread, else the serial one (with one
    thread the parallel kernel gains nothing and is never compiled)."""
    if pixels > SERIAL_PIXELS and numba.get_num_threads() > 1:
        return stack_moments
    return stack_moments_serial
