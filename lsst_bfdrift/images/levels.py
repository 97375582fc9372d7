"""Levels of an image: its robust median and scatter, and the plateau of a clipped one.

:func:`robust_level` gives the median and robust scatter of an image's
unblocked pixels from an evenly strided sample of a large image;
:func:`plateau_level` finds the level an image without a stated saturation
was clipped at (:func:`~lsst_bfdrift.images.electrons.saturation_level`
uses it, the warnings of :mod:`lsst_bfdrift.correction.checks` use the
former).
"""

import numpy as np

__all__ = ["robust_level", "plateau_level", "plateau_warning", "ROBUST_SAMPLE", "PLATEAU_PIXELS"]


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
        Pixels left out: the plateau is the largest value of the others
        (a blocked pixel above it, a masked hot pixel, hides nothing).

    Returns
    -------
    float or None
    """
    if image.size == 0:
        return None
    if blocked is not None and blocked.any():
        if blocked.all():
            return None
        top = image[~blocked].max()  # a blocked (e.g. hot) pixel above it hides nothing
        n = int(np.count_nonzero((image == top) & ~blocked))
    else:
        top = image.max()
        n = int(np.count_nonzero(image == top))
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
