"""What looks wrong with an input the Task was given: warnings, not refusals.

:func:`input_warnings` names a mask that covers the sources and a bias
pedestal (from :func:`~lsst_bfdrift.images.levels.robust_level`; mask bits
no plane declares are named where the image is read,
:func:`~lsst_bfdrift.images.electrons.to_electrons`). The refusals
(images the model cannot describe) live with the solvers
(:func:`~lsst_bfdrift.templates.swept.refuse_out_of_range`) and with the
reading of an image (:func:`~lsst_bfdrift.images.electrons.to_electrons`).
"""

import numpy as np

from lsst_bfdrift.images.levels import robust_level

__all__ = ["input_warnings", "BLOCKED_BRIGHT_WARN"]


#: Fraction of the bright pixels' charge that, blocked, makes the Task warn.
BLOCKED_BRIGHT_WARN = 0.5


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
    * **A negative image**: a median more than 5 times its robust scatter
      below zero (a flipped sign, a bias subtracted twice): the model
      describes collected charge.

    Median and scatter come from at most :data:`ROBUST_SAMPLE` pixels
    (:func:`~lsst_bfdrift.images.levels.robust_level`).

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
                       f"lsst_bfdrift.images.exposure.read_exposure (named planes) or set "
                       f"blocking_mask_planes")
    if med < -5.0 * max(mad, 1.0):
        out.append(f"median {med:.4g} e, {-med / max(mad, 1.0):.0f} times its scatter below "
                   f"zero: the image is mostly negative (a sign flipped, or a bias subtracted "
                   f"twice?); the correction needs collected charge, e >= 0 but for noise")
    if med > 1000.0 and mad * mad < 0.1 * med:
        out.append(f"median {med:.4g} e with a scatter of {mad:.3g} e, far below its Poisson "
                   f"noise ({np.sqrt(med):.3g} e): a bias pedestal or an image in ADU? The "
                   f"correction needs post-ISR images in electrons (bias subtracted, gain "
                   f"applied)")
    return out
