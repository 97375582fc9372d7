"""Spot series shared by the spot-calibration tests (drawn once per process).

:func:`forward_spot_images` records a grid of Gaussian spots through a
template with the package's drift forward model
(:func:`~lsst_bfdrift.correction.solvers.recorded_image`). Every spot takes
one of a few sub-pixel phases, and spots of one phase and image are the same
recorded stamp, so a series costs a few recordings per image; the images
are otherwise noise-free (1 e of Gaussian read noise), while the
measurement's errors are those of the spots' Poisson noise: the fit weighs
the spots as it would weigh real ones, and what it does with them is not
blurred by noise.
"""

import functools

import numpy as np

from tests.calibration.test_star_fit import _calibration
from lsst_bfdrift.correction.solvers import recorded_image
from lsst_bfdrift.templates.refine import curl_free_template
from lsst_bfdrift.templates.swept import SweptAreas

#: Mean spot flux of each image (e): the brightest peaks at 7e4 e, within the
#: modelled range of the strength-10 templates of the tests.
LEVELS = np.geomspace(2e4, 1e6, 5)


def _gaussian(side, x0, y0, sigma):
    """A unit-flux circular Gaussian sampled at the pixel centres of a side x side stamp."""
    jj, ii = np.mgrid[:side, :side]
    g = np.exp(-0.5 * ((ii - x0) ** 2 + (jj - y0) ** 2) / sigma ** 2)
    return g / g.sum()


def forward_spot_images(template, *, grid=5, pitch=26, levels=LEVELS, sigma=1.5, n_phases=4,
                        read_noise=1.0, seed=7, margin=20):
    """A spot series recorded through ``template`` by the drift forward model.

    Parameters
    ----------
    template : DistortionTemplate
    grid : int
        Spots along x and y.
    pitch : int
        Spacing (px); 26 keeps 1.5 px spots uncrowded for the default weight.
    levels : array_like
        Spot flux of each image (e); the exposure times are ``levels / 1e5`` s.
    sigma : float
        Spot sigma (px).
    n_phases : int
        Distinct sub-pixel phases (spot k takes phase k mod n_phases).
    read_noise : float
        Gaussian noise (e rms).
    seed : int
    margin : int
        Distance (px) of the outer spots from the image edge.

    Returns
    -------
    images : list of ndarray
        One per level (e).
    exptimes : list of float
        s.
    """
    rng = np.random.default_rng(seed)
    side, h = 31, 15
    shape = (pitch * (grid - 1) + 2 * margin,) * 2
    phases = [(rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5)) for _ in range(n_phases)]
    swept = SweptAreas(template, (side, side))
    images = []
    for f in levels:
        stamps = [recorded_image(f * _gaussian(side, h + px, h + py, sigma), swept)
                  for px, py in phases]
        img = np.zeros(shape)
        for k in range(grid * grid):
            x, y = margin + pitch * (k % grid), margin + pitch * (k // grid)
            img[y - h:y + h + 1, x - h:x + h + 1] += stamps[k % n_phases]
        images.append(img + rng.normal(0.0, read_noise, shape))
    return images, list(np.asarray(levels) / 1e5)


@functools.lru_cache(maxsize=None)
def curl_free_spots():
    """Spots of a sensor whose boundary shifts are curl-free, with the flats template's areas.

    The flats template T_a of ``test_star_fit._calibration`` (GalSim ITL's
    a-matrix at strength 10, on the bundled model) holds the model's
    divergence-free part; the truth here is
    :func:`~lsst_bfdrift.templates.refine.curl_free_template` of it: the same
    a_ij, none of that part (T_a plus -1 step of ``curl``).

    Returns
    -------
    truth : DistortionTemplate
    images : list of ndarray
    exptimes : list of float
    """
    truth = curl_free_template(_calibration().template)
    images, exptimes = forward_spot_images(truth)
    return truth, images, exptimes
