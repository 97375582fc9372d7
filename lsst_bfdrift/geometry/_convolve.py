"""FFT convolution of a charge image with a template's boundary kernels.

Shared by the exact moments of :mod:`lsst_bfdrift.geometry.superpose` (the
whole image, block by block) and of the exact windows of
:mod:`lsst_bfdrift.geometry._exact`: every boundary channel's displacement
field is a 2-d convolution of the charge with a fixed kernel
(:class:`Convolver`), taken over the rows that reach a block of pixel rows
(:func:`block_stack`).
"""

import numpy as np
from scipy import fft as sp_fft

__all__ = ["Convolver", "block_stack"]


class Convolver:
    """FFT convolution of one image block with the template's kernels.

    The kernels (every boundary channel, divided by the template charge) are
    transformed once per padded block shape and kept as one stacked array;
    the block's transform is multiplied by all of them and transformed back
    in one batched call.

    Parameters
    ----------
    template : DistortionTemplate
        The Green's function (its channels: the corners' x and y, the
        vertical then the horizontal edge samples, then the tangential ones
        if any).
    dtype : {numpy.float64, numpy.float32}, optional
        Precision of the transforms.
    """

    def __init__(self, template, *, dtype=np.float64):
        self.t = template
        self.dtype = np.dtype(dtype)
        n1 = template.size + 1
        ns = template.edge_samples
        tang = template.vedge_t is not None
        nch = 2 + 2 * ns * (2 if tang else 1)
        k = np.zeros((nch, n1, n1))
        k[0], k[1] = template.corner_d[..., 0], template.corner_d[..., 1]
        k[2:2 + ns, :-1, :] = np.moveaxis(template.vedge_d, -1, 0)
        k[2 + ns:2 + 2 * ns, :, :-1] = np.moveaxis(template.hedge_d, -1, 0)
        if tang:
            o = 2 + 2 * ns
            k[o:o + ns, :-1, :] = np.moveaxis(template.vedge_t, -1, 0)
            k[o + ns:o + 2 * ns, :, :-1] = np.moveaxis(template.hedge_t, -1, 0)
        self.kernels = (k / template.charge).astype(self.dtype)
        self._cache = {}

    def kernel_ffts(self, shape, workers=1):
        """The kernels' transforms padded to ``shape`` (kept for the last shape)."""
        if shape not in self._cache:
            self._cache.clear()
            self._cache[shape] = sp_fft.rfft2(self.kernels, shape, axes=(-2, -1),
                                              workers=workers)
        return self._cache[shape]

    def stack(self, block, workers=1):
        """Full convolutions of ``block`` with every kernel, shape (nch, rows, cols)."""
        n1 = self.t.size + 1
        shape = (sp_fft.next_fast_len(block.shape[0] + n1 - 1, real=True),
                 sp_fft.next_fast_len(block.shape[1] + n1 - 1, real=True))
        fk = self.kernel_ffts(shape, workers)
        fb = sp_fft.rfft2(block.astype(self.dtype, copy=False), shape, workers=workers)
        prod = fk * fb
        del fb
        return sp_fft.irfft2(prod, shape, axes=(-2, -1), workers=workers, overwrite_x=True)


def block_stack(conv, charge, r0, r1, workers=1):
    """Displacement channels reaching pixel rows r0..r1-1, and the row offset.

    Corner (r0 + J, I) (the lower left one of pixel (r0 + J, I)) and the
    edges of pixel (r0 + J, I) are at ``stack[:, J + ro, I + c]`` (c the
    template's centre), in the channel order of :class:`Convolver`.
    """
    c = conv.t.center
    ny = charge.shape[0]
    # Aggressor rows that can reach corner rows r0..r1: ja in [r0 - c, r1 + c].
    a0 = max(r0 - c - 1, 0)
    a1 = min(r1 + c + 1, ny)
    # D[J] = F[J + c] in full-image rows; in block rows F_b[m] with m = J + c - a0.
    return conv.stack(charge[a0:a1], workers=workers), r0 + c - a0
