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
:data:`~lsst_bfdrift.calibration.tuning.CANDIDATES`: the directions the
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
unmeasured far lags; :func:`~lsst_bfdrift.templates.refine.area_response_directions`).
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
  half the stars). The directions' corrected catalogues are computed once
  and serve the three fits.

How many stars: the size slope of a field is measured to about
``1 / sqrt(N)`` of its own scatter, the photon noise of the brightest stars'
sizes (:mod:`~lsst_bfdrift.catalogs.slopes`); the validate-sky
benchmark measured it to 15 % (z = 6.6) with 150 stars of 1e4-1.5e6 e on a
1k x 1k ITL field. A star field constrains the template when its
uncorrected size slope is detected at z > 10: several hundred unsaturated,
isolated stars spanning 1e4 to 1e6 e (docs/calibration.rst gives the
figures per sensor).
"""

import time

import numpy as np
from scipy import stats

from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.catalogs.catalog import FLAG_NAMES, detect_stars, measure_stars
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.calibration.star_result import (_SLOPES, StarCalibrationResult,
                                                  fields_for_precision)
from lsst_bfdrift.catalogs.slopes import FLUX_UNIT, birge_scale, select_stars, shape_flux_relations
from lsst_bfdrift.calibration.tuning import CalibrationError, _select
from lsst_bfdrift.templates.refine import (area_response_directions, combine_templates,
                                          curl_free_template, template_alpha,
                                          template_difference)
from lsst_bfdrift.templates.template import build_template
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["StarField", "calibrate_with_stars", "check_size_goal"]

#: Finite-difference step of the star Jacobian (in units of each direction).
_EPS = 0.25
#: Prior width (steps) of every direction of the template family.
PRIOR_STEPS = 3.0


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
        scene, so that the two catalogues hold the same stars row by row);
        default: detected on this image.
    """

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

    def corrected_catalog(self, template):
        """Catalogue of the same stars after a drift correction with ``template``
        (None: the uncorrected image). Kept per template: the fit, the
        bootstrap and the held-out stars reuse one correction."""
        if template is None:
            return self.catalog
        key = id(template)
        if key not in self._corrected:
            from astropy import units as u
            from astropy.nddata import CCDData

            from lsst_bfdrift.correction.task import (BrighterFatterDriftConfig,
                                                      BrighterFatterDriftTask)
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
            self._slopes[key] = {k: (rel[k]["slope"], rel[k]["slope_err"]) for k in _SLOPES} \
                | {"n_stars": rel["n_stars"]}
        return dict(self._slopes[key])


def _star_vector(slopes_per_field, fields):
    vals, errs = [], []
    for f in fields:
        s = slopes_per_field[f.name]
        for k in _SLOPES:
            vals.append(s[k][0])
            errs.append(s[k][1])
    return np.array(vals), np.array(errs)


def _combine_folds(rows):
    """Held-out slopes of the cross-validation folds combined (inverse-variance means;
    the folds' stars are disjoint, so their slopes are independent)."""
    out = {"folds": rows, "n_stars": int(sum(r["n_stars"] for r in rows))}
    for what in ("before", "flats_only", "joint"):
        comb = {"n_stars": int(sum(r[what]["n_stars"] for r in rows))}
        for k in _SLOPES:
            v = np.array([r[what][k][0] for r in rows])
            e = np.array([r[what][k][1] for r in rows])
            w = 1.0 / np.maximum(e, 1e-300) ** 2
            comb[k] = (float(np.sum(w * v) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w))))
        out[what] = comb
    return out


def check_size_goal(value, name="size_goal"):
    """Raise InputError unless ``value`` is a finite precision > 0 (% of the
    uncorrected size slope); ``name`` labels it in the message (the CLI checks
    ``--size-goal`` before it reads any file)."""
    if not (np.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a finite precision > 0 (% of the uncorrected "
                         f"size slope), got {value!r}")


def calibrate_with_stars(result, stars, *, holdout="auto", seed=20151, max_directions=6,
                         n_boot=200, iterations=2, gain=None, min_snr=30.0,
                         min_stars=30, flats_uncertainty=True, fitted_slopes=("size",),
                         scale_star_errors=True, size_goal=3.0, progress=False):
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
    if result.template is None or result.built_template is None:
        raise CalibrationError("calibrate_with_stars needs a calibration with its template "
                               "built (calibrate(..., build=True))")
    fitted_slopes = tuple(fitted_slopes)
    if not fitted_slopes or set(fitted_slopes) - set(_SLOPES):
        raise InputError(f"fitted_slopes must be a non-empty subset of {_SLOPES}, got "
                         f"{fitted_slopes!r}")
    check_size_goal(size_goal)
    stars = list(stars) if not isinstance(stars, (str, np.ndarray, StarField)) else [stars]
    if not stars:
        raise CalibrationError("no star fields given")
    fields = []
    for k, s in enumerate(stars):
        if isinstance(s, StarField):
            fields.append(s)
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
    if holdout not in ("auto", "cross", "split", "last"):
        raise InputError(f"holdout must be 'auto', 'cross', 'split' or 'last', got {holdout!r}")
    mode = "cross" if holdout == "auto" else holdout
    if mode == "last" and len(fields) < 2:
        raise CalibrationError("holdout='last' needs two or more star fields")
    fit_fields = fields[:-1] if mode == "last" else fields
    hold_fields = fields[-1:] if mode == "last" else fields
    warn = []
    for f in fields:
        f.split(seed)
        if mode == "split":
            n_fit = int(f.fit_stars.sum())
        else:  # 'last' fits every star of the other fields, 'cross' each half in turn
            n_fit = int(min(f.half_a.sum(), f.half_b.sum())) if mode == "cross" \
                else int(f.usable.sum())
            f.fit_stars = f.usable.copy()
            f.held_out = f.usable.copy()
        if n_fit < min_stars:
            flagged = ", ".join(f"{v} {k}" for k, v in f.flag_counts.items() if v)
            raise CalibrationError(
                f"star field {f.name}: {n_fit} usable stars to fit (SNR >= {f.min_snr:g}; "
                f"flagged: {flagged or 'none'}); need at least {min_stars}, and several "
                "hundred isolated, unsaturated stars of 1e4-1e6 e to constrain the template")
        if f.flag_counts.get("saturated"):
            warn.append(f"{f.name}: {f.flag_counts['saturated']} saturated stars excluded")
        if f.flag_counts.get("blended"):
            warn.append(f"{f.name}: {f.flag_counts['blended']} blended detections excluded")
        if f.flag_counts.get("masked"):
            warn.append(f"{f.name}: {f.flag_counts['masked']} stars with masked or non-finite "
                        "pixels in their aperture excluded")
    # directions: the built template's change per parameter step
    params, settings = result.params, result.settings
    cands = result.candidates
    base_built = result.built_template
    ta = result.template
    table = result.table
    mask = table.mask()
    c = ta.center
    L = min(table.max_lag, c - 1)
    lag_mask = mask[:L + 1, :L + 1]
    a_meas = table.a[:L + 1, :L + 1][lag_mask]
    a_sig = table.sigma[:L + 1, :L + 1][lag_mask]

    def alpha_of(t):
        return template_alpha(t)[c:c + L + 1, c:c + L + 1].T[lag_mask]

    # the flats' own uncertainty: per measured lag, the curl-free change of one error
    sig_lags = np.where(mask, table.sigma, np.nan)[:L + 1, :L + 1]
    lag_dirs = area_response_directions(ta, sig_lags, max_lag=L) if flats_uncertainty else {}
    n_fits = 3 if mode == "cross" else 1
    n_model = 0 if lag_dirs else len(cands) + 1  # the candidates and 'scale'
    n_steps = n_model + 2 + len(fit_fields) * (n_model + 1 + len(lag_dirs)
                                               + n_fits * (iterations + 1)) \
        + len(hold_fields) * 3 * (2 if mode == "cross" else 1)
    bar = ProgressBar(n_steps, "stars", enabled=progress)
    # 'scale': the flats template itself (its overall strength, c = fractional change).
    # With the a-matrix's own directions, the model's are left out (but curl): the
    # a-matrix directions would undo a model direction's change at the measured lags
    # for free, leaving a change of the unmeasured far lags alone that nothing measures
    dirs, steps, deltas = [], {}, []
    if not lag_dirs:
        dirs, steps = ["scale"], {"scale": 1.0}
        deltas = [{k: getattr(ta, k) for k in ("corner_d", "vedge_d", "hedge_d", "vedge_t",
                                                "hedge_t")}]
    for n, (lo, hi) in ({} if lag_dirs else cands).items():
        bar(1)
        x0 = float(getattr(params, n))
        h = 0.1 * max(abs(x0), 0.01 * (hi - lo))
        if x0 + h > hi:
            h = -h
        if x0 + h < lo:
            continue
        try:
            tk = build_template(params.replace(**{n: x0 + h}), settings)
        except (RuntimeError, ValueError) as exc:
            warn.append(f"direction {n} skipped: the model fails at {n} = {x0 + h:g} ({exc})")
            continue
        dirs.append(n)
        deltas.append(template_difference(tk, base_built))
        steps[n] = h
    # 'curl': the part of T_a's boundary shifts that the a-matrix does not see
    bar(1)
    dirs.append("curl")
    deltas.append(template_difference(ta, curl_free_template(ta)))
    steps["curl"] = 1.0
    lag_names = set()
    for name, d in lag_dirs.items():
        dirs.append(name)
        deltas.append(d["delta"])
        steps[name] = 1.0
        lag_names.add(name)
    t_dirs = time.perf_counter() - t0
    # a-matrix Jacobian (exact: linear area response is linear in displacements)
    a0 = alpha_of(ta)
    Ja = np.column_stack([alpha_of(combine_templates(ta, [d], [1.0])) - a0 for d in deltas])
    # the direction templates, each correcting every field once (the catalogues are
    # kept per template: every subset of stars reuses them)
    dir_templates, dir_eps, keep = [], [], []
    for k, d in enumerate(deltas):
        # a quarter step: small enough that bright pixels stay in the modelled range
        # (a lag's step, one error of one a_ij, is usually small: a whole one, else less)
        for eps in ((1.0, _EPS, 0.05) if dirs[k] in lag_names else (_EPS,)):
            t_k = combine_templates(ta, [d], [eps])
            try:
                for f in fit_fields:
                    f.corrected_catalog(t_k)
            except InputError as exc:
                failed = exc
                continue
            break
        else:
            warn.append(f"direction {dirs[k]} skipped: the stars cannot be corrected with "
                        f"it ({failed})")
            bar(len(fit_fields))
            continue
        bar(len(fit_fields))
        keep.append(k)
        dir_templates.append(t_k)
        dir_eps.append(eps)
    dirs = [dirs[k] for k in keep]
    deltas = [deltas[k] for k in keep]
    Ja = Ja[:, keep]
    if not dirs:
        raise CalibrationError("no direction of the template family can be evaluated on "
                               "the star fields")
    t_jac = time.perf_counter() - t0 - t_dirs
    a_res0 = a0 - a_meas
    n_a = a0.size
    is_lag = np.array([n in lag_names for n in dirs], bool)
    # the star vector's rows (_star_vector: each fitted field's size, e1, e2) that are fitted
    fitted_rows = np.tile([k in fitted_slopes for k in _SLOPES], len(fit_fields))

    def fit(subsets):
        """The joint fit to the a-matrix and the stars ``subsets`` (field name -> mask)."""
        def vec(template, n_b=0):
            return _star_vector({f.name: f.slopes(template, subsets[f.name], n_boot=n_b,
                                                  seed=seed) for f in fit_fields}, fit_fields)

        r_s0, sig_u = vec(ta, n_boot)
        # slopes not fitted: measured, no weight; fitted: bootstrap errors (x the Birge ratio)
        sig_s = np.where(fitted_rows, sig_u * star_scale[0], np.inf)
        Js = np.column_stack([(vec(t_k)[0] - r_s0) / e for t_k, e in zip(dir_templates,
                                                                           dir_eps)])
        # the a-matrix rows measure the change from T_a (the flats' estimate; its
        # residuals to the measured a_ij are the flats fit's business), plus a Gaussian
        # prior of PRIOR_STEPS steps per model direction: keeps directions the data
        # hardly see inside the linear range of the family (the lags' prior is the
        # a-matrix itself)
        nd = len(dirs)
        r0 = np.concatenate([np.zeros(n_a), r_s0, np.zeros(nd)])
        sig = np.concatenate([a_sig, sig_s, np.where(is_lag, np.inf, PRIOR_STEPS)])
        J = np.vstack([Ja, Js, np.eye(nd)])
        n_data = n_a + r_s0.size  # data rows (ln N counts the fitted ones), then the prior
        # the prior rows take part in the choice: a direction that would need many
        # steps (beyond its linear range) to lower chi2 pays for them; the lags are
        # always in
        chosen, selection = _select(J, r0, sig, np.ones(J.shape[0], bool), dirs,
                                    max_params=max_directions, always_first=False,
                                    n_points=n_a + int(np.isfinite(sig_s).sum()),
                                    base=np.flatnonzero(is_lag))
        cols = list(np.flatnonzero(is_lag)) + [dirs.index(n) for n in chosen]
        rows = np.r_[np.arange(n_data), n_data + np.asarray(cols, int)]
        Jc, r0c, sigc = J[rows][:, cols], r0[rows], sig[rows]
        W = 1.0 / sigc ** 2
        cov = np.linalg.pinv(Jc.T @ (Jc * W[:, None])) if cols else np.zeros((0, 0))
        # the same without the stars: the flats' (and priors') covariance of the steps
        no_star = (rows < n_a) | (rows >= n_data)
        cov_flats = np.linalg.pinv(Jc[no_star].T @ (Jc[no_star] * W[no_star, None])) \
            if cols else np.zeros((0, 0))
        # and with every measured slope fitted (the slopes not fitted with their own errors):
        # what fitting them would do to the precision, reported, not used
        sig_all = np.concatenate([a_sig, sig_u * star_scale[0],
                                  np.where(is_lag, np.inf, PRIOR_STEPS)])[rows]
        cov_all = np.linalg.pinv(Jc.T @ (Jc / sig_all[:, None] ** 2)) \
            if cols and "e1" not in fitted_slopes else None
        coef = -cov @ (Jc.T @ (W * r0c))
        sr = (rows >= n_a) & (rows < n_data)  # the star rows: the parameters they determine
        lev = float(np.sum((Jc[sr] @ cov) * Jc[sr] * W[sr, None])) if cols else 0.0
        # Gauss-Newton refinement with exact star evaluations
        # no direction: T_a itself (its corrections are already made)
        t_joint = combine_templates(ta, [deltas[k] for k in cols], coef) if cols else ta
        s_j = r_s0
        if cols:
            for it in range(max(int(iterations), 0) + 1):
                for _f in fit_fields:
                    bar(1)
                try:
                    s_j = vec(t_joint)[0]
                except InputError as exc:
                    raise CalibrationError(
                        "the joint template ("
                        + ", ".join(f"{n} {c:+.3g} steps" for n, c in zip(chosen, coef))
                        + f") cannot correct the star fields: {exc}") from exc
                r = np.concatenate([alpha_of(t_joint) - a0, s_j, coef])
                step = -cov @ (Jc.T @ (W * r))
                if it >= iterations or np.all(np.abs(step) < 0.02 * np.sqrt(np.diag(cov))
                                              + 1e-12):
                    break
                coef = coef + step
                t_joint = combine_templates(ta, [deltas[k] for k in cols], coef)
        r_fin = np.concatenate([alpha_of(t_joint) - a_meas, s_j])
        return {"chosen": chosen, "cols": cols, "coef": coef, "cov": cov, "t": t_joint,
                "cov_flats": cov_flats, "cov_all": cov_all,
                "a_change": alpha_of(t_joint) - a0,
                "r_s0": r_s0, "sig_s": sig_s, "sig_u": sig_u, "Js": Js, "r_fin": r_fin,
                "selection": selection, "star_leverage": lev}

    def held_slopes(f, sub, template_of):
        row = {}
        for what in ("before", "flats_only", "joint"):
            bar(1)
            row[what] = f.slopes(template_of[what], sub, n_boot=n_boot, seed=seed + 1)
        row["n_stars"] = row["before"]["n_stars"]
        return row

    star_scale = [1.0]
    final = fit({f.name: f.fit_stars for f in fit_fields})
    if scale_star_errors:
        scale = birge_scale(final["r_fin"][n_a:], final["sig_s"], final["star_leverage"])
        if scale > 1.0:
            n_fit_s = int(np.isfinite(final["sig_s"]).sum())
            warn.append(f"the {n_fit_s} fitted star slopes scatter {scale:.2f} times their "
                        "bootstrap errors after the fit; their errors were scaled by it")
            star_scale[0] = scale
            final = fit({f.name: f.fit_stars for f in fit_fields})
    held = {}
    if mode == "cross":
        # two folds: each half of every field fitted alone and validated on the other half
        folds = []
        for k, (fit_half, other) in enumerate((("A", "B"), ("B", "A"))):
            sub = {f.name: (f.half_a if fit_half == "A" else f.half_b) for f in fields}
            fk = fit(sub)
            folds.append((k, fit_half, other, fk))
        for f in fields:
            rows = []
            for k, fit_half, other, fk in folds:
                sub = f.half_b if fit_half == "A" else f.half_a
                row = held_slopes(f, sub, {"before": None, "flats_only": ta, "joint": fk["t"]})
                row["fitted_on"] = f"half {fit_half}"
                row["directions"] = fk["chosen"]
                rows.append(row)
            held[f.name] = _combine_folds(rows)
    else:
        for f in hold_fields:
            held[f.name] = held_slopes(f, f.held_out,
                                       {"before": None, "flats_only": ta, "joint": final["t"]})
    chosen, cols, coef, cov = final["chosen"], final["cols"], final["coef"], final["cov"]
    t_joint, r_s0, sig_s, Js = final["t"], final["r_s0"], final["sig_s"], final["Js"]
    r_fin, selection = final["r_fin"], final["selection"]
    chi2_a0 = float(np.sum((a_res0 / a_sig) ** 2))
    # chi2 and tension with the bootstrap errors as measured: a scale absorbs a field of
    # another sensor as readily as noise the bootstrap misses, so the tension stays blind
    # to it (the fit's weights and covariance use the scaled errors)
    sig_s = sig_s / star_scale[0]
    chi2_s0 = float(np.sum((r_s0 / sig_s) ** 2))
    chi2_a1 = float(np.sum((r_fin[:n_a] / a_sig) ** 2))
    chi2_s1 = float(np.sum((r_fin[n_a:] / sig_s) ** 2))
    # tension: the a-matrix chi2 of the template's change plus the stars' chi2 left, the
    # rise of the total from the flats' optimum T_a, against chi2(n_star)
    n_s = int(np.isfinite(sig_s).sum())
    rise = float(np.sum((final["a_change"] / a_sig) ** 2)) + chi2_s1
    tension = {"chi2_rise": rise, "dof": n_s, "p_value": float(stats.chi2.sf(rise, n_s)),
               "note": "rise of the total chi2 from the a-matrix-only optimum when the star "
                       "slopes are added; large with a small p-value means the model's "
                       "directions cannot satisfy both data sets"}
    unfitted = [k for k in _SLOPES if k not in fitted_slopes]
    if unfitted:
        # the slopes measured and not fitted, after the fit, against zero (a check: the
        # loop's curl term shows in e1 here first)
        sig_u, rows_u = final["sig_u"], ~fitted_rows
        chi2_u = float(np.sum((r_fin[n_a:][rows_u] / sig_u[rows_u]) ** 2))
        tension["unfitted"] = {"slopes": unfitted, "chi2": chi2_u, "dof": int(rows_u.sum()),
                               "p_value": float(stats.chi2.sf(chi2_u, int(rows_u.sum())))}
    if tension["p_value"] < 1e-3:
        sig_d = np.concatenate([a_sig, sig_s])
        worst = np.argsort(-np.abs(r_fin / sig_d))[:3]
        labels = [f"a{i}{j}" for i in range(L + 1) for j in range(L + 1) if lag_mask[i, j]] + \
            [f"{f.name}:{k}" for f in fit_fields for k in _SLOPES]
        tension["worst"] = [{"what": labels[w], "pull": float(r_fin[w] / sig_d[w])}
                            for w in worst]
        warn.append("tension between the a-matrix and the stars (p = "
                    f"{tension['p_value']:.1e}); worst: " + ", ".join(
                        f"{t['what']} pull {t['pull']:+.1f}" for t in tension["worst"]))
    n_lag = int(is_lag.sum())  # the lags come first in cols, the chosen model directions after
    Fa = Ja[:, cols].T @ (Ja[:, cols] / a_sig[:, None] ** 2)
    Fs = Js[:, cols].T @ (Js[:, cols] / (star_scale[0] * sig_s[:, None]) ** 2)
    info = {n: float(Fs[k, k] / (Fa[k, k] + Fs[k, k])) if (Fa[k, k] + Fs[k, k]) > 0 else None
            for k, n in enumerate(chosen, start=n_lag)}
    err = np.sqrt(np.clip(np.diag(cov), 0, None))
    coefficients = {n: {"steps": float(coef[k]), "steps_err": float(err[k]),
                        "parameter_change": float(coef[k] * steps[n]),
                        "parameter_change_err": float(abs(err[k] * steps[n])),
                        "step": float(steps[n])} for k, n in enumerate(chosen, start=n_lag)}
    uncertainty = None
    if n_lag:
        # the joint template's change from T_a as the a-matrix sees it (exact polygon
        # areas, computed by the fit; with model directions in, their a_ij change is part
        # of it), and what the whole move does to each fitted slope (linear)
        d_a = np.full(lag_mask.shape, np.nan)
        d_a[lag_mask] = final["a_change"]
        pulls = {(f"a{i}{j}" if max(i, j) < 10 else f"a{i},{j}"): (float(d_a[i, j]),
                                                                  float(d_a[i, j]
                                                                        / sig_lags[i, j]))
                 for i, j in zip(*np.nonzero(lag_mask))}
        order = sorted(pulls, key=lambda n: -abs(pulls[n][1]))
        moved = Js[:, cols] @ coef
        # how well each fitted field's size slope after correction is known: from the
        # flats' errors alone, and with the stars (linear propagation of the steps'
        # covariances; the directions span the a-matrix's errors, not the model's own)
        # (e1: in % of the e1 slope the flats template removes, the correction's own e1
        # change on the same stars; a field's uncorrected e1 slope is mostly its noise)
        size_sigma, e1_sigma = {}, {}
        for m, f in enumerate(fit_fields):
            before = f.slopes(None, f.fit_stars, n_boot=n_boot, seed=seed)
            flats = f.slopes(ta, f.fit_stars, n_boot=n_boot, seed=seed)
            removed = float(before["e1"][0] - flats["e1"][0])
            for i, out, ref in ((0, size_sigma, abs(before["size"][0])),
                                (1, e1_sigma, abs(removed))):
                g = Js[3 * m + i, cols]
                sf, sj = (float(np.sqrt(max(g @ cv @ g, 0.0)))
                          for cv in (final["cov_flats"], cov))
                pf, pj = ((100.0 * v / ref if ref > 0 else float("nan")) for v in (sf, sj))
                out[f.name] = {"flats": sf, "joint": sj, "flats_percent": pf,
                               "joint_percent": pj}
                if i == 1:
                    out[f.name]["removed"] = removed
                    if final["cov_all"] is not None:
                        sa = float(np.sqrt(max(g @ final["cov_all"] @ g, 0.0)))
                        out[f.name]["all_fitted"] = sa
                        out[f.name]["all_fitted_percent"] = 100.0 * sa / ref if ref > 0 \
                            else float("nan")
        uncertainty = {
            "n_directions": n_lag,
            "steps": {dirs[cols[k]]: float(coef[k]) for k in range(n_lag)},
            "chi2": float(sum(v[1] ** 2 for v in pulls.values())),
            "a_change": {n: v[0] for n, v in pulls.items()},
            "largest": [{"lag": n, "a_change": pulls[n][0], "sigma": pulls[n][1]}
                        for n in order[:3]],
            "slope_change": {f.name: {k: float(moved[3 * m + i]) for i, k in enumerate(_SLOPES)}
                             for m, f in enumerate(fit_fields)},
            "size_slope_sigma": size_sigma,
            "e1_slope_sigma": e1_sigma,
            "note": "the joint template's change from the flats template: a_ij change per "
                    "lag (1/e) and its chi2 with the a-matrix's errors; steps along the "
                    "directions of those errors (sum rule kept); size_slope_sigma: per "
                    "fitted field, the standard deviation of its corrected size slope (per "
                    "1e5 e, and % of its uncorrected slope) that the flats' errors leave, "
                    "and that the flats and the stars together leave; e1_slope_sigma: the "
                    "same for the e1 slope, in % of the e1 slope the flats template "
                    "removes from the field (``removed``, per 1e5 e), and, when e1 is not "
                    "fitted, with every measured slope fitted (``all_fitted``)"}
        e1_pct = np.array([v["joint_percent"] for v in e1_sigma.values()], float)
        if np.all(np.isfinite(e1_pct)) and np.mean(e1_pct) > 100.0:
            per = np.mean([v["joint"] for v in e1_sigma.values()])
            warn.append(f"the corrected e1 slope is uncertain by +- {np.mean(e1_pct):.0f} % of "
                        f"the e1 slope the flats template removes (+- {per:.1e} per 1e5 e): "
                        "the flats do not pin the sensor's serial/parallel anisotropy, so the "
                        "correction's e1 is not known; more flat pairs (the e1 error falls as "
                        "their square root) or e1 fitted on many fields would pin it")
        if size_sigma:
            fp, jp = (float(np.mean([v[k] for v in size_sigma.values()]))
                      for k in ("flats_percent", "joint_percent"))
            need = fields_for_precision(fp, jp, len(fit_fields), size_goal)
            uncertainty["fields_for_size_goal"] = {"goal_percent": float(size_goal),
                                                   "fields": need}
            if np.isfinite(jp) and jp > size_goal:
                how = (f"about {need} fields like these would state it to +- {size_goal:g} % "
                       "(each field's stars add alike), or more flat pairs"
                       if need is not None else
                       "the stars add no measurable precision; more flat pairs would")
                warn.append(f"the corrected size slope is known to +- {jp:.1f} % of the "
                            f"uncorrected (+- {fp:.1f} % from the flats alone): {how}")
    fit_slopes = {}
    for f in fit_fields:
        fit_slopes[f.name] = {
            "before": f.slopes(None, f.fit_stars, n_boot=n_boot, seed=seed),
            "flats_only": f.slopes(ta, f.fit_stars, n_boot=n_boot, seed=seed),
            "joint": f.slopes(t_joint, f.fit_stars, n_boot=n_boot, seed=seed)}
    if t_joint is ta:  # the result is a template of its own (the input is not modified)
        t_joint = combine_templates(ta, [], [])
    meta = dict(ta.meta)
    calib = dict(meta.get("calibration", {}))
    calib["stars"] = {"fields": [f.name for f in fields], "holdout": mode,
                      "directions": chosen, "coefficients": coefficients,
                      "flats_uncertainty": uncertainty,
                      "chi2_amatrix": chi2_a1, "chi2_stars": chi2_s1, "tension": tension,
                      "held_out": held}
    meta["calibration"] = calib
    t_joint.meta = meta
    bar.done = bar.total
    if progress:
        bar._draw(final=True)
    fields_info = [{"name": f.name, "n_detections": len(f.catalog),
                    "n_usable": int(f.usable.sum()),
                    "n_fit": int(f.fit_stars.sum()) if f in fit_fields else 0,
                    "n_held_out": int(f.held_out.sum()) if f in hold_fields else 0,
                    "flagged": f.flag_counts} for f in fields]
    return StarCalibrationResult(
        template=t_joint, flats_template=ta, directions=chosen, coefficients=coefficients,
        uncertainty=uncertainty,
        covariance=cov, chi2={"flats_only": {"amatrix": chi2_a0, "stars": chi2_s0},
                              "joint": {"amatrix": chi2_a1, "stars": chi2_s1},
                              "n_amatrix": int(n_a), "n_stars": int(n_s)},
        tension=tension, star_information=info, fit_slopes=fit_slopes, held_out=held,
        selection=selection, fields=fields_info, warnings=warn, star_error_scale=star_scale[0],
        seconds={"directions": t_dirs, "star_jacobian": t_jac,
                 "total": time.perf_counter() - t0}, flux_unit=FLUX_UNIT)
