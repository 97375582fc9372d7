"""What looks wrong with an input the Task was given: warnings, not refusals.

:func:`input_warnings` names a mask that covers the sources and a bias
pedestal; :func:`robust_level` gives the median and robust scatter it uses,
from an evenly strided sample of a large image; :func:`plateau_level` finds
the level an image without a stated saturation was clipped at. The
refusals (images the model cannot describe) live with the solvers
(:func:`~lsst_bfdrift.templates.swept.refuse_out_of_range`).
"""

import numpy as np

from lsst_bfdrift.utils.exposure import undeclared_bits

__all__ = ["input_warnings", "mask_warnings", "robust_level", "plateau_level", "plateau_warning",
           "BLOCKED_BRIGHT_WARN", "ROBUST_SAMPLE", "PLATEAU_PIXELS"]


#: Fraction of the bright pixels' charge that, blocked, makes the Task warn.
BLOCKED_BRIGHT_WARN = 0.5


#: Largest number of pixels :func:`robust_level` reads (an evenly strided sample).
ROBUST_SAMPLE = 1 << 20


#: Unblocked pixels that must share the image's largest value exactly for
#: :func:`plateau_level` to take it as the saturation level.
PLATEAU_PIXELS = 3


def plateau_level(image, blocked=None):
    """The level an image was clipped at: its largest value, when at least
    :data:`PLATEAU_PIXELS` unblocked pixels (and not most of the image) share
    it exactly and it stands more than 10 sigma above the median (robust
    scatter, at least the Poisson noise of the median); else None.

    A star's peak is shared by no other pixel of a noisy image; a value that
    several pixels share exactly is where the read-out (or a clipping step)
    stopped. The level test keeps the largest counts of an integer sky,
    which several pixels can share by chance, from passing for a plateau.
    Used when no saturation level is stated (the Task's ``saturation``, a
    SATURATE keyword), with a warning.

    Parameters
    ----------
    image : ndarray
        Finite values (e).
    blocked : ndarray of bool, optional
        Pixels left out of the count (a largest value that only blocked
        pixels hold is not a plateau).

    Returns
    -------
    float or None
    """
    if image.size == 0:
        return None
    top = image.max()
    eq = image == top
    n = int(np.count_nonzero(eq))
    if n < PLATEAU_PIXELS:
        return None
    if blocked is not None:
        n = int(np.count_nonzero(eq & ~blocked))
    if n < PLATEAU_PIXELS or n > image.size // 2:
        return None
    med, mad = robust_level(image, np.zeros(image.shape, bool) if blocked is None else blocked)
    if med is not None and not top > med + 10.0 * max(mad, np.sqrt(max(med, 1.0))):
        return None
    return float(top)


def plateau_warning(image, level, remedy):
    """The warning for a saturation level taken from :func:`plateau_level`:
    how many pixels of ``image`` hold ``level`` (e), what was done, and
    ``remedy`` (how to state the level instead)."""
    n = int(np.count_nonzero(image == level))
    return (f"no saturation level given: {n} pixels share the image's largest value, "
            f"{level:.6g} e (a flat top: the image was clipped there); {remedy}")


def robust_level(image, blocked, *, sample=ROBUST_SAMPLE):
    """Median and robust scatter (1.4826 x the median absolute deviation) of
    the unblocked pixels, e.

    Beyond ``sample`` pixels both come from every k-th pixel in memory
    order, k odd (a fixed, evenly spread sample: rows and columns of a
    power-of-two image all take part), for the warnings' thresholds. The
    median's sampling error is about 1.25 sigma / sqrt(sample), 1e-3 of the
    scatter at the default; the full image's median and MAD took a third of
    an astier23 correction of a 4k x 4k CCD.

    Parameters
    ----------
    image : ndarray
        Finite values (e).
    blocked : ndarray of bool
        Pixels left out.
    sample : int, optional
        Largest number of pixels read.

    Returns
    -------
    median, scatter : float or None
        None when fewer than 16 pixels are left.
    """
    flat, blk = image.ravel(), blocked.ravel()
    step = max(1, -(-flat.size // int(sample)))
    step += 1 - step % 2  # odd
    if step > 1:
        flat, blk = flat[::step], blk[::step]
    good = flat[~blk] if blk.any() else flat
    if good.size < 16:
        return None, None
    med = float(np.median(good))
    return med, float(np.median(np.abs(good - med))) * 1.4826


def input_warnings(image, blocked):
    """What looks wrong with an input the Task was given (messages; empty if nothing).

    * **Most of the bright charge blocked**: more than
      :data:`BLOCKED_BRIGHT_WARN` of the charge in pixels 10 sigma above the
      median sits in blocked pixels. A mask that covers the sources (e.g. a
      DETECTED plane read as a boolean mask by ``CCDData.read(hdu_mask=...)``)
      leaves them uncorrected although the solver converges.
    * **A bias pedestal**: a median above 1000 e whose robust scatter is far
      below its Poisson noise (variance < 10 % of the median) is an image in
      ADU with its bias in, not post-ISR electrons.

    Median and scatter come from at most :data:`ROBUST_SAMPLE` pixels
    (:func:`robust_level`).

    Parameters
    ----------
    image : ndarray
        The image in electrons (finite values).
    blocked : ndarray of bool

    Returns
    -------
    list of str
    """
    out = []
    med, mad = robust_level(image, blocked)
    if med is None:
        return out
    thresh = med + 10.0 * max(mad, np.sqrt(max(med, 1.0)))
    bright = image > thresh
    total = float(np.sum(image[bright] - med)) if bright.any() else 0.0
    if total > 0 and blocked.any():
        frac = float(np.sum((image - med)[bright & blocked])) / total
        if frac > BLOCKED_BRIGHT_WARN:
            out.append(f"{100 * frac:.0f} % of the charge in bright pixels (> {thresh:.3g} e) "
                       f"is blocked by the mask, so those sources are not corrected; is an "
                       f"informational plane (DETECTED) part of the mask? Read LSST files with "
                       f"lsst_bfdrift.utils.exposure.read_exposure (named planes) or set "
                       f"blocking_mask_planes")
    if med > 1000.0 and mad * mad < 0.1 * med:
        out.append(f"median {med:.4g} e with a scatter of {mad:.3g} e, far below its Poisson "
                   f"noise ({np.sqrt(med):.3g} e): a bias pedestal or an image in ADU? The "
                   f"correction needs post-ISR images in electrons (bias subtracted, gain "
                   f"applied)")
    return out


def mask_warnings(exposure, kind):
    """A bit-plane mask with bits set that no plane declares: they never block
    (their meaning is unknown), which the user should know.

    Parameters
    ----------
    exposure : object
        The Task's input.
    kind : str
        Its kind as :func:`~lsst_bfdrift.correction.task.unpack_exposure`
        gives it; only 'exposure' (a
        :class:`~lsst_bfdrift.utils.exposure.MaskedExposure`) and 'afw' carry
        bit planes.

    Returns
    -------
    list of str
    """
    if kind == "exposure":
        mask, planes = exposure.mask, exposure.mask_planes
    elif kind == "afw":
        mask, planes = np.asarray(exposure.mask.array), exposure.mask.getMaskPlaneDict()
    else:
        return []
    bits = undeclared_bits(mask, planes)
    if not bits:
        return []
    n = int(np.count_nonzero(mask & sum(1 << b for b in bits)))
    return [f"mask bits {bits} are set in {n} pixels but no MP_<NAME> card declares them: "
            f"those pixels are not blocked (declared planes: {sorted(planes) or 'none'}); "
            f"declare the planes in the MASK header to use them"]
