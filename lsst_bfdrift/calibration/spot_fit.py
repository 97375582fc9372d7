"""Calibrate on spot-projector series too: the anisotropy the a-matrix cannot see.

Flats measure the a-matrix: the net area change of each pixel, the
divergence of the boundary shifts. How that change divides between a
pixel's serial and parallel edges (the divergence-free part of the shifts)
is invisible to them, and it sets the e1 slope of every source: a
flat-calibrated template leaves about 12 % of GalSim ITL stars' e1 slope,
and LSSTCam's spot data show about 10 % left along rows and columns
(Broughton et al. 2024). A spot series
(:class:`~lsst_bfdrift.catalogs.spot_series.SpotSeries`) sees the same spots
at many fluxes with no PSF variation from spot to spot, so it measures its
e1 slope as well as its size slope, where a star field measures e1 only to
about its own size.

:func:`calibrate_with_spots` fits the flats template T_a to the a-matrix and
to one or several spot series (and, if given, star fields) together, by the
star route's machinery
(:func:`~lsst_bfdrift.calibration.star_fit.joint_calibration`): the same
directions (those of the a-matrix's errors, and ``curl``), the same
linearised fit with Gauss-Newton steps, the same chi2, tension and
cross-validation. A spot series enters as a :class:`SpotField`, which
stands in for a :class:`~lsst_bfdrift.calibration.star_fit.StarField`:

* its slopes (size = ln T, e1, e2 per 1e5 e) are those of
  :meth:`SpotSeries.slopes <lsst_bfdrift.catalogs.spot_series.SpotSeries.slopes>`:
  every image corrected by the Task (drift) with the template, the same
  spots measured on the same grid with the same fixed weight, and the
  common slope fitted with one intercept per spot; a right template leaves
  zero. Their errors are the spot fit's (the largest of the formal error
  and its image-to-image and spot-to-spot Birge scalings), not a bootstrap;
* it fits its **e1** slope (and size and e2, :data:`SPOT_FITTED_SLOPES`):
  the star route fits size alone by default, as a field's e1 is mostly
  noise;
* the direction ``curl`` (T_a minus the curl-free template with its areas:
  it moves the e1 slope and no a_ij) is **always in the fit** when spot
  series are given (:data:`SPOT_DIRECTIONS`), with its prior of 3 steps,
  rather than chosen by the ln N test: it is the direction the spots are
  there to measure. The directions of the a-matrix's errors move e1 too,
  at their chi2 cost, so the fit divides the e1 change between the
  template's divergence-free part (free for the a-matrix) and the lags (as
  their errors allow);
* those directions span the a-matrix's **full** errors
  (``keep_lag_sum=False``): a change of the measured lags' area sum (most
  of it a00's) moves area between the measured lags and the far ones
  beyond them, at its chi2 cost. The star route keeps that sum, as a
  field's noisy size slope would move the far lags, which nothing else
  measures; spots of two sizes measure their size slopes to a fraction of
  a per cent, and the far area is what sets them apart: on GalSim's spots
  of 1 and 2 px the flats template from GalSim's a-matrix over-corrects the
  2 px spots' size slope about twice as much as the 1 px spots', and with
  the sum kept no template of the fit matches both
  (``benchmarks/calibration/spots_stars.py``);
* its halves (two-fold cross-validation, ``holdout`` 'cross', and 'split')
  are halves of its **spots**, paired by their mean flux (the projector's
  illumination), every image of a spot on one side; or halves of its
  **images** (``split_by='images'``, paired by exposure time), every spot
  in both: held-out spots test the template on spots it never saw,
  held-out images on fluxes it never saw;
* what it asks of its slopes is what the drift correction leaves on its
  design with a right template, not zero (``correction_bias``, by default;
  :mod:`~lsst_bfdrift.calibration.spot_bias`): about -2 % of the size slope
  on spots of sigma 1 px, which the correction over-corrects;
* it needs ``min_spots`` usable spots to fit (per half with 'cross';
  :data:`MIN_FIT_SPOTS`), else a clear error with the count and what was
  flagged.

The tension (:func:`~lsst_bfdrift.calibration.star_report.tension_test`)
says whether one template satisfies the a-matrix and the spots, and names
its drivers: the lags the fit moved most (in units of their errors) and the
slopes it left furthest from zero.
"""

import copy
import os
import time

import numpy as np

from lsst_bfdrift.calibration.spot_bias import spot_correction_bias
from lsst_bfdrift.calibration.star_fit import (check_star_inputs, holdout_fields,
                                               joint_calibration, read_star_fields, split_fields)
from lsst_bfdrift.calibration.star_result import STAR_SLOPES
from lsst_bfdrift.calibration.tuning import CalibrationError
from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.catalogs.spots import spot_flag_counts
from lsst_bfdrift.utils.errors import InputError

__all__ = ["SpotField", "calibrate_with_spots", "read_spot_fields", "check_spot_fields",
           "SPOT_FITTED_SLOPES", "SPOT_SPLITS", "SPOT_DIRECTIONS", "MIN_FIT_SPOTS"]

#: The slopes a spot series fits by default (all it measures: no PSF variation).
SPOT_FITTED_SLOPES = ("size", "e1", "e2")
#: How a spot series is halved for the held-out check (``split_by``).
SPOT_SPLITS = ("spots", "images")
#: Model directions always in the fit when spot series are given.
SPOT_DIRECTIONS = ("curl",)
#: Fewest usable spots a series fits (per half with two-fold cross-validation).
MIN_FIT_SPOTS = 4


def _check_slopes(fitted_slopes, name):
    fitted_slopes = tuple(fitted_slopes)
    if not fitted_slopes or set(fitted_slopes) - set(STAR_SLOPES):
        raise InputError(f"{name} must be a non-empty subset of {STAR_SLOPES}, got "
                         f"{fitted_slopes!r}")
    return fitted_slopes


def _series_name(series, k):
    """A label for series ``k``: its files' common prefix and ``*``, else ``spots<k>``."""
    names = series.names
    if all(os.path.sep in n or n.lower().endswith((".fits", ".fit", ".fits.gz"))
           for n in names):
        head = os.path.commonprefix([os.path.basename(n) for n in names])
        if head:
            return os.path.join(os.path.dirname(names[0]), head + "*")
    return f"spots{k}"


def _check_bias(bias):
    """``bias`` as {quantity: (slope, error)} of floats (None: empty)."""
    if bias is None:
        return {}
    try:
        out = {q: (float(bias[q][0]), float(bias[q][1])) for q in STAR_SLOPES if q in bias}
    except (TypeError, ValueError, IndexError) as exc:
        raise InputError(f"bias must map 'size', 'e1', 'e2' to (slope, error) per 1e5 e, got "
                         f"{bias!r}") from exc
    if not all(np.isfinite(v).all() and v[1] >= 0 for v in out.values()):
        raise InputError(f"bias slopes must be finite with errors >= 0, got {out!r}")
    return out


class SpotField:
    """A spot series prepared for the joint calibration, in a star field's place.

    Parameters
    ----------
    series : SpotSeries
        The measured series.
    name : str, optional
        Label in reports (default ``spots``).
    fitted_slopes : sequence of {'size', 'e1', 'e2'}, optional
        The slopes the fit nulls on this series.
    split_by : {'spots', 'images'}, optional
        Halves of the series' spots (paired by mean flux) or of its images
        (paired by exposure time).
    min_spots : int, optional
        Fewest usable spots to fit (per half with 'cross').
    bias : dict, optional
        Quantity -> (slope, error) per 1e5 e: what the drift correction
        leaves on this series' design with a right template
        (:func:`~lsst_bfdrift.calibration.spot_bias.spot_correction_bias`).
        Subtracted from the slopes a correction leaves (its error added in
        quadrature), so that the fit asks for that instead of zero. None
        (the default): zero.

    Attributes
    ----------
    kind : str
        ``'spots'``.
    usable, fit_stars, held_out, half_a, half_b : ndarray of bool
        Per row of ``series.catalog`` (one per image and spot): the rows
        used (unflagged, of spots with two or more of them), fitted, held
        out, and the two halves of :meth:`split`.
    flag_counts : dict
        Rows per flag (:func:`~lsst_bfdrift.catalogs.spots.spot_flag_counts`).

    Raises
    ------
    InputError
        ``fitted_slopes``, ``split_by`` or ``min_spots`` not valid.
    """

    kind = "spots"

    def __init__(self, series, *, name=None, fitted_slopes=SPOT_FITTED_SLOPES,
                 split_by="spots", min_spots=MIN_FIT_SPOTS, bias=None):
        if not isinstance(series, SpotSeries):
            raise InputError(f"series must be a SpotSeries, got {type(series).__name__}")
        if split_by not in SPOT_SPLITS:
            raise InputError(f"split_by must be one of {SPOT_SPLITS}, got {split_by!r}")
        if int(min_spots) < 2:
            raise InputError(f"min_spots must be at least 2 (a slope with one intercept per "
                             f"spot), got {min_spots!r}")
        self.series, self.name = series, name or "spots"
        self.fitted_slopes = _check_slopes(fitted_slopes, "spot fitted_slopes")
        self.split_by, self.min_spots = split_by, int(min_spots)
        self._bias = _check_bias(bias)
        cat = series.catalog
        self.spot, self.image = np.asarray(cat["spot"]), np.asarray(cat["image"])
        self.flux = np.asarray(cat["flux"].value, float)
        use = np.asarray(cat["use"], bool)
        per_spot = np.bincount(self.spot[use], minlength=len(series.grid))
        self.usable = use & (per_spot[self.spot] >= 2)
        counts = spot_flag_counts(cat)
        self.flag_counts = {k: v for k, v in counts.items() if k not in ("used", "rows")}
        self.min_snr = series.min_snr
        self.fit_stars = self.usable.copy()
        self.held_out = np.zeros_like(self.usable)
        self.half_a, self.half_b = self.usable.copy(), np.zeros_like(self.usable)
        self._slopes = {}

    @property
    def bias(self):
        """The correction's own slopes subtracted from the corrected ones:
        ``{quantity: (slope, error)}`` (empty: none)."""
        return dict(self._bias)

    @bias.setter
    def bias(self, value):
        self._bias = _check_bias(value)
        self._slopes = {}  # the kept slopes had the former bias subtracted

    def copy(self):
        """A field of the same series whose split, name and bias can change
        without changing this one. The slopes kept are shared until the copy's
        bias changes (their keys hold the template and the subset)."""
        return copy.copy(self)

    @property
    def n_detections(self):
        """Spots in the grid."""
        return len(self.series.grid)

    def n_spots(self, rows):
        """Distinct spots among ``rows`` (a row mask)."""
        return int(np.unique(self.spot[np.asarray(rows, bool)]).size)

    def split(self, seed):
        """Hold out a seeded half of the usable spots (paired by mean flux) or images
        (paired by exposure time), every row of each on one side."""
        rng = np.random.default_rng(seed)
        if self.split_by == "spots":
            unit = self.spot
            ids = np.unique(unit[self.usable])
            key = np.array([self.flux[self.usable & (unit == k)].mean() for k in ids])
        else:
            unit = self.image
            ids = np.unique(unit[self.usable])
            key = np.array([self.series.exposures[int(k)].exptime for k in ids])
        order = ids[np.argsort(key, kind="stable")]
        hold_ids = []
        for k in range(0, order.size, 2):  # one of each consecutive pair
            pair = order[k:k + 2]
            if pair.size == 2 or rng.random() < 0.5:
                hold_ids.append(pair[rng.integers(pair.size)])
        hold = self.usable & np.isin(unit, hold_ids)
        self.held_out = hold
        self.fit_stars = self.usable & ~hold
        self.half_a, self.half_b = self.fit_stars.copy(), hold.copy()

    def _images(self, rows):
        return int(np.unique([self.series.exposures[int(i)].exptime
                              for i in self.image[np.asarray(rows, bool)]]).size)

    def check_split(self, mode, min_stars=None):
        """Set the rows fitted and held out for ``mode`` (after :meth:`split`) and check
        there are enough spots.

        Parameters
        ----------
        mode : {'cross', 'split', 'last'}
            As :meth:`StarField.check_split
            <lsst_bfdrift.calibration.star_fit.StarField.check_split>`.
        min_stars : int, optional
            Not used: a series needs ``min_spots`` spots (the stars' minimum
            does not apply).

        Returns
        -------
        list of str
            Warnings: the rows excluded, per flag.

        Raises
        ------
        CalibrationError
            Fewer than ``min_spots`` usable spots to fit (per half with
            'cross'), or a fitted half of the images with a single exposure
            time.
        """
        if mode == "split":
            sets = [self.fit_stars]
        else:
            sets = [self.half_a, self.half_b] if mode == "cross" else [self.usable]
            self.fit_stars = self.usable.copy()
            self.held_out = self.usable.copy()
        n_fit = min(self.n_spots(s) for s in sets)
        n_times = min(self._images(s) for s in sets)
        per = " per half (two-fold cross-validation)" if mode == "cross" else ""
        if n_fit < self.min_spots or n_times < 2:
            flagged = ", ".join(f"{v} {k}" for k, v in self.flag_counts.items() if v)
            what = (f"{n_fit} usable spots to fit{per}" if n_fit < self.min_spots else
                    f"a single exposure time to fit{per} (halves of the images)")
            raise CalibrationError(
                f"spot series {self.name}: {what} ({self.n_spots(self.usable)} usable spots of "
                f"the grid's {self.n_detections}, SNR >= {self.min_snr:g}; flagged rows: "
                f"{flagged or 'none'}); need at least {self.min_spots} spots{per} seen at 2 "
                "or more exposure times: a grid of more unsaturated, isolated spots")
        return [f"{self.name}: {v} {k} spot rows excluded"
                for k, v in self.flag_counts.items() if v]

    def corrected_catalog(self, template):
        """Rows of the series after a drift correction with ``template``
        (:meth:`SpotSeries.corrected_catalog
        <lsst_bfdrift.catalogs.spot_series.SpotSeries.corrected_catalog>`; kept per
        template)."""
        return self.series.corrected_catalog(template)

    def slopes(self, template, subset, *, n_boot=0, seed=20151):
        """Size, e1 and e2 slopes (per 1e5 e) of the rows ``subset`` after a drift correction.

        Parameters
        ----------
        template : DistortionTemplate or None
            None: the measured rows.
        subset : ndarray of bool
            Rows of ``series.catalog``.
        n_boot, seed : int, optional
            Not used: the errors are the spot fit's
            (:func:`~lsst_bfdrift.catalogs.spot_slopes.fit_spot_slope`), which
            see the image-to-image and spot-to-spot scatter.

        Returns
        -------
        dict
            ``size``, ``e1``, ``e2``: (slope, error); ``n_stars``: the rows
            fitted (as :meth:`StarField.slopes
            <lsst_bfdrift.calibration.star_fit.StarField.slopes>`).
        """
        subset = np.asarray(subset, bool)
        self.corrected_catalog(template)  # keeps the template, so its id stays unique
        key = (None if template is None else id(template), subset.tobytes())
        if key not in self._slopes:
            out = self.series.slopes(template, use=subset, quantities=STAR_SLOPES)
            if template is not None:
                for q, (b, be) in self._bias.items():
                    out[q] = (out[q][0] - b, float(np.hypot(out[q][1], be)))
            self._slopes[key] = out
        return dict(self._slopes[key])


def _as_series_list(spots):
    """``spots`` as a list of series inputs: one series of images, or several series."""
    if isinstance(spots, (SpotSeries, SpotField)):
        return [spots]
    spots = list(spots)
    if spots and all(isinstance(s, (SpotSeries, SpotField, list, tuple)) for s in spots):
        return spots
    return [spots]


def read_spot_fields(spots, *, gain=None, saturation=None, fitted_slopes=SPOT_FITTED_SLOPES,
                     split_by="spots", min_spots=MIN_FIT_SPOTS, names=None, progress=False):
    """The spot series of :func:`calibrate_with_spots`'s ``spots``, with distinct names.

    Parameters
    ----------
    spots : SpotSeries, SpotField or sequence
        One series (a SpotSeries, or a sequence of image paths, arrays in
        electrons or CCDData/NDData), or several (a sequence of such
        series: SpotSeries, SpotField or sequences of images). SpotField
        objects are taken as they are (copied).
    gain : float, optional
        e/ADU of images in ADU without a GAIN keyword.
    saturation : float, optional
        Saturation level of the images (their unit; default SATURATE).
    fitted_slopes, split_by, min_spots
        Of every new :class:`SpotField` (a SpotField given is copied, so that
        the calibration's split, names and bias leave the caller's as it was).
    names : sequence of str, optional
        One label per series (default: the files' common prefix, else
        ``spots<k>``).
    progress : bool, optional
        Progress bars of the measurement.

    Returns
    -------
    list of SpotField

    Raises
    ------
    CalibrationError
        No spot series.
    InputError
        Any refusal of :class:`~lsst_bfdrift.catalogs.spot_series.SpotSeries`
        (images in ADU without a gain, without EXPTIME, of different
        shapes, too few spots or images), or options not valid.
    """
    items = _as_series_list(spots)
    if not items or any(isinstance(s, (list, tuple)) and not s for s in items):
        raise CalibrationError("no spot series given")
    if names is not None and len(names) != len(items):
        raise InputError(f"names has {len(names)} entries for {len(items)} spot series")
    out = []
    for k, s in enumerate(items):
        if isinstance(s, SpotField):
            out.append(s.copy())  # the caller's field is not split, renamed or biased
            continue
        series = s if isinstance(s, SpotSeries) else SpotSeries(
            list(s), gain=gain, saturation=saturation, progress=progress)
        out.append(SpotField(series, name=names[k] if names else _series_name(series, k),
                             fitted_slopes=fitted_slopes, split_by=split_by,
                             min_spots=min_spots))
    return out


def check_spot_fields(fields, holdout, *, seed=20151, n_stars=0):
    """Refuse spot series too small for the calibration's held-out scheme, before it runs.

    Parameters
    ----------
    fields : sequence of SpotField
    holdout : {'auto', 'cross', 'split', 'last'}
        As :func:`calibrate_with_spots`.
    seed : int, optional
        Seed of the split (the calibration's).
    n_stars : int, optional
        Star fields given too (they come first: 'last' holds out the last
        spot series).

    Raises
    ------
    CalibrationError, InputError
        As :func:`~lsst_bfdrift.calibration.star_fit.holdout_fields` and
        :meth:`SpotField.check_split`.
    """
    mode = holdout_fields([None] * int(n_stars) + list(fields), holdout)[0]
    split_fields([f.copy() for f in fields], mode, seed=seed)  # the fields left unsplit


def calibrate_with_spots(result, spots, *, stars=(), holdout="auto", split_by="spots",
                         seed=20151, max_directions=6, n_boot=200, iterations=2, gain=None,
                         saturation=None, min_snr=30.0, min_stars=30, min_spots=MIN_FIT_SPOTS,
                         flats_uncertainty=True, keep_lag_sum=False, fitted_slopes=("size",),
                         spot_slopes=SPOT_FITTED_SLOPES, scale_star_errors=True,
                         size_goal=3.0, correction_bias=True, bias_centres=3, progress=False):
    """Refit a calibration jointly to its a-matrix and to spot series (and star fields).

    Parameters
    ----------
    result : CalibrationResult
        From :func:`~lsst_bfdrift.calibration.tuning.calibrate` (with its
        template built).
    spots : SpotSeries, SpotField or sequence
        One or several spot series (:func:`read_spot_fields`).
    stars : sequence, optional
        Star fields fitted too (:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`'s
        ``stars``); they come before the spot series.
    holdout : {'auto', 'cross', 'split', 'last'}, optional
        Held-out spots (and stars): 'cross' (and 'auto'), two-fold
        cross-validation over the halves of every series (and field), the
        template fitted to all of them; 'split', one half fitted and the
        other held out; 'last', the last data set held out.
    split_by : {'spots', 'images'}, optional
        The halves of a series: its spots (paired by mean flux) or its images
        (paired by exposure time).
    seed : int, optional
        Seed of the split (and the stars' bootstrap).
    max_directions, n_boot, iterations
        As :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`
        (``n_boot`` serves the stars only).
    gain : float, optional
        e/ADU of spot images and star fields in ADU without a GAIN keyword.
    saturation : float, optional
        Saturation level of the spot images (their unit; default SATURATE).
    min_snr, min_stars
        Of the star fields.
    min_spots : int, optional
        Fewest usable spots a series fits (per half with 'cross').
    flats_uncertainty : bool, optional
        As :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`.
    keep_lag_sum : bool, optional
        As :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`,
        with the opposite default: the spots may move the measured lags'
        area sum, and with it the area the template sends beyond the
        measured lags (module docstring). True keeps the flats template's.
    fitted_slopes : sequence of {'size', 'e1', 'e2'}, optional
        The slopes fitted on the star fields.
    spot_slopes : sequence of {'size', 'e1', 'e2'}, optional
        The slopes fitted on the spot series (default all three: a series
        measures its e1 slope as well as its size slope).
    scale_star_errors, size_goal
        As :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`.
    correction_bias : bool, optional
        Ask of every series (without a ``bias`` of its own) the slopes the
        drift correction leaves on its design with a right template instead
        of zero: :func:`~lsst_bfdrift.calibration.spot_bias.spot_correction_bias`
        with ``result``'s template on ``bias_centres`` x ``bias_centres``
        sub-pixel centres (up to about 30 s per series; the series' field
        records keep it as ``correction_bias``). On GalSim's paired spots of 1
        and 2 px it moves the size slope left on held-out stars by 0.2-0.8 %
        points, toward zero, on the four sensor models of
        ``benchmarks/calibration/spots_stars.py``.
        Default True.
    bias_centres : int, optional
        Sub-pixel centres per side of that simulation.
    progress : bool, optional
        As :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`.

    Returns
    -------
    StarCalibrationResult
        As the star route's; the spot series appear by name in
        ``fit_slopes``, ``held_out`` (with ``kind`` 'spots'; ``n_stars``
        counts spot rows), ``fields`` and the tension's rows; ``directions``
        starts with ``curl``, always in the fit; the template's
        ``meta['calibration']['spots']`` records the fit.

    Raises
    ------
    CalibrationError
        No template in ``result``, no spot series, or a series (or field)
        with too few usable spots (stars) to fit.
    InputError
        Spot images the series refuses (in ADU without a gain, without
        EXPTIME, of different shapes, too few spots or images), or options
        not valid.
    """
    t0 = time.perf_counter()
    fitted_slopes = check_star_inputs(result, fitted_slopes, size_goal)
    spot_slopes = _check_slopes(spot_slopes, "spot_slopes")
    spot_fields = read_spot_fields(spots, gain=gain, saturation=saturation,
                                   fitted_slopes=spot_slopes, split_by=split_by,
                                   min_spots=min_spots, progress=progress)
    if correction_bias:
        for f in spot_fields:
            if not f.bias:  # a series' own stated bias is kept
                f.bias = spot_correction_bias(f.series, result.template,
                                              centres=bias_centres)
    stars = list(stars) if not isinstance(stars, (str, np.ndarray)) else [stars]
    star_fields = read_star_fields(stars, gain=gain, min_snr=min_snr) if stars else []
    fields = star_fields + spot_fields
    names = [f.name for f in fields]
    if len(set(names)) != len(names):
        for k, f in enumerate(fields):
            f.name = f"{f.name}#{k}"
    return joint_calibration(result, fields, holdout=holdout, seed=seed,
                             max_directions=max_directions, n_boot=n_boot,
                             iterations=iterations, min_stars=min_stars,
                             flats_uncertainty=flats_uncertainty, keep_lag_sum=keep_lag_sum,
                             fitted_slopes=fitted_slopes, scale_star_errors=scale_star_errors,
                             size_goal=size_goal, always=SPOT_DIRECTIONS, meta_key="spots",
                             progress=progress, t0=t0)
