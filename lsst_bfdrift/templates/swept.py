"""Swept-area operator of a distortion template (FFT convolution).

Every pixel edge of an image sweeps an area that is linear in the charge
collected: a convolution of the charge with the template's swept-area
kernels (:func:`swept_area_kernels`). :class:`SweptAreas` applies it to one
image or to a stack of equally shaped windows, and :class:`OperatorCache`
keeps the kernel transforms of the shapes already seen, so that a Task
correcting many exposures (or strips of one) transforms the kernels once.
Used by :mod:`lsst_bfdrift.correction.solvers` and :mod:`lsst_bfdrift.correction.series`.
"""

import threading

import numpy as np
from scipy import fft as sp_fft
from lsst_bfdrift.utils.errors import InputError

__all__ = ["swept_area_kernels", "SweptAreas", "OperatorCache", "kernel_abs_sum",
           "refuse_out_of_range", "MAX_SWEEP"]


class _ThreadArrays:
    """Work arrays kept between calls, one set per thread (a Task may be
    shared by the threads of a dask worker); contents undefined unless the
    caller keeps them."""

    def __init__(self):
        self._local = threading.local()

    def get(self, name, shape, dtype, *, zero=False):
        """The array ``name`` of this shape and dtype (made anew, zeroed if
        ``zero``, when absent or of another shape or dtype)."""
        shape, dtype = tuple(int(v) for v in shape), np.dtype(dtype)
        store = getattr(self._local, "arrays", None)
        if store is None:
            store = self._local.arrays = {}
        buf = store.get(name)
        if buf is None or (buf.shape, buf.dtype) != (shape, dtype):
            buf = store[name] = (np.zeros if zero else np.empty)(shape, dtype)
        return buf


def _trapezoid(c0, samples, c1, fractions):
    """Integral over [0, 1] of the piecewise-linear profile through the knots."""
    s = np.concatenate([[0.0], fractions, [1.0]])
    vals = np.concatenate([c0[..., None], samples, c1[..., None]], axis=-1)
    return np.sum(0.5 * (vals[..., 1:] + vals[..., :-1]) * np.diff(s), axis=-1)


def swept_area_kernels(template):
    """Areas swept by the template's edges (px^2 per template charge).

    Returns
    -------
    kv : ndarray, shape (N, N + 1)
        Vertical edges (left edge of pixel offset (I - c, J - c)); positive
        when the edge moved towards +x.
    kh : ndarray, shape (N + 1, N)
        Horizontal edges (bottom edge); positive when moved towards +y.
    """
    t = template
    kv = _trapezoid(t.corner_d[:-1, :, 0], t.vedge_d, t.corner_d[1:, :, 0], t.fractions)
    kh = _trapezoid(t.corner_d[:, :-1, 1], t.hedge_d, t.corner_d[:, 1:, 1], t.fractions)
    return kv, kh


class SweptAreas:
    """Linear operator Q -> swept areas of every edge of an image (FFT).

    Parameters
    ----------
    template : DistortionTemplate
        Green's function.
    shape : tuple of int
        (ny, nx) of the images.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the transforms (float32 halves time and memory; the
        swept areas keep a relative accuracy ~1e-6 of the largest, see
        ``docs/benchmarks.rst``).

    Notes
    -----
    Each thread that applies the operator to single images keeps a
    zero-padded input and a spectrum product of the padded shape between
    calls (about two padded images in ``dtype``).
    """

    def __init__(self, template, shape, *, workers=1, dtype=np.float64):
        self.ny, self.nx = (int(v) for v in shape)
        self.c = template.center
        kv, kh = swept_area_kernels(template)
        n1 = template.size + 1
        self.fshape = (sp_fft.next_fast_len(self.ny + n1 - 1, real=True),
                       sp_fft.next_fast_len(self.nx + n1 - 1, real=True))
        self.workers = workers
        self.dtype = np.dtype(dtype)
        if self.dtype not in (np.dtype(np.float64), np.dtype(np.float32)):
            raise InputError(f"dtype must be float64 or float32, got {dtype!r}")
        q = 1.0 / template.charge
        self.fkv = sp_fft.rfft2((kv * q).astype(self.dtype), self.fshape, workers=workers)
        self.fkh = sp_fft.rfft2((kh * q).astype(self.dtype), self.fshape, workers=workers)
        # zero-padded input and spectrum product, kept between calls:
        # allocating them anew for every strip (and page-faulting them in)
        # cost about a third of each application (docs/benchmarks.rst)
        self._arrays = _ThreadArrays()

    def __call__(self, charge, *, extra=None):
        """Swept areas (sv of shape (ny, nx + 1), sh of shape (ny + 1, nx)), px^2.

        Views into the padded transforms, in the operator's ``dtype``.

        Parameters
        ----------
        charge : ndarray, shape (ny, nx)
            Charge (e).
        extra : ndarray, shape (m, fy, fx // 2 + 1), optional
            Transforms of ``m`` more kernels padded to :attr:`fshape` (in the
            operator's complex dtype): the charge's transform is shared with
            them, and their convolutions with the charge (the whole padded
            arrays of shape (fy, fx), a list; same frame as the swept areas:
            the convolution with a kernel placed at the origin) are returned
            as a third output. The swept areas are the same, bit for bit, with
            or without.
        """
        c, ny, nx = self.c, self.ny, self.nx
        if np.shape(charge) != (ny, nx):
            raise InputError(f"charge must have shape {(ny, nx)}, got {np.shape(charge)}")
        pad = self._arrays.get("pad", self.fshape, self.dtype, zero=True)  # zero beyond (ny, nx)
        prod = self._arrays.get("prod", self.fkv.shape, self.fkv.dtype)
        pad[:ny, :nx] = charge
        fq = sp_fft.rfft2(pad, workers=self.workers)
        np.multiply(fq, self.fkv, out=prod)
        sv = sp_fft.irfft2(prod, self.fshape, workers=self.workers, overwrite_x=True)
        if extra is not None:
            more = []
            for k in range(len(extra)):
                np.multiply(fq, extra[k], out=prod)
                more.append(sp_fft.irfft2(prod, self.fshape, workers=self.workers,
                                          overwrite_x=True))
        np.multiply(fq, self.fkh, out=fq)
        sh = sp_fft.irfft2(fq, self.fshape, workers=self.workers, overwrite_x=True)
        del fq
        if extra is not None:
            return sv[c:c + ny, c:c + nx + 1], sh[c:c + ny + 1, c:c + nx], more
        return sv[c:c + ny, c:c + nx + 1], sh[c:c + ny + 1, c:c + nx]

    def apply_stack(self, charges):
        """Swept areas of a stack of images of the operator's shape.

        Parameters
        ----------
        charges : ndarray, shape (k, ny, nx)
            Charge images (e).

        Returns
        -------
        sv : ndarray, shape (k, ny, nx + 1)
        sh : ndarray, shape (k, ny + 1, nx)
            Views, in the operator's ``dtype`` (px^2). One batched transform
            for the whole stack.
        """
        q = np.asarray(charges, self.dtype)
        if q.ndim != 3 or q.shape[1:] != (self.ny, self.nx):
            raise InputError(f"expected a stack of shape (k, {self.ny}, {self.nx}), got {q.shape}")
        fq = sp_fft.rfft2(q, self.fshape, axes=(-2, -1), workers=self.workers)
        c, ny, nx = self.c, self.ny, self.nx
        sv = sp_fft.irfft2(fq * self.fkv, self.fshape, axes=(-2, -1), workers=self.workers,
                           overwrite_x=True)
        np.multiply(fq, self.fkh, out=fq)
        sh = sp_fft.irfft2(fq, self.fshape, axes=(-2, -1), workers=self.workers,
                           overwrite_x=True)
        return sv[:, c:c + ny, c:c + nx + 1], sh[:, c:c + ny + 1, c:c + nx]


class OperatorCache:
    """:class:`SweptAreas` operators of one template, kept by image shape.

    Parameters
    ----------
    template : DistortionTemplate
        Green's function.
    workers : int, optional
        FFT threads.
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the transforms.
    max_shapes : int, optional
        Operators kept; the oldest is dropped beyond this (each holds two
        kernel transforms of its padded shape).
    """

    def __init__(self, template, *, workers=1, dtype=np.float64, max_shapes=16):
        self.template = template
        self.workers = workers
        self.dtype = np.dtype(dtype)
        self.max_shapes = int(max_shapes)
        self._ops = {}
        self._scratch = _ThreadArrays()
        self._lock = threading.Lock()
        #: Largest sum of abs(kernel) over one edge (px^2 per electron): a bound
        #: on abs(swept area) per electron of the largest abs(charge) in reach.
        self.kernel_abs_sum = kernel_abs_sum(template)

    def __call__(self, shape):
        """The operator for images of ``shape`` (built on first use)."""
        shape = (int(shape[0]), int(shape[1]))
        with self._lock:  # shared by the threads of a dask worker
            op = self._ops.get(shape)
            if op is None:
                if len(self._ops) >= self.max_shapes:
                    self._ops.pop(next(iter(self._ops)))
                op = SweptAreas(self.template, shape, workers=self.workers, dtype=self.dtype)
                self._ops[shape] = op
        return op

    def scratch(self, name, shape, dtype):
        """A work array kept between calls (contents undefined).

        Large temporaries of the windowed series (the swept areas of the
        whole image) are reused from one exposure to the next instead of
        being allocated (and page-faulted) anew; each thread has its own.
        """
        return self._scratch.get(name, shape, dtype)

    def matches(self, template, workers, dtype):
        """True if this cache serves ``template`` with these settings."""
        return (template is self.template and workers == self.workers
                and np.dtype(dtype) == self.dtype)


#: Largest area (px^2) the model lets one edge sweep: beyond it boundaries would
#: cross and the linear superposition of the template no longer describes them.
MAX_SWEEP = 1.0


def kernel_abs_sum(template):
    """Largest sum of abs(swept-area kernel) over one edge, px^2 per electron."""
    kv, kh = swept_area_kernels(template)
    return float(max(np.abs(kv).sum(), np.abs(kh).sum()) / template.charge)


def refuse_out_of_range(finite_data, kernel_abs_sum, unit_note=""):
    """Refuse images whose values the brighter-fatter model cannot describe: the one
    range check of every entry point that takes a charge image (the Task, the
    solvers, the geometry maps).

    Parameters
    ----------
    finite_data : ndarray
        The image's finite values (e).
    kernel_abs_sum : float
        :func:`kernel_abs_sum` of the template (px^2 per e).
    unit_note : str, optional
        Appended to the message.

    Raises
    ------
    InputError
        When ``kernel_abs_sum * max|I|`` exceeds :data:`MAX_SWEEP`.
    """
    # max and -min: no full-size temporary for abs()
    peak = max(float(finite_data.max()), -float(finite_data.min())) if finite_data.size else 0.0
    if kernel_abs_sum * peak > MAX_SWEEP:
        raise InputError(
            f"pixel values up to {peak:.3g} e: the template would sweep "
            f"{kernel_abs_sum * peak:.3g} px^2 across an edge (at most {MAX_SWEEP} is "
            f"modelled, i.e. |I| <= {MAX_SWEEP / kernel_abs_sum:.3g} e); mask them (a "
            f"blocking mask plane, or NaN): masked pixels beyond that are interpolated as "
            f"aggressors{unit_note}")

