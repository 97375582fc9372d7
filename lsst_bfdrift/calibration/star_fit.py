"""Calibrate on the sky too: star fields fitted jointly with the flats' a-matrix.

Flats measure the a-matrix: the net area change of each pixel, the
divergence of the boundary shifts. Stars respond to how the boundaries move,
including the part flats cannot see (Broughton et al. 2024 found a
flat-calibrated correction corrects flats better than stars). A star field
carries that information without truth: after a right correction, star size
and shape no longer depend on flux at fixed position
(:func:`~lsst_bfdrift.catalogs.slopes.shape_flux_relations`).

:func:`calibrate_with_stars` takes the result of
:func:`~lsst_bfdrift.calibration.tuning.calibrate` (the a-matrix fit and its
template T_a) and one or several star fields, and fits

.. math::

    T(c) = T_a + \\sum_k c_k \\, \\Delta T_k

where :math:`\\Delta T_k` is the change of the built template when model
parameter k moves by its step h_k (every candidate of
:data:`~lsst_bfdrift.calibration.fit_model.CANDIDATES`: the directions the
physics allows, including those the a-matrix does not see), plus the
direction ``scale``, T_a itself (an overall strength change, c the
fractional change), and the direction ``curl``: the part of T_a's boundary
shifts that the a-matrix cannot see, T_a minus the curl-free template with
the same areas (:func:`~lsst_bfdrift.templates.refine.curl_free_template`).
It moves how a pixel's area change divides between its serial and parallel
edges, and with it the stars' e1 slope, and leaves every a_ij unchanged
(c = -1 removes it, c = +1 doubles it). With ``flats_uncertainty`` (the
default) there are the directions of the a-matrix's errors: minimum-norm,
curl-free edge shifts that change the measured a_ij by one standard
deviation along each principal axis of their errors, conditioned on the sum
rule (the measured lags' area sum is kept, so no area is pushed into the
unmeasured far lags, unless ``keep_lag_sum=False``, the spot route's default;
:func:`~lsst_bfdrift.templates.refine.area_response_directions`).
They span what the flats leave uncertain: T_a plus their sum with standard
normal coefficients is a template drawn from those errors. They are always
in the fit (not chosen), and each step costs one unit of the a-matrix's
chi2. With them, the model's directions are left out, but ``curl``: they
would undo a model direction's change at the measured lags for free,
leaving a change of the unmeasured far lags alone, which nothing measures
(``flats_uncertainty=False`` fits the model's directions instead, to ask
which physics resolves a tension). So the stars
move the template within the a-matrix's errors, along the combination that
changes their slopes most for the least chi2: a Gaussian update of the
flats' estimate by the stars. It matters where the flats are small: the
flats of ``benchmarks/calibration/calibrate_noise_floor.py`` (800 x 800 px, 36 pairs)
leave GalSim ITL's size slope uncertain by about 12 % rms, and a field of
800 stars measures it to 9-13 %. Both data sets are linear in c:

* the a-matrix: the template's linear area response is linear in its
  displacements, so a(c) = a(T_a) + sum_k c_k alpha(Delta T_k) exactly;
* the stars: each field is corrected by the Task (drift) with T_a and with
  T_a + Delta T_k, and the same stars (same detections, stamps and weights,
  :func:`~lsst_bfdrift.catalogs.catalog.detect_stars`) give the size,
  e1 and e2 slopes (per 1e5 e) and their finite differences.

The chi2 is the a-matrix's, of the template's change from T_a (measured
errors; T_a is the flats' estimate, and its residuals to the measured a_ij,
where the refinement kept the model within their errors, are not refitted),
plus the stars' (slopes / their bootstrap errors; a right correction leaves
zero). By default only the size slopes are fitted: a 2k x 2k field of 800
stars measures its e1 slope no better than its size slope, while the e1
slope is 8-30 times smaller, and the directions of the a-matrix's errors
leave e1 nearly free (one draw of the flats' errors, matched lag by lag,
moves GalSim ITL stars' e1 slope by -65 to +46 % of itself, their size by
-10 to +20 %; ``benchmarks/calibration/calibrate_noise_floor.py``), so the fields' e1
noise would go straight into the template. The
e1 and e2 slopes are still measured, reported and held out
(``fitted_slopes`` adds them). Directions are added one
at a time while the chi2 drops by more than ln N (the same rule as the
a-matrix fit); then c is solved by weighted least squares and refined by
Gauss-Newton steps with exact evaluations of the stars' slopes (the Jacobian
kept). The result reports:

* each data set's chi2 with T_a and with T(c), and the **tension**: the rise
  of the a-matrix chi2 needed to null the star slopes, with its p-value
  (chi2 with as many degrees of freedom as star slopes);
* per direction, the share of its Fisher information that comes from the
  stars;
* **held-out stars**: the slopes, with bootstrap errors, of stars not used
  in the fit, before correction, corrected with T_a and with T(c). Only
  these count as a validation. By default the template is fitted to all the
  stars, and two-fold cross-validation gives the held-out slopes: each field
  is split into two seeded halves paired in flux, the fit (direction choice
  included) is repeated on one half alone and measured on the other, both
  ways. Every star is then measured with a template that never saw it, and
  no star is wasted on validation alone (a single split leaves the template
  half the stars). The directions' corrected catalogs are computed once
  and serve the three fits.

How many stars: the size slope of a field is measured to about
``1 / sqrt(N)`` of its own scatter, the photon noise of the brightest stars'
sizes (:mod:`~lsst_bfdrift.catalogs.slopes`); the validate-sky
benchmark measured it to 15 % (z = 6.6) with 150 stars of 1e4-1.5e6 e on a
1k x 1k ITL field. A star field constrains the template when its
uncorrected size slope is detected at z > 10: several hundred unsaturated,
isolated stars spanning 1e4 to 1e6 e (docs/calibration.rst gives the
figures per sensor).

The steps, each a function of its own:

* the fields (this module): :func:`read_star_fields`, :func:`holdout_fields`
  and :func:`split_fields` (the fit/held-out split and the checks);
* the directions (:mod:`~lsst_bfdrift.calibration.star_basis`):
  :func:`~lsst_bfdrift.calibration.star_basis.direction_basis`, evaluated on
  the fields by :func:`~lsst_bfdrift.calibration.star_basis.evaluated_basis`;
* the fit and the held-out stars (:mod:`~lsst_bfdrift.calibration.star_solve`):
  :func:`~lsst_bfdrift.calibration.star_solve.fit_joint`, with the Birge
  scaling (:func:`~lsst_bfdrift.calibration.star_solve.fit_with_error_scale`),
  then :func:`~lsst_bfdrift.calibration.star_solve.cross_validate` or
  :func:`~lsst_bfdrift.calibration.star_solve.held_out_validation`;
* the report (:mod:`~lsst_bfdrift.calibration.star_report`): the chi2, the
  tension test, the stars' information, the coefficients and the
  precision the fit leaves; then the result
  (:func:`~lsst_bfdrift.calibration.star_result.joint_template`,
  :func:`fitted_star_slopes`, :func:`fields_summary`).

From the fields on, the steps are :func:`joint_calibration`'s, and a spot
series (:class:`~lsst_bfdrift.calibration.spot_fit.SpotField`,
:func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`) takes a
field's place: a data set has a ``name``, a ``kind``, its own
``fitted_slopes`` (None: the calibration's), row masks (``usable``,
``fit_stars``, ``held_out``, ``half_a``, ``half_b``) set by ``split`` and
``check_split``, and ``slopes`` and ``corrected_catalog`` per template.
"""

import copy
import functools
import time

import numpy as np
from astropy import units as u
from astropy.nddata import CCDData

from lsst_bfdrift.calibration.star_basis import AmatrixRows, direction_basis, evaluated_basis
from lsst_bfdrift.calibration.star_report import (direction_coefficients, fit_chi2,
                                                  star_information, tension_test,
                                                  uncertainty_report)
from lsst_bfdrift.calibration.star_result import (STAR_SLOPES, StarCalibrationResult,
                                                  joint_template)
from lsst_bfdrift.calibration.star_solve import (cross_validate, fit_joint,
                                                 fit_with_error_scale, held_out_validation)
from lsst_bfdrift.calibration.tuning import CalibrationError
from lsst_bfdrift.catalogs.catalog import FLAG_NAMES, detect_stars, measure_stars
from lsst_bfdrift.catalogs.slopes import FLUX_UNIT, select_stars, shape_flux_relations
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.templates.refine import area_response_directions
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["StarField", "calibrate_with_stars", "joint_calibration", "check_size_goal",
           "check_star_inputs",
           "read_star_fields", "HOLDOUTS", "holdout_fields", "split_fields", "progress_steps",
           "fitted_star_slopes", "fields_summary"]

#: The ``holdout`` choices of :func:`calibrate_with_stars`.
HOLDOUTS = ("auto", "cross", "split", "last")


class StarField:
    """A star field prepared for the calibration: detections, usable stars, fit/held-out split.

    Parameters
    ----------
    exposure : ndarray, CCDData, NDData or path
        Image in electrons (or ADU with ``gain`` / GAIN keyword); never modified.
    gain, mask, saturation
        See :func:`~lsst_bfdrift.images.electrons.to_electrons`.
    min_snr : float, optional
        Stars below this signal-to-noise ratio are not used.
    name : str, optional
        Label in reports (default the file name or ``field<k>``).
    catalog_kwargs : dict, optional
        Options of :func:`~lsst_bfdrift.catalogs.catalog.detect_stars`.
    detections : StarDetections, optional
        Detections to measure the stars on (e.g. another image's of the same
        scene, so that the two catalogs hold the same stars row by row);
        default: detected on this image.

    Attributes
    ----------
    kind : str
        ``'stars'`` (a spot series is ``'spots'``:
        :class:`~lsst_bfdrift.calibration.spot_fit.SpotField`).
    fitted_slopes : None
        The field fits the calibration's ``fitted_slopes``.
    usable, fit_stars, held_out, half_a, half_b : ndarray of bool
        Per catalog row: the stars used, fitted, held out, and the two
        halves of :meth:`split`.
    """

    kind = "stars"
    fitted_slopes = None

    def __init__(self, exposure, *, gain=None, mask=None, saturation=None, min_snr=30.0,
                 name=None, catalog_kwargs=None, detections=None):
        self.name = name or (str(exposure) if isinstance(exposure, str) else "field")
        image = to_electrons(exposure, gain=gain, mask=mask, saturation=saturation)
        image.warn()
        data, bad, sat_e, g, sat_pix = (image.data, image.bad, image.saturation, image.gain,
                                        image.sat_plane)
        self.data, self.bad, self.saturation, self.gain = data, bad, sat_e, g
        self.detections = detections if detections is not None else detect_stars(
            data, mask=bad, saturation=sat_e, saturated=sat_pix, **dict(catalog_kwargs or {}))
        self.catalog = measure_stars(data, mask=bad, saturation=sat_e,
                                     detections=self.detections)
        self.min_snr = float(min_snr)
        self.usable = select_stars(self.catalog, self.min_snr)
        ny, nx = data.shape
        self.frame = (0.5 * (nx - 1), 0.5 * (ny - 1), 0.5 * nx, 0.5 * ny)
        flags = np.asarray(self.catalog["flags"])
        self.flag_counts = {n[5:]: int(np.sum((flags & b) != 0)) for b, n in FLAG_NAMES.items()}
        self.fit_stars = self.usable.copy()
        self.held_out = np.zeros_like(self.usable)
        self._corrected = {}
        self._slopes = {}

    def split(self, seed):
        """Hold out a seeded random half of the usable stars (stratified by flux)."""
        idx = np.flatnonzero(self.usable)
        order = idx[np.argsort(np.asarray(self.catalog["flux"].value)[idx])]
        rng = np.random.default_rng(seed)
        hold = np.zeros(len(self.catalog), bool)
        for k in range(0, order.size, 2):  # one of each consecutive pair in flux
            pair = order[k:k + 2]
            if pair.size == 2 or rng.random() < 0.5:
                hold[pair[rng.integers(pair.size)]] = True
        self.held_out = hold
        self.fit_stars = self.usable & ~hold
        self.half_a, self.half_b = self.fit_stars.copy(), hold.copy()

    @property
    def n_detections(self):
        """Sources detected (catalog rows)."""
        return len(self.catalog)

    def check_split(self, mode, min_stars):
        """Set the stars fitted and held out for ``mode`` (after :meth:`split`) and check
        there are enough.

        Parameters
        ----------
        mode : {'cross', 'split', 'last'}
            'split' fits half A and holds out half B; 'cross' and 'last' fit
            every usable star and hold every one out.
        min_stars : int
            Fewest stars to fit (per half with 'cross').

        Returns
        -------
        list of str
            Warnings: the saturated, blended and masked stars excluded.

        Raises
        ------
        CalibrationError
            Fewer than ``min_stars`` stars to fit.
        """
        if mode == "split":
            n_fit = int(self.fit_stars.sum())
        else:  # 'last' fits every star of the other fields, 'cross' each half in turn
            n_fit = int(min(self.half_a.sum(), self.half_b.sum())) if mode == "cross" \
                else int(self.usable.sum())
            self.fit_stars = self.usable.copy()
            self.held_out = self.usable.copy()
        if n_fit < min_stars:
            flagged = ", ".join(f"{v} {k}" for k, v in self.flag_counts.items() if v)
            raise CalibrationError(
                f"star field {self.name}: {n_fit} usable stars to fit (SNR >= "
                f"{self.min_snr:g}; flagged: {flagged or 'none'}); need at least {min_stars}, "
                "and several hundred isolated, unsaturated stars of 1e4-1e6 e to constrain the "
                "template")
        warnings = []
        if self.flag_counts.get("saturated"):
            warnings.append(f"{self.name}: {self.flag_counts['saturated']} saturated stars "
                            "excluded")
        if self.flag_counts.get("blended"):
            warnings.append(f"{self.name}: {self.flag_counts['blended']} blended detections "
                            "excluded")
        if self.flag_counts.get("masked"):
            warnings.append(f"{self.name}: {self.flag_counts['masked']} stars with masked or "
                            "non-finite pixels in their aperture excluded")
        return warnings

    def copy(self):
        """A field of the same stars whose split and name can change without
        changing this one. The corrections and slopes kept are shared (their
        keys hold the template and the subset, not the split)."""
        return copy.copy(self)

    def corrected_catalog(self, template):
        """Catalog of the same stars after a drift correction with ``template``
        (None: the uncorrected image). Kept per template: the fit, the
        bootstrap and the held-out stars reuse one correction."""
        if template is None:
            return self.catalog
        key = id(template)
        if key not in self._corrected:
            cfg = BrighterFatterDriftConfig(method="drift", compute_geometry=False,
                                            saturation=self.saturation)
            res = BrighterFatterDriftTask(config=cfg, template=template).run(
                CCDData(self.data, unit=u.electron, mask=self.bad))
            cat = measure_stars(np.asarray(res.exposure.data, float), mask=self.bad,
                                saturation=self.saturation, detections=self.detections)
            self._corrected[key] = (template, cat)  # the template kept: its id stays unique
        return self._corrected[key][1]

    def slopes(self, template, subset, *, n_boot=0, seed=20151):
        """Size, e1 and e2 slopes (per 1e5 e) of ``subset`` after a drift correction.

        ``template`` None: the uncorrected image. Kept per template, subset,
        ``n_boot`` and ``seed``: the fits, the folds and the report ask for the
        same slopes more than once, and the bootstrap is not free.
        """
        subset = np.asarray(subset, bool)
        self.corrected_catalog(template)  # keeps the template, so its id stays unique
        key = (None if template is None else id(template), subset.tobytes(), int(n_boot),
               int(seed))
        if key not in self._slopes:
            cat = self.corrected_catalog(template).copy(copy_data=False)
            cat["use"] = subset
            rel = shape_flux_relations(cat, min_snr=self.min_snr, n_boot=n_boot, seed=seed,
                                       frame=self.frame)
            self._slopes[key] = {k: (rel[k]["slope"], rel[k]["slope_err"]) for k in STAR_SLOPES} \
                | {"n_stars": rel["n_stars"]}
        return dict(self._slopes[key])



def check_size_goal(value, name="size_goal"):
    """Raise InputError unless ``value`` is a finite precision > 0 (% of the
    uncorrected size slope); ``name`` labels it in the message (the CLI checks
    ``--size-goal`` before it reads any file)."""
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a finite precision > 0 (% of the uncorrected "
                         f"size slope), got {value!r}")


def check_star_inputs(result, fitted_slopes, size_goal):
    """Check the calibration and the options of :func:`calibrate_with_stars`.

    Parameters
    ----------
    result : CalibrationResult
    fitted_slopes : sequence of str
    size_goal : float

    Returns
    -------
    tuple of str
        ``fitted_slopes``.

    Raises
    ------
    CalibrationError
        No template (built) in ``result``.
    InputError
        ``fitted_slopes`` not a non-empty subset of :data:`STAR_SLOPES
        <lsst_bfdrift.calibration.star_result.STAR_SLOPES>`, or ``size_goal``
        not valid (:func:`check_size_goal`).
    """
    if result.template is None or result.built_template is None:
        raise CalibrationError("calibrate_with_stars needs a calibration with its template "
                               "built (calibrate(..., build=True))")
    fitted_slopes = tuple(fitted_slopes)
    if not fitted_slopes or set(fitted_slopes) - set(STAR_SLOPES):
        raise InputError(f"fitted_slopes must be a non-empty subset of {STAR_SLOPES}, got "
                         f"{fitted_slopes!r}")
    check_size_goal(size_goal)
    return fitted_slopes


def read_star_fields(stars, *, gain=None, min_snr=30.0):
    """The star fields of :func:`calibrate_with_stars`'s ``stars``, with distinct names.

    Parameters
    ----------
    stars : sequence or one field
        Paths, arrays (electrons), CCDData/NDData or :class:`StarField`
        objects (taken as they are).
    gain : float, optional
        e/ADU of fields in ADU without a GAIN keyword.
    min_snr : float, optional
        Stars below this signal-to-noise ratio are not used.

    Returns
    -------
    list of StarField
        Named by their path, else ``field<k>``; when two names agree, every
        name gets ``#<k>`` appended.

    Raises
    ------
    CalibrationError
        No field, or a field that cannot be read or has no stars.
    """
    stars = list(stars) if not isinstance(stars, (str, np.ndarray, StarField)) else [stars]
    if not stars:
        raise CalibrationError("no star fields given")
    fields = []
    for k, s in enumerate(stars):
        if isinstance(s, StarField):
            fields.append(s.copy())  # the caller's field is not split or renamed
            continue
        name = str(s) if isinstance(s, str) or hasattr(s, "__fspath__") else f"field{k}"
        try:
            fields.append(StarField(s, gain=gain, min_snr=min_snr, name=name))
        except ValueError as exc:
            raise CalibrationError(f"star field {name}: {exc}") from exc
    names = [f.name for f in fields]
    if len(set(names)) != len(names):
        for k, f in enumerate(fields):
            f.name = f"{f.name}#{k}"
    return fields


def holdout_fields(fields, holdout):
    """The held-out scheme, and the fields fitted and those with held-out stars.

    Parameters
    ----------
    fields : list of StarField
    holdout : {'auto', 'cross', 'split', 'last'}
        As :func:`calibrate_with_stars` ('auto' is 'cross').

    Returns
    -------
    mode : {'cross', 'split', 'last'}
    fit_fields, hold_fields : list of StarField
        Every field both, but with 'last': the others fitted, the last held
        out.

    Raises
    ------
    InputError
        ``holdout`` not one of :data:`HOLDOUTS`.
    CalibrationError
        'last' with one field.
    """
    if holdout not in HOLDOUTS:
        raise InputError(f"holdout must be 'auto', 'cross', 'split' or 'last', got {holdout!r}")
    mode = "cross" if holdout == "auto" else holdout
    if mode == "last" and len(fields) < 2:
        raise CalibrationError("holdout='last' needs two or more star fields")
    fit_fields = fields[:-1] if mode == "last" else fields
    hold_fields = fields[-1:] if mode == "last" else fields
    return mode, fit_fields, hold_fields


def split_fields(fields, mode, *, seed=20151, min_stars=30):
    """Split every data set for ``mode`` and check there are enough stars or spots to fit.

    Every data set is split in two seeded halves (:meth:`StarField.split`:
    stars paired in flux; :meth:`SpotField.split
    <lsst_bfdrift.calibration.spot_fit.SpotField.split>`: spots paired in
    flux, or images). 'split' fits one half and holds out the other;
    'cross' and 'last' fit every usable star (and hold every one out:
    'cross' measures each half with the other half's fit, 'last' the last
    data set's stars).

    Parameters
    ----------
    fields : list of StarField or SpotField
    mode : {'cross', 'split', 'last'}
    seed : int, optional
        Seed of the split.
    min_stars : int, optional
        Fewest stars to fit per field (per half with 'cross'); a spot
        series has its own minimum of spots (``min_spots``).

    Returns
    -------
    list of str
        Warnings: the saturated, blended and masked stars (or spot rows)
        excluded.

    Raises
    ------
    CalibrationError
        A data set with too few stars or spots to fit (the message counts
        them and what was flagged).
    """
    warnings = []
    for f in fields:
        f.split(seed)
        warnings += f.check_split(mode, min_stars)
    return warnings


def progress_steps(n_model, n_lag_dirs, n_fit_fields, n_hold_fields, mode, iterations):
    """Steps of :func:`calibrate_with_stars`'s progress bar.

    Parameters
    ----------
    n_model : int
        Model directions tried (the candidates and ``scale``; 0 with the
        lag directions).
    n_lag_dirs : int
        Directions of the a-matrix's errors.
    n_fit_fields, n_hold_fields : int
        Fields fitted, and with held-out stars.
    mode : {'cross', 'split', 'last'}
    iterations : int
        Gauss-Newton steps.

    Returns
    -------
    int
        One per field and direction evaluated, and per held-out field,
        template and fold; per field, the star evaluations of every fit
        (three fits with 'cross') if each takes all its Gauss-Newton steps;
        and ``n_model + 2`` for the directions built (the model's candidates
        and ``curl`` tick one each). An upper bound: the bar is filled at
        the end.
    """
    n_fits = 3 if mode == "cross" else 1
    return n_model + 2 + n_fit_fields * (n_model + 1 + n_lag_dirs + n_fits * (iterations + 1)) \
        + n_hold_fields * 3 * (2 if mode == "cross" else 1)


def fitted_star_slopes(fields, flats_template, joint_template, *, n_boot=200, seed=20151):
    """Slopes of the fitted stars: uncorrected, with the flats template and the joint one.

    Parameters
    ----------
    fields : sequence of StarField
        The fitted fields (``fit_stars``).
    flats_template, joint_template : DistortionTemplate
    n_boot, seed : int, optional
        Bootstrap of the errors.

    Returns
    -------
    dict
        Field name -> ``before``, ``flats_only``, ``joint``:
        :meth:`StarField.slopes`.
    """
    return {f.name: {"before": f.slopes(None, f.fit_stars, n_boot=n_boot, seed=seed),
                     "flats_only": f.slopes(flats_template, f.fit_stars, n_boot=n_boot,
                                            seed=seed),
                     "joint": f.slopes(joint_template, f.fit_stars, n_boot=n_boot, seed=seed)}
            for f in fields}


def fields_summary(fields, fit_fields, hold_fields):
    """Per data set: name, kind, detections, usable, fitted and held-out stars, flag counts.

    Parameters
    ----------
    fields, fit_fields, hold_fields : sequence of StarField or SpotField
        Every data set, those fitted and those with held-out stars.

    Returns
    -------
    list of dict
        ``name``, ``kind`` (``stars`` or ``spots``), ``n_detections``
        (sources detected; spots in the grid), ``n_usable``, ``n_fit``,
        ``n_held_out`` (stars; spot rows, one per spot and image),
        ``flagged`` (counts per flag) and, for a spot series fitted with one,
        ``correction_bias`` (quantity -> (slope, error) per 1e5 e).
    """
    return [{"name": f.name, "kind": f.kind, "n_detections": f.n_detections,
             "n_usable": int(f.usable.sum()),
             "n_fit": int(f.fit_stars.sum()) if f in fit_fields else 0,
             "n_held_out": int(f.held_out.sum()) if f in hold_fields else 0,
             "flagged": f.flag_counts}
            | ({"correction_bias": dict(f.bias)} if getattr(f, "bias", None) else {})
            for f in fields]


def calibrate_with_stars(result, stars, *, holdout="auto", seed=20151, max_directions=6,
                         n_boot=200, iterations=2, gain=None, min_snr=30.0,
                         min_stars=30, flats_uncertainty=True, keep_lag_sum=True,
                         fitted_slopes=("size",), scale_star_errors=True, size_goal=3.0,
                         progress=False):
    """Refit a calibration jointly to its a-matrix and to star fields.

    Parameters
    ----------
    result : CalibrationResult
        From :func:`~lsst_bfdrift.calibration.tuning.calibrate` (with its
        template built).
    stars : sequence
        Star fields: paths, arrays (electrons), CCDData/NDData, or
        :class:`StarField` objects.
    holdout : {'auto', 'cross', 'split', 'last'}, optional
        Held-out stars. 'cross' (and 'auto'): two-fold cross-validation. The
        template is fitted to all the stars; every field is split in two
        seeded halves (paired in flux), the fit is repeated on each half
        alone, and each half's slopes are measured with the template fitted
        to the other half; the held-out slopes are the two folds' combined.
        'split' fits one half and holds out the other; 'last' holds out the
        last field (needs two or more).
    seed : int, optional
        Seed of the split and the bootstrap.
    max_directions : int, optional
        Most model directions the fit may use (0: with ``flats_uncertainty``,
        only the directions of the a-matrix's errors).
    n_boot : int, optional
        Bootstrap resamples of the slope errors.
    iterations : int, optional
        Gauss-Newton steps with exact star evaluations after the linear solve.
    gain : float, optional
        e/ADU of fields in ADU without a GAIN keyword.
    min_snr : float, optional
        Stars below this signal-to-noise ratio are not used.
    min_stars : int, optional
        Fewest usable fitted stars per field.
    flats_uncertainty : bool, optional
        Let the stars move the template within the a-matrix's errors (with
        its sum rule; :func:`~lsst_bfdrift.templates.refine.area_response_directions`):
        directions always in the fit, their cost the a-matrix's chi2
        (module docstring); the model's directions are then left out, but
        ``curl``. False: the model's directions (tension resolved by physics).
    keep_lag_sum : bool, optional
        The a-matrix's directions keep the measured lags' area sum (True:
        a field's noisy size slope moves no area into the far lags), or
        span its full errors (False, the spot route's default: a change of
        that sum, mostly a00's, moves area to or from the far lags).
    fitted_slopes : sequence of {'size', 'e1', 'e2'}, optional
        The star slopes the fit nulls (default: size). The others are
        measured and reported (held-out stars included, and their chi2
        after the fit in ``tension['unfitted']``) but carry no weight: a
        field measures its e1 slope to about its own size (module
        docstring), and the directions of the a-matrix's errors leave e1
        free, so fitting it moves the template's e1 by the fields' noise.
    scale_star_errors : bool, optional
        With six or more fitted slopes, scale their bootstrap errors by the
        Birge ratio of their residuals after the fit when it exceeds 1
        (:func:`~lsst_bfdrift.catalogs.slopes.birge_scale`; the
        fields' own scatter, counted against the parameters the stars
        determine) and refit; reported in ``star_error_scale`` and as a
        warning. A set of fields can scatter beyond its bootstrap errors:
        the brighter-fatter-free twins of ten GalSim ITL fields do, with
        chi2 26 for 10 (``benchmarks/stars/field_twins.py``), while larger sets
        drawn alike scatter as their errors say
        (``benchmarks/stars/star_slope_bias.py``). The chi2 and the tension keep
        the bootstrap errors, so fields that disagree (another sensor, a
        missing effect) are still reported.
    size_goal : float, optional
        Precision (% of the uncorrected size slope) the report measures the
        fit against: when the flats and the stars state the corrected size
        slope less precisely, a warning says how many fields like these
        would reach it
        (:func:`~lsst_bfdrift.calibration.star_result.fields_for_precision`;
        ``uncertainty['fields_for_size_goal']``).
    progress : bool, optional
        Progress bar on stderr.

    Returns
    -------
    StarCalibrationResult

    Raises
    ------
    CalibrationError
        No template in ``result``, too few usable stars in a field, or no
        star fields.
    InputError
        ``fitted_slopes`` or ``size_goal`` not valid.
    """
    t0 = time.perf_counter()
    fitted_slopes = check_star_inputs(result, fitted_slopes, size_goal)
    fields = read_star_fields(stars, gain=gain, min_snr=min_snr)
    return joint_calibration(result, fields, holdout=holdout, seed=seed,
                             max_directions=max_directions, n_boot=n_boot,
                             iterations=iterations, min_stars=min_stars,
                             flats_uncertainty=flats_uncertainty, keep_lag_sum=keep_lag_sum,
                             fitted_slopes=fitted_slopes, scale_star_errors=scale_star_errors,
                             size_goal=size_goal, progress=progress, t0=t0)


def joint_calibration(result, fields, *, holdout="auto", seed=20151, max_directions=6,
                      n_boot=200, iterations=2, min_stars=30, flats_uncertainty=True,
                      keep_lag_sum=True, fitted_slopes=("size",), scale_star_errors=True,
                      size_goal=3.0, always=(), meta_key="stars", progress=False, t0=None):
    """The joint fit of a calibration to data sets read already: star fields, spot series.

    The body of :func:`calibrate_with_stars` and
    :func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`, after
    their inputs are checked and read (module docstring: the steps).

    Parameters
    ----------
    result : CalibrationResult
        With its template built (:func:`check_star_inputs`).
    fields : list of StarField or SpotField
        The data sets, with distinct names.
    holdout, seed, max_directions, n_boot, iterations, min_stars, flats_uncertainty, keep_lag_sum
        As :func:`calibrate_with_stars`.
    fitted_slopes : tuple of str
        The slopes fitted on data sets that state none of their own (star
        fields; a spot series fits its own ``fitted_slopes``).
    scale_star_errors, size_goal, progress
        As :func:`calibrate_with_stars`.
    always : sequence of str, optional
        Model directions always in the fit
        (:func:`~lsst_bfdrift.calibration.star_solve.solve_joint`).
    meta_key : str, optional
        Key of the fit's record in the template's ``meta['calibration']``.
    t0 : float, optional
        ``time.perf_counter()`` at the start of the calibration (default now).

    Returns
    -------
    StarCalibrationResult
    """
    t0 = time.perf_counter() if t0 is None else t0
    mode, fit_fields, hold_fields = holdout_fields(fields, holdout)
    warn = split_fields(fields, mode, seed=seed, min_stars=min_stars)
    # the directions: the built template's change per parameter step, or the flats' own
    # uncertainty (per measured lag, the curl-free change of one error), and 'curl'
    ta = result.template
    rows = AmatrixRows(result.table, ta)
    lag_dirs = area_response_directions(ta, rows.sigma_lags, max_lag=rows.max_lag,
                                        sum_rule=bool(keep_lag_sum)) \
        if flats_uncertainty else {}
    n_model = 0 if lag_dirs else len(result.candidates) + 1  # the candidates and 'scale'
    bar = ProgressBar(progress_steps(n_model, len(lag_dirs), len(fit_fields), len(hold_fields),
                                     mode, iterations), meta_key, enabled=progress)
    names, steps, deltas, lag_names, more = direction_basis(result, lag_dirs, bar=bar)
    warn += more
    t_dirs = time.perf_counter() - t0
    # each direction corrects every fitted field once (the catalogs are kept per
    # template: every subset of stars reuses them)
    basis, more = evaluated_basis(ta, rows, names, steps, deltas, lag_names, fit_fields,
                                  bar=bar)
    warn += more
    t_jac = time.perf_counter() - t0 - t_dirs
    # the fit to every fitted star, refitted with the star errors scaled when they scatter
    fit = functools.partial(fit_joint, fields=fit_fields, template=ta, basis=basis, rows=rows,
                            fitted_slopes=fitted_slopes, max_directions=max_directions,
                            iterations=iterations, n_boot=n_boot, seed=seed, always=always,
                            bar=bar)
    final, star_scale, more = fit_with_error_scale(
        fit, {f.name: f.fit_stars for f in fit_fields}, n_amatrix=rows.size,
        scale_errors=scale_star_errors)
    warn += more
    if mode == "cross":
        held = cross_validate(fields, functools.partial(fit, star_scale=star_scale), ta,
                              n_boot=n_boot, seed=seed, bar=bar)
    else:
        held = held_out_validation(hold_fields, ta, final["t"], n_boot=n_boot, seed=seed,
                                   bar=bar)
    # the report
    chi2, sig_s = fit_chi2(final, rows, star_scale)
    tension, more = tension_test(final, rows, sig_s, fit_fields, fitted_slopes=fitted_slopes)
    warn += more
    info = star_information(final, basis, rows, sig_s, star_scale)
    coefficients = direction_coefficients(final, basis)
    uncertainty, more = uncertainty_report(final, basis, rows, fit_fields, ta, n_boot=n_boot,
                                           seed=seed, size_goal=size_goal)
    warn += more
    fit_slopes = fitted_star_slopes(fit_fields, ta, final["t"], n_boot=n_boot, seed=seed)
    t_joint = joint_template(final["t"], ta, {
        "fields": [f.name for f in fields], "kinds": [f.kind for f in fields],
        "holdout": mode, "directions": final["chosen"],
        "coefficients": coefficients, "flats_uncertainty": uncertainty,
        "keep_lag_sum": bool(keep_lag_sum) if flats_uncertainty else None,
        "chi2_amatrix": chi2["joint"]["amatrix"], "chi2_stars": chi2["joint"]["stars"],
        "tension": tension, "held_out": held,
        "correction_bias": {f.name: dict(f.bias) for f in fields if getattr(f, "bias", None)}},
        key=meta_key)
    bar.done = bar.total
    if progress:
        bar._draw(final=True)
    return StarCalibrationResult(
        template=t_joint, flats_template=ta, directions=final["chosen"],
        coefficients=coefficients, uncertainty=uncertainty, covariance=final["cov"],
        chi2=chi2, tension=tension, star_information=info, fit_slopes=fit_slopes,
        held_out=held, selection=final["selection"],
        fields=fields_summary(fields, fit_fields, hold_fields), warnings=warn,
        star_error_scale=star_scale,
        seconds={"directions": t_dirs, "star_jacobian": t_jac,
                 "total": time.perf_counter() - t0}, flux_unit=FLUX_UNIT)
