"""The joint fit of a template to the a-matrix and star fields, and its cross-validation.

The steps of :func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`
between the directions (:mod:`~lsst_bfdrift.calibration.star_basis`) and the
report (:mod:`~lsst_bfdrift.calibration.star_report`):

* :func:`fit_joint`: the fit to one subset of stars per field: the star
  slopes with T_a and their Jacobian (:func:`star_vector`,
  :func:`star_jacobian`), the choice of directions and the weighted
  least-squares solution (:func:`solve_joint`), and Gauss-Newton steps with
  exact evaluations of the stars (:func:`refine_joint`);
* :func:`fit_with_error_scale`: the fit, refitted with the star errors
  scaled by their Birge ratio when they scatter beyond them;
* the held-out stars: :func:`cross_validate` (two folds, each half fitted
  alone and measured with the other half's template,
  :func:`combine_folds`) or :func:`held_out_validation` (stars held out of
  the one fit).

A spot series (:class:`~lsst_bfdrift.calibration.spot_fit.SpotField`) takes
a star field's place in every step: its slopes are rows of the star vector
like a field's, with the slopes it fits (:func:`fitted_rows`), and its
halves are halves of its spots.
"""

import numpy as np

from lsst_bfdrift.calibration.star_result import STAR_SLOPES
from lsst_bfdrift.calibration.tuning import CalibrationError, select_parameters
from lsst_bfdrift.catalogs.slopes import birge_scale
from lsst_bfdrift.templates.refine import combine_templates
from lsst_bfdrift.utils.errors import InputError

__all__ = ["PRIOR_STEPS", "star_vector", "fitted_rows", "star_jacobian", "solve_joint",
           "refine_joint",
           "fit_joint", "fit_with_error_scale", "held_out_slopes", "combine_folds",
           "cross_validate", "held_out_validation"]

#: Prior width (steps) of every model direction of the template family.
PRIOR_STEPS = 3.0


def _tick(bar, n=1):
    """Advance the progress bar ``bar`` (None: no bar) by ``n``."""
    if bar is not None:
        bar(n)


def star_vector(fields, subsets, template, *, n_boot=0, seed=20151):
    """The star slopes of every field after a correction, in the fit's row order.

    Parameters
    ----------
    fields : sequence of StarField
    subsets : dict
        Field name -> mask of the stars used.
    template : DistortionTemplate or None
        The correction's template (None: uncorrected).
    n_boot : int, optional
        Bootstrap resamples of the errors (0: none).
    seed : int, optional
        Seed of the bootstrap.

    Returns
    -------
    values, errors : ndarray, shape (3 * len(fields),)
        Size, e1 and e2 slopes (per 1e5 e; :data:`STAR_SLOPES`) of each
        field in turn, and their errors.
    """
    vals, errs = [], []
    for f in fields:
        s = f.slopes(template, subsets[f.name], n_boot=n_boot, seed=seed)
        for k in STAR_SLOPES:
            vals.append(s[k][0])
            errs.append(s[k][1])
    return np.array(vals), np.array(errs)


def fitted_rows(fields, fitted_slopes):
    """Which rows of the star vector the fit weighs.

    Parameters
    ----------
    fields : sequence
        The fitted data sets (star fields, spot series), in row order.
    fitted_slopes : sequence of {'size', 'e1', 'e2'}
        The slopes fitted on a data set that states none of its own.

    Returns
    -------
    ndarray of bool, shape (3 * len(fields),)
        Per data set, its size, e1 and e2 rows (:data:`STAR_SLOPES`): True
        for the slopes in its ``fitted_slopes`` attribute (a spot series
        fits its e1 slope, which it measures well,
        :class:`~lsst_bfdrift.calibration.spot_fit.SpotField`), else in
        ``fitted_slopes``.
    """
    rows = []
    for f in fields:
        own = getattr(f, "fitted_slopes", None)
        rows.extend(k in (own or fitted_slopes) for k in STAR_SLOPES)
    return np.array(rows, bool)


def star_jacobian(fields, subsets, basis, base, *, seed=20151):
    """Change of the star vector per unit of each direction (finite differences).

    Parameters
    ----------
    fields, subsets
        As :func:`star_vector`.
    basis : DirectionBasis
        ``templates`` (T_a plus ``eps`` of each direction) and ``eps``.
    base : ndarray
        The star vector with T_a.
    seed : int, optional
        As :func:`star_vector` (no bootstrap here).

    Returns
    -------
    ndarray, shape (base.size, len(basis.templates))
    """
    return np.column_stack([(star_vector(fields, subsets, t_k, seed=seed)[0] - base) / e
                            for t_k, e in zip(basis.templates, basis.eps)])


def solve_joint(amatrix_jacobian, star_jacobian, star_residuals, amatrix_sigma, star_sigma,
                is_lag, names, *, max_directions, star_sigma_all=None,
                prior_steps=PRIOR_STEPS, always=()):
    """Choice of directions and weighted least-squares steps of the linearised joint fit.

    The rows are the a-matrix's (the change from T_a, residual 0 at T_a),
    the stars' (their slopes with T_a) and a Gaussian prior of
    ``prior_steps`` per model direction, which keeps directions the data
    hardly see inside the linear range of the family (the lag directions'
    prior is the a-matrix itself). The lag directions are always in; the
    model directions are chosen by
    :func:`~lsst_bfdrift.calibration.tuning.select_parameters` (chi2 drop
    > ln N, N the data rows with weight; the prior rows take part, so a
    direction that needs many steps pays for them).

    Parameters
    ----------
    amatrix_jacobian : ndarray, shape (n_a, n_dir)
    star_jacobian : ndarray, shape (n_s, n_dir)
    star_residuals : ndarray, shape (n_s,)
        The star slopes with T_a.
    amatrix_sigma, star_sigma : ndarray
        Errors of the a-matrix and star rows (inf: measured, not fitted).
    is_lag : ndarray of bool, shape (n_dir,)
    names : sequence of str
        Direction names.
    max_directions : int
        Most model directions chosen.
    star_sigma_all : ndarray, optional
        Errors of every star row as if all were fitted: ``cov_all`` is the
        steps' covariance with them (None: not computed).
    prior_steps : float, optional
        Prior width (steps) of every model direction.
    always : sequence of str, optional
        Model directions always in the fit, with their prior, not chosen
        (``curl`` with spot series: they measure the e1 slope it moves);
        they come first in ``chosen`` and are not counted in
        ``max_directions``. Names not in ``names`` are ignored.

    Returns
    -------
    dict
        ``chosen`` (model directions) and ``selection``; ``cols`` (indices
        of the directions in the fit: the lags first, then ``chosen``);
        ``coef`` (steps along them), ``cov`` (their covariance),
        ``cov_flats`` (without the star rows), ``cov_all`` (None without
        ``star_sigma_all``); ``star_leverage`` (the trace of the star rows'
        block of the hat matrix: the parameters the stars determine);
        ``jacobian`` and ``weights`` of the rows in the fit (the data rows,
        then the prior rows of ``cols``).
    """
    Ja, Js, r_s0, a_sig, sig_s = (amatrix_jacobian, star_jacobian, star_residuals,
                                  amatrix_sigma, star_sigma)
    n_a, nd = Ja.shape[0], len(names)
    r0 = np.concatenate([np.zeros(n_a), r_s0, np.zeros(nd)])
    prior = np.where(is_lag, np.inf, prior_steps)
    sig = np.concatenate([a_sig, sig_s, prior])
    J = np.vstack([Ja, Js, np.eye(nd)])
    n_data = n_a + r_s0.size  # data rows (ln N counts the fitted ones), then the prior
    fixed = [names.index(n) for n in always if n in names and not is_lag[names.index(n)]]
    chosen, selection = select_parameters(J, r0, sig, np.ones(J.shape[0], bool), names,
                                          max_params=max_directions, always_first=False,
                                          n_points=n_a + int(np.isfinite(sig_s).sum()),
                                          base=list(np.flatnonzero(is_lag)) + fixed)
    chosen = [names[k] for k in fixed] + chosen
    cols = list(np.flatnonzero(is_lag)) + [names.index(n) for n in chosen]
    rows = np.r_[np.arange(n_data), n_data + np.asarray(cols, int)]
    Jc, r0c, sigc = J[rows][:, cols], r0[rows], sig[rows]
    W = 1.0 / sigc ** 2
    cov = np.linalg.pinv(Jc.T @ (Jc * W[:, None])) if cols else np.zeros((0, 0))
    # the same without the stars: the flats' (and priors') covariance of the steps
    no_star = (rows < n_a) | (rows >= n_data)
    cov_flats = np.linalg.pinv(Jc[no_star].T @ (Jc[no_star] * W[no_star, None])) \
        if cols else np.zeros((0, 0))
    cov_all = None
    if cols and star_sigma_all is not None:
        # every measured slope fitted: what fitting them would do to the precision
        sig_all = np.concatenate([a_sig, star_sigma_all, prior])[rows]
        cov_all = np.linalg.pinv(Jc.T @ (Jc / sig_all[:, None] ** 2))
    coef = -cov @ (Jc.T @ (W * r0c))
    sr = (rows >= n_a) & (rows < n_data)  # the star rows: the parameters they determine
    lev = float(np.sum((Jc[sr] @ cov) * Jc[sr] * W[sr, None])) if cols else 0.0
    return {"chosen": chosen, "selection": selection, "cols": cols, "coef": coef, "cov": cov,
            "cov_flats": cov_flats, "cov_all": cov_all, "star_leverage": lev,
            "jacobian": Jc, "weights": W}


def refine_joint(template, basis, rows, solution, base, fields, subsets, *, iterations=2,
                 seed=20151, bar=None):
    """Gauss-Newton steps of the joint fit with exact evaluations of the stars.

    The Jacobian of :func:`solve_joint` is kept; each step evaluates the
    stars and the a-matrix rows at the current template. The steps stop
    after ``iterations``, or when every step is below 2 % of its error.

    Parameters
    ----------
    template : DistortionTemplate
        T_a.
    basis : DirectionBasis
    rows : AmatrixRows
    solution : dict
        :func:`solve_joint`'s.
    base : ndarray
        The star vector with T_a (returned when no direction is in the fit).
    fields, subsets
        The fitted fields and their stars (:func:`star_vector`).
    iterations : int, optional
        Most steps after the linear solve.
    seed : int, optional
    bar : callable, optional
        Progress bar, advanced once per field and evaluation.

    Returns
    -------
    template : DistortionTemplate
        T(c) (T_a itself when no direction is in the fit).
    coef : ndarray
        The steps c along ``solution['cols']``.
    slopes : ndarray
        The star vector with T(c).

    Raises
    ------
    CalibrationError
        When the stars cannot be corrected with T(c).
    """
    cols, coef, cov = solution["cols"], solution["coef"], solution["cov"]
    Jc, W = solution["jacobian"], solution["weights"]
    if not cols:  # no direction: T_a itself (its corrections are already made)
        return template, coef, base
    t_joint = combine_templates(template, [basis.deltas[k] for k in cols], coef)
    s_j = base
    for it in range(max(int(iterations), 0) + 1):
        for _f in fields:
            _tick(bar)
        try:
            s_j = star_vector(fields, subsets, t_joint, seed=seed)[0]
        except InputError as exc:
            raise CalibrationError(
                "the joint template ("
                + ", ".join(f"{n} {c:+.3g} steps" for n, c in zip(solution["chosen"], coef))
                + f") cannot correct the star fields: {exc}") from exc
        r = np.concatenate([rows.alpha(t_joint) - rows.start, s_j, coef])
        step = -cov @ (Jc.T @ (W * r))
        if it >= iterations or np.all(np.abs(step) < 0.02 * np.sqrt(np.diag(cov)) + 1e-12):
            break
        coef = coef + step
        t_joint = combine_templates(template, [basis.deltas[k] for k in cols], coef)
    return t_joint, coef, s_j


def fit_joint(subsets, fields, template, basis, rows, *, fitted_slopes=("size",),
              star_scale=1.0, max_directions=6, iterations=2, n_boot=200, seed=20151,
              always=(), bar=None):
    """The joint fit of the template to the a-matrix and to the stars ``subsets``.

    Parameters
    ----------
    subsets : dict
        Field name -> mask of the stars fitted.
    fields : sequence of StarField
        The fitted fields.
    template : DistortionTemplate
        T_a.
    basis : DirectionBasis
    rows : AmatrixRows
    fitted_slopes : sequence of {'size', 'e1', 'e2'}, optional
        The slopes fitted on data sets that state none of their own
        (:func:`fitted_rows`); the others are measured with no weight.
    star_scale : float, optional
        Factor on the fitted slopes' bootstrap errors
        (:func:`fit_with_error_scale`).
    max_directions, iterations : int, optional
        As :func:`solve_joint` and :func:`refine_joint`.
    n_boot : int, optional
        Bootstrap resamples of the errors of the slopes with T_a.
    seed : int, optional
    always : sequence of str, optional
        Model directions always in the fit (:func:`solve_joint`).
    bar : callable, optional

    Returns
    -------
    dict
        ``chosen``, ``selection``, ``cols``, ``coef``, ``cov``,
        ``cov_flats``, ``cov_all`` and ``star_leverage`` (:func:`solve_joint`;
        ``coef`` refined); ``t`` (T(c)); ``a_change`` (its a_ij change from
        T_a); ``r_s0``, ``sig_u`` (the star vector with T_a and its bootstrap
        errors), ``sig_s`` (the errors of the fit: scaled, inf where not
        fitted), ``Js`` (the star Jacobian); ``r_fin`` (the a-matrix rows'
        residuals to the measured a_ij, and the star vector, with T(c)).
    """
    fitted = fitted_rows(fields, fitted_slopes)
    r_s0, sig_u = star_vector(fields, subsets, template, n_boot=n_boot, seed=seed)
    # slopes not fitted: measured, no weight; fitted: bootstrap errors (x the Birge ratio)
    sig_s = np.where(fitted, sig_u * star_scale, np.inf)
    Js = star_jacobian(fields, subsets, basis, r_s0, seed=seed)
    # the slopes not fitted with their own errors: reported, not used
    sig_all = sig_u * star_scale if not fitted[1::3].all() else None
    sol = solve_joint(basis.jacobian, Js, r_s0, rows.sigma, sig_s, basis.is_lag, basis.names,
                      max_directions=max_directions, star_sigma_all=sig_all, always=always)
    t_joint, coef, s_j = refine_joint(template, basis, rows, sol, r_s0, fields, subsets,
                                      iterations=iterations, seed=seed, bar=bar)
    r_fin = np.concatenate([rows.alpha(t_joint) - rows.measured, s_j])
    return {"chosen": sol["chosen"], "cols": sol["cols"], "coef": coef, "cov": sol["cov"],
            "t": t_joint, "cov_flats": sol["cov_flats"], "cov_all": sol["cov_all"],
            "a_change": rows.alpha(t_joint) - rows.start,
            "r_s0": r_s0, "sig_s": sig_s, "sig_u": sig_u, "Js": Js, "r_fin": r_fin,
            "selection": sol["selection"], "star_leverage": sol["star_leverage"]}


def fit_with_error_scale(fit, subsets, *, n_amatrix, scale_errors=True):
    """The fit, refitted with the star errors scaled when they scatter beyond them.

    Parameters
    ----------
    fit : callable
        ``fit(subsets, star_scale=...)`` returning :func:`fit_joint`'s dict.
    subsets : dict
        Field name -> mask of the stars fitted.
    n_amatrix : int
        Number of a-matrix rows (they come first in ``r_fin``).
    scale_errors : bool, optional
        False: one fit with the bootstrap errors.

    Returns
    -------
    final : dict
        The fit.
    scale : float
        The factor on the star errors:
        :func:`~lsst_bfdrift.catalogs.slopes.birge_scale` of the fitted
        slopes' residuals, counted against the parameters the stars
        determine (``star_leverage``), when it exceeds 1; else 1.
    warnings : list of str
        The scaling, when made.
    """
    final = fit(subsets, star_scale=1.0)
    if not scale_errors:
        return final, 1.0, []
    scale = birge_scale(final["r_fin"][n_amatrix:], final["sig_s"], final["star_leverage"])
    if scale <= 1.0:
        return final, 1.0, []
    n_fit_s = int(np.isfinite(final["sig_s"]).sum())
    warning = (f"the {n_fit_s} fitted star slopes scatter {scale:.2f} times their "
               "bootstrap errors after the fit; their errors were scaled by it")
    return fit(subsets, star_scale=scale), scale, [warning]


def held_out_slopes(field, subset, templates, *, n_boot=200, seed=20152, bar=None):
    """Slopes of held-out stars: uncorrected, with the flats template and the joint one.

    Parameters
    ----------
    field : StarField
    subset : ndarray of bool
        The held-out stars.
    templates : dict
        ``before`` (None), ``flats_only`` and ``joint`` templates.
    n_boot, seed : int, optional
        Bootstrap of the errors.
    bar : callable, optional
        Progress bar, advanced once per template.

    Returns
    -------
    dict
        Per key of ``templates``, :meth:`StarField.slopes
        <lsst_bfdrift.calibration.star_fit.StarField.slopes>`; ``n_stars``.
    """
    row = {}
    for what in ("before", "flats_only", "joint"):
        _tick(bar)
        row[what] = field.slopes(templates[what], subset, n_boot=n_boot, seed=seed)
    row["n_stars"] = row["before"]["n_stars"]
    return row


def combine_folds(rows):
    """Held-out slopes of the cross-validation folds combined.

    The folds' stars are disjoint, so their slopes are independent: each
    slope is the inverse-variance mean of the folds'.

    Parameters
    ----------
    rows : sequence of dict
        :func:`held_out_slopes` of each fold.

    Returns
    -------
    dict
        ``folds`` (``rows``), ``n_stars`` (their sum) and, per ``before``,
        ``flats_only`` and ``joint``, each slope's (mean, error) and the
        stars counted.
    """
    out = {"folds": rows, "n_stars": int(sum(r["n_stars"] for r in rows))}
    for what in ("before", "flats_only", "joint"):
        comb = {"n_stars": int(sum(r[what]["n_stars"] for r in rows))}
        for k in STAR_SLOPES:
            v = np.array([r[what][k][0] for r in rows])
            e = np.array([r[what][k][1] for r in rows])
            w = 1.0 / np.maximum(e, 1e-300) ** 2
            comb[k] = (float(np.sum(w * v) / np.sum(w)), float(1.0 / np.sqrt(np.sum(w))))
        out[what] = comb
    return out


def cross_validate(fields, fit, flats_template, *, n_boot=200, seed=20151, bar=None):
    """Two-fold cross-validation: each half of every field fitted alone, measured on the other.

    Every field is split in two halves (``half_a``, ``half_b``:
    :meth:`StarField.split <lsst_bfdrift.calibration.star_fit.StarField.split>`).
    The fit (direction choice included) is repeated on the A halves of all
    the fields, then on the B halves; each half's slopes are measured with
    the template fitted to the other half, so every star is measured with a
    template that never saw it.

    Parameters
    ----------
    fields : sequence of StarField
    fit : callable
        ``fit(subsets)`` returning :func:`fit_joint`'s dict.
    flats_template : DistortionTemplate
        T_a.
    n_boot : int, optional
    seed : int, optional
        The calibration's seed (the held-out bootstrap uses ``seed + 1``).
    bar : callable, optional

    Returns
    -------
    dict
        Field name -> :func:`combine_folds` of its two folds, each with
        ``fitted_on`` (``half A`` or ``half B``) and the ``directions``
        chosen, and the data set's ``kind`` (``stars`` or ``spots``).
    """
    folds = []
    for fit_half in ("A", "B"):
        sub = {f.name: (f.half_a if fit_half == "A" else f.half_b) for f in fields}
        folds.append((fit_half, fit(sub)))
    held = {}
    for f in fields:
        rows = []
        for fit_half, fk in folds:
            sub = f.half_b if fit_half == "A" else f.half_a
            row = held_out_slopes(f, sub, {"before": None, "flats_only": flats_template,
                                           "joint": fk["t"]}, n_boot=n_boot, seed=seed + 1,
                                  bar=bar)
            row["fitted_on"] = f"half {fit_half}"
            row["directions"] = fk["chosen"]
            rows.append(row)
        held[f.name] = combine_folds(rows) | {"kind": f.kind}
    return held


def held_out_validation(fields, flats_template, joint_template, *, n_boot=200, seed=20151,
                        bar=None):
    """Slopes of the stars held out of the fit (``holdout`` 'split' or 'last').

    Parameters
    ----------
    fields : sequence of StarField
        The fields with held-out stars (``held_out``).
    flats_template, joint_template : DistortionTemplate
        T_a and T(c).
    n_boot : int, optional
    seed : int, optional
        The calibration's seed (the bootstrap uses ``seed + 1``).
    bar : callable, optional

    Returns
    -------
    dict
        Field name -> :func:`held_out_slopes`, with the data set's ``kind``.
    """
    templates = {"before": None, "flats_only": flats_template, "joint": joint_template}
    return {f.name: held_out_slopes(f, f.held_out, templates, n_boot=n_boot, seed=seed + 1,
                                    bar=bar) | {"kind": f.kind} for f in fields}
