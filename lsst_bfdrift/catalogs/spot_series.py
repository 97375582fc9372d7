"""A spot series ready for calibration: images, grid, rows, slopes, corrected or predicted.

:class:`SpotSeries` reads the images of a spot series
(:func:`~lsst_bfdrift.catalogs.spots.read_spot_images`), finds the grid
once (:func:`~lsst_bfdrift.catalogs.spots.find_spots`) and measures every
spot in every image (:func:`~lsst_bfdrift.catalogs.spots.measure_spots`).
Its slopes (:func:`~lsst_bfdrift.catalogs.spot_slopes.spot_slopes`) are the
spot route's data, in the form the star route holds a field's
(:meth:`lsst_bfdrift.calibration.star_fit.StarField.slopes`): a template is
judged either by correcting the images with it and measuring the same spots
with the same weight again (:meth:`SpotSeries.slopes`; a right template
leaves zero slopes), or by the slopes it predicts for the measured rows
(:meth:`SpotSeries.predict`; a right template predicts the measured ones).
"""

import numpy as np
from astropy import units as u
from astropy.nddata import CCDData

from lsst_bfdrift.catalogs.spot_slopes import predict_spot_slopes, slope_values, spot_slopes
from lsst_bfdrift.catalogs.spots import (MIN_SNR, MIN_SPOTS, SPOT_QUANTITIES, find_spots,
                                         measure_spots, read_spot_images)
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.utils.errors import InputError

__all__ = ["SpotSeries", "MIN_IMAGES"]

#: Fewest images of a series (and at least two exposure times).
MIN_IMAGES = 3


class SpotSeries:
    """The images of a spot series, their grid and per-spot rows.

    Parameters
    ----------
    images : sequence
        Paths, arrays (electrons) or CCDData/NDData, one per exposure
        (:func:`~lsst_bfdrift.catalogs.spots.read_spot_images`).
    gain, saturation, exptimes, names
        See :func:`~lsst_bfdrift.catalogs.spots.read_spot_images`.
    weight_sigma : float, optional
        Sigma of the fixed weight (px); default from the spots
        (:func:`~lsst_bfdrift.catalogs.spots.find_spots`).
    min_snr : float, optional
        Rows below this signal-to-noise ratio are not fitted.
    min_spots : int, optional
        Fewest spots in the grid and detected in every image.
    grid : SpotGrid, optional
        A grid found already (e.g. on the uncorrected images).
    find_kwargs : dict, optional
        Other options of :func:`~lsst_bfdrift.catalogs.spots.find_spots`.
    gain_name, saturation_name : str, optional
        How messages name the options.
    progress : bool, optional
        Progress bars on stderr.

    Attributes
    ----------
    exposures : list of SpotExposure
    grid : SpotGrid
    catalog : QTable
        One row per image and spot.

    Raises
    ------
    InputError
        Any refusal of the steps, and a series of fewer than
        :data:`MIN_IMAGES` images or of a single exposure time.
    """

    def __init__(self, images, *, gain=None, saturation=None, exptimes=None, names=None,
                 weight_sigma=None, min_snr=MIN_SNR, min_spots=MIN_SPOTS, grid=None,
                 find_kwargs=None, gain_name="gain", saturation_name="saturation",
                 progress=False):
        self.exposures = read_spot_images(images, gain=gain, saturation=saturation,
                                          exptimes=exptimes, names=names, gain_name=gain_name,
                                          saturation_name=saturation_name)
        n = len(self.exposures)
        times = sorted({ex.exptime for ex in self.exposures})
        if n < MIN_IMAGES or len(times) < 2:
            raise InputError(f"a spot series needs at least {MIN_IMAGES} images at 2 or more "
                             f"exposure times (the same spots at several fluxes); got {n} "
                             f"image{'s' if n != 1 else ''} at {len(times)} exposure "
                             f"time{'s' if len(times) != 1 else ''}")
        self.min_snr, self.min_spots, self.progress = float(min_snr), int(min_spots), progress
        self.grid = grid if grid is not None else find_spots(
            self.exposures, weight_sigma=weight_sigma, min_spots=min_spots,
            **dict(find_kwargs or {}))
        self.catalog = measure_spots(self.exposures, self.grid, min_snr=min_snr,
                                     min_spots=min_spots, progress=progress)
        self._corrected = {}

    @property
    def names(self):
        """The images' names, in series order."""
        return [ex.name for ex in self.exposures]

    def corrected_catalog(self, template):
        """Rows of the same spots after a drift correction of every image with
        ``template`` (None: the measured rows), measured on the same grid with
        the same weight. Kept per template."""
        if template is None:
            return self.catalog
        key = id(template)
        if key not in self._corrected:
            corrected = []
            for ex in self.exposures:
                cfg = BrighterFatterDriftConfig(method="drift", compute_geometry=False,
                                                saturation=ex.saturation)
                res = BrighterFatterDriftTask(config=cfg, template=template).run(
                    CCDData(ex.data, unit=u.electron, mask=ex.bad))
                corrected.append(ex.with_data(np.asarray(res.exposure.data, float)))
            cat = measure_spots(corrected, self.grid, min_snr=self.min_snr, min_spots=None)
            # the measured rows' exclusions hold: the same spots are compared
            cat["use"] = np.asarray(cat["use"]) & np.asarray(self.catalog["use"])
            self._corrected[key] = (template, cat)  # the template kept: its id stays unique
        return self._corrected[key][1]

    def fit(self, template=None, *, use=None, quantities=SPOT_QUANTITIES):
        """:func:`~lsst_bfdrift.catalogs.spot_slopes.spot_slopes` of the rows
        (after a correction with ``template``; None: as measured)."""
        cat = self.corrected_catalog(template)
        if use is not None:
            use = np.asarray(use, bool) & np.asarray(cat["use"], bool)
        return spot_slopes(cat, quantities=quantities, use=use)

    def slopes(self, template=None, *, use=None, quantities=("size", "e1", "e2")):
        """(slope, error) per 1e5 e of each quantity after a correction with
        ``template`` (None: as measured), in the form of
        :meth:`lsst_bfdrift.calibration.star_fit.StarField.slopes`
        (:func:`~lsst_bfdrift.catalogs.spot_slopes.slope_values`)."""
        return slope_values(self.fit(template, use=use, quantities=quantities),
                            quantities=quantities)

    def predict(self, template, *, model="gaussian", use=None, quantities=SPOT_QUANTITIES,
                measured=None):
        """The slopes ``template`` predicts for the measured rows
        (:func:`~lsst_bfdrift.catalogs.spot_slopes.predict_spot_slopes`)."""
        return predict_spot_slopes(self.catalog, template, exposures=self.exposures,
                                   model=model, use=use, quantities=quantities,
                                   measured=measured, progress=self.progress)
