"""Diagnosis: where the base model is wrong, which effect explains it.

The base model is the electrostatic a_ij pattern linearised about the fit to
measured coefficients (:class:`~lsst_bfdrift.calibration.acoeff_model.LinearBasis`), with
its parameters free. :func:`diagnose` then repeats

1. for every effect of the library (:mod:`lsst_bfdrift.simulation.effects`) that the
   input can identify, fit base + effects so far + the candidate;
2. score each candidate by the Bayesian information criterion
   BIC = chi2 + k ln n and by K-fold cross-validation over the data points
   (fit on K - 1 folds, chi2 of the held-out fold, summed);
3. add the best candidate only when it lowers BIC by more than
   ``bic_threshold`` *and* lowers the cross-validated chi2 (in most folds,
   and summed over all folds but the worst);

until nothing pays. The verdict then says plainly whether the residual is
consistent with noise (chi2 p-value >= ``p_threshold``) or an unexplained
residual remains, with the largest residual lags.

Inputs (:class:`~lsst_bfdrift.diagnosis.observations.Observations`):

``table``
    a_ij with errors (lags <= L); a00 is left out of chi2 when it was set by
    the sum rule. Base parameters: the electrostatic ones.
``ptc``
    mean and variance per signal level (ADU); base: Astier's exponential
    C00 model (gain, a00, noise). Without errors in the file, errors are
    scaled so that the base fit has chi2/dof = 1 (relative comparison only).
``flats``
    difference-image covariances C_ij(mu) and pair-sum statistics S_ij(mu)
    from flat pairs, and the pair means against EXPTIME (block 'M', when the
    pairs carry at least 3 exposure times); base: Astier's full covariance
    model with the electrostatic a_ij, free scales of a00, a01 and a10
    (:data:`BASE_SCALES`, with a Gaussian prior of :data:`BASE_SCALE_PRIOR`,
    block 'P'), gain, read
    noise and the line mu = rate t + offset. An effect that changes the
    measured signal (a gain non-linearity) must explain the means and the
    covariances together: a00 cannot take up the variance's curvature while
    the means say the signal chain is linear.

Beside the fit, every other observable the input carries is checked
(:mod:`lsst_bfdrift.diagnosis.findings`: linearity in exposure time,
the sum rule, image halves, the two flats of each pair, the turn-off); a
significant finding is named in the verdict with the effects that could
produce it, and never credited to the base model. These checks do not
change the choice of effects. Pairs above the turn-off are left out of the
fit and listed.
"""

import math
import os

import numpy as np
from scipy import stats

from lsst_bfdrift.calibration.acoeff_model import DEFAULT_FREE
from lsst_bfdrift.calibration.fitting import fit_parameters
from lsst_bfdrift.diagnosis.findings import assess_observables, credit_findings
from lsst_bfdrift.ptc.observables import exposure_line, pair_mean_errors
from lsst_bfdrift.diagnosis.observations import (Observations, edge_signature,
                                                 observations_from_pairs)
from lsst_bfdrift.ptc.covariances import fit_ptc_exponential, read_ptc_text
from lsst_bfdrift.ptc.full_model import covariance_model
from lsst_bfdrift.ptc.inputs import detect_input_kind, read_amatrix_file
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.utils.io import data_files
from lsst_bfdrift.simulation.effects import effect_library, EFFECT_NAMES

__all__ = ["diagnose",
           "Diagnosis", "BASE_SCALES", "BASE_SCALE_PRIOR", "scaled_basis", "base_acoeffs",
           "LINEAR_RANGE", "load_input"]

#: Lags whose a_ij get a free scale in the base model of flat pairs: a00, a01
#: and a10. The shipped basis is the electrostatics linearised about one
#: sensor; it misses the noise-free a-matrices of other sensors by up to 17 %
#: at these lags (:data:`BASE_SCALE_PRIOR`), which large flat sets resolve
#: and an effect would otherwise absorb.
BASE_SCALES = (((0, 0),), ((0, 1),), ((1, 0),))

#: Prior error of each scale of :data:`BASE_SCALES` (fractional). The size of
#: the shipped basis' misses on the noise-free a-matrices of GalSim's two
#: sensor models with its parameters free within their range: a01 by 17 %,
#: a00 by 6-9 %, a10 by up to 5 % (lsst_itl_50_8 and lsst_e2v_50_8, lags <= 3).
BASE_SCALE_PRIOR = 0.2

#: Fractional range around the expansion point within which the linearised
#: electrostatic parameters may move.
LINEAR_RANGE = 0.5


class _Problem:
    """Base model and parameter bookkeeping for one kind of observations."""

    def __init__(self, obs, basis):
        self.obs, self.basis = obs, basis
        self.y, self.sigma, self.labels = obs.data()
        if obs.kind == "ptc":
            e = fit_ptc_exponential(obs.mu, obs.var, mu_max=None)
            self.names = ["gain", "a00", "noise"]
            self.x0 = np.array([e["gain"], e["a00"], max(e["noise"], 1.0)])
            self.scale = np.array([0.1, 1e-7, 10.0])
            self.lo = np.array([1e-3, -1e-4, -1e6])
            self.hi = np.array([1e3, 1e-4, 1e8])
            m = covariance_model(obs.mu, e["gain"], [[e["a00"]]], [[0.0]],
                                 [[e["noise"]]])[:, 0, 0]
            r = obs.var - m
            # errors unknown: relative errors fixed so that the base fit has chi2/dof = 1
            rel = np.sqrt(np.sum((r / obs.var) ** 2) / max(obs.mu.size - 3, 1))
            obs._sig = obs.var * rel
            self.y, self.sigma, self.labels = obs.data()
            return
        if basis is None:
            raise InputError(f"input kind {obs.kind!r} needs an electrostatic basis")
        if basis.max_lag < obs.max_lag:
            raise InputError(f"basis has lags <= {basis.max_lag}, data {obs.max_lag}")
        self.names = list(basis.names)
        if obs.kind == "table" and self.y.size <= len(self.names):
            k = len(self.names)
            need = math.ceil(math.sqrt(k + 2)) - 1  # (L + 1)^2 lags, a00 perhaps left out
            raise InputError(
                f"{getattr(obs, 'source', 'the a_ij table')}: {self.y.size} lag(s) in chi2 "
                f"(lags 0..{obs.max_lag}), no more than the {k} free parameters of the base "
                f"model ({', '.join(self.names)}): nothing is left to diagnose; accepted: a "
                f"table with more lags than parameters (lags 0..{need} or more)")
        self.x0 = np.array([basis.x0[n] for n in self.names])
        self.scale = np.array([max(basis.errors[n], 1e-6 * max(abs(basis.x0[n]), 1.0))
                               for n in self.names])
        # the linear approximation is trusted within +-LINEAR_RANGE of each value,
        # inside the physical bounds of the fit
        span = LINEAR_RANGE * np.abs(self.x0)
        self.lo = np.array([max(self.x0[k] - span[k], DEFAULT_FREE.get(n, (-np.inf,))[0])
                            for k, n in enumerate(self.names)])
        self.hi = np.array([min(self.x0[k] + span[k], DEFAULT_FREE.get(n, (0, np.inf))[1])
                            for k, n in enumerate(self.names)])
        self.exptime = None
        if obs.kind == "flats":
            e = fit_ptc_exponential(obs.mu, obs.cov[:, 0, 0], mu_max=None)
            self.names += ["gain", "noise"]
            self.x0 = np.concatenate([self.x0, [e["gain"], max(e["noise"], 1.0)]])
            self.scale = np.concatenate([self.scale, [0.01 * e["gain"], 10.0]])
            self.lo = np.concatenate([self.lo, [1e-3, -1e6]])
            self.hi = np.concatenate([self.hi, [1e3, 1e8]])
            self._add_linearity(e["gain"], max(e["noise"], 0.0))
        self._add_scale_priors()

    def _add_scale_priors(self):
        """A Gaussian prior on each scale of the basis (block 'P').

        The scales overlap the electrostatic directions (both move a00, a01
        and a10); without a prior the fit wanders along that valley and its
        cross-validation folds disagree. The prior (mean 1, the basis' error
        of the scale, :meth:`LinearBasis.with_scales`) keeps the valley's
        floor and lets the scales take up what the electrostatics cannot.
        """
        self.prior_index = [k for k, n in enumerate(self.names) if n.startswith("scale")]
        if not self.prior_index:
            return
        err = np.array([self.basis.errors[self.names[k]] for k in self.prior_index])
        self.y = np.concatenate([self.y, np.ones(err.size)])
        self.sigma = np.concatenate([self.sigma, err])
        self.labels = self.labels + [("P", 0, k, 0) for k in range(err.size)]

    def _add_linearity(self, gain, noise):
        """The pair means against EXPTIME as a block of the fit ('M').

        Base model: mu = rate t + offset (two more base parameters); an
        effect that changes the measured signal (``Effect.measured_signal``)
        changes this block too, so that a signal-chain non-linearity is seen
        in the means as well as in the variances and the BF coefficients
        cannot absorb it. Errors: the shot noise of the pair mean and the
        exposure scatter measured from the two flats of each pair
        (:func:`~lsst_bfdrift.ptc.observables.exposure_scatter`).
        Needs the per-pair quantities of :func:`observations_from_pairs` and
        at least 3 distinct exposure times; otherwise the block is left out
        (the linearity check says why).
        """
        o = self.obs
        t, extra = getattr(o, "exptime", None), getattr(o, "pairs", None)
        if t is None or extra is None or np.unique(np.round(np.log(t), 3)).size < 3:
            return
        t = np.asarray(t, float)
        sig, scatter = pair_mean_errors(o.mu, extra, gain, noise)
        sig = np.sqrt(sig**2 + (scatter * o.mu) ** 2 / 2.0)
        coef, cov = exposure_line(o.mu, t, sig)
        err = np.sqrt(np.diag(cov))
        self.exptime = t
        self.names += ["rate", "offset"]
        self.x0 = np.concatenate([self.x0, coef])
        self.scale = np.concatenate([self.scale, err])
        self.lo = np.concatenate([self.lo, [0.0, -np.inf]])
        self.hi = np.concatenate([self.hi, [np.inf, np.inf]])
        self.y = np.concatenate([self.y, o.mu])
        self.sigma = np.concatenate([self.sigma, sig])
        self.labels = self.labels + [("M", k, 0, 0) for k in range(o.mu.size)]

    def predict(self, xb, effects, thetas):
        out = self._predict(xb, effects, thetas)
        if getattr(self, "prior_index", None):
            out = np.concatenate([out, np.asarray(xb)[self.prior_index]])
        return out

    def _predict(self, xb, effects, thetas):
        o = self.obs
        if o.kind == "table":
            a = self.basis.a(xb, o.max_lag)
            for e, t in zip(effects, thetas):
                a = e.apply_a(a, t, self.basis)
            return a[o.mask]
        if o.kind == "ptc":
            g, a00, noise = xb
            a = np.array([[a00]])
            b = np.zeros((1, 1))
            for e, t in zip(effects, thetas):
                bt = e.b_term(a, t, self.basis)
                if bt is not None:
                    b = b + bt[:1, :1]
            mu, fac = o.mu, np.ones(o.mu.size)
            for e, t in zip(effects, thetas):
                mu, f = e.measured_signal(mu, t)
                fac = fac * f
            c = covariance_model(mu, g, a, b, [[noise]]) * np.asarray(fac)[:, None, None]
            for e, t in zip(effects, thetas):
                c = e.apply_cov(c, t)
            return c[:, 0, 0]
        L = o.max_lag
        ne = len(self.basis.names)
        a = self.basis.a(xb[:ne], L)
        g, noise = xb[ne], xb[ne + 1]
        for e, t in zip(effects, thetas):
            a = e.apply_a(a, t, self.basis)
        b = np.zeros_like(a)
        for e, t in zip(effects, thetas):
            bt = e.b_term(a, t, self.basis)
            if bt is not None:
                b = b + bt
        mu, fac = o.mu, np.ones(o.mu.size)
        for e, t in zip(effects, thetas):
            mu, f = e.measured_signal(mu, t)
            fac = fac * f
        nz = np.zeros_like(a)
        nz[0, 0] = noise
        c = covariance_model(mu, g, a, b, nz) * fac[:, None, None]
        for e, t in zip(effects, thetas):
            c = e.apply_cov(c, t)
        s = np.zeros_like(c)
        for e, t in zip(effects, thetas):
            st = e.static(o.mu, L, t)
            if st is not None:
                s = s + st
        if self.exptime is None:
            return np.concatenate([c.ravel(), s.ravel()])
        # measured means: the line in exposure time, mapped through the signal chain
        # (to first order in the effect: mu_obs - (mu_lin(mu_obs) - line))
        line = xb[ne + 2] * self.exptime + xb[ne + 3]
        return np.concatenate([c.ravel(), s.ravel(), o.mu - (mu - line)])

    def fit(self, effects, start=None, train=None):
        """Fit of base model plus ``effects`` with the package's fit engine
        (:func:`~lsst_bfdrift.calibration.fitting.fit_parameters`, Jacobian
        recomputed after every accepted step: the model is cheap).

        ``start`` replaces the first values of the start (e.g. the previous
        stage's optimum); ``train`` is the mask of the points in chi2.
        Returns dict with x, errors, chi2 (over ``train``), model (all points).
        """
        lo = [self.lo] + [np.array([b[0] for b in e.bounds]) for e in effects]
        hi = [self.hi] + [np.array([b[1] for b in e.bounds]) for e in effects]
        sc = [self.scale] + [np.array(e.scale) for e in effects]
        x0 = [self.x0] + [np.array(e.start, float) for e in effects]
        lo, hi, sc = np.concatenate(lo), np.concatenate(hi), np.concatenate(sc)
        x0 = np.concatenate(x0)
        if start is not None:
            x0[:len(start)] = start
        x0 = np.clip(x0, lo + 1e-3 * sc, hi - 1e-3 * sc)
        nb = self.x0.size
        sizes = [len(e.param_names) for e in effects]
        sel = np.ones(self.y.size, bool) if train is None else train

        def split(x):
            out, k = [], nb
            for s in sizes:
                out.append(x[k:k + s])
                k += s
            return x[:nb], out

        names = [f"p{k}" for k in range(x0.size)]

        def model(v):
            xb, th = split(np.array([v[k] for k in names]))
            return self.predict(xb, effects, th)

        fit = fit_parameters(model, self.y, self.sigma, dict(zip(names, x0)),
                             {k: (a, b) for k, a, b in zip(names, lo, hi)}, mask=sel,
                             update="exact", max_evaluations=200 * (x0.size + 1))
        x = np.array([fit.values[k] for k in names])
        err = np.array([fit.errors[k] for k in names])
        xb, th = split(x)
        return {"x": x, "err": err, "chi2": fit.chi2, "model": fit.model,
                "n_params": x.size, "thetas": th, "theta_err": split(err)[1],
                "base_cov": np.asarray(fit.covariance, float)[:nb, :nb]}


class Diagnosis:
    """Result of :func:`diagnose`; see :meth:`as_dict` for the JSON layout."""

    def __init__(self, **kw):
        self.__dict__.update(kw)

    def as_dict(self):
        """JSON-friendly dictionary with the keys documented in ``docs/calibration.rst``."""
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_")}


def _step_summary(problem, fit, effects, label):
    r = (problem.y - fit["model"]) / problem.sigma
    n = problem.y.size
    dof = n - fit["n_params"]
    order = np.argsort(-np.abs(r))[:5]
    worst = [{"block": problem.labels[k][0], "level": int(problem.labels[k][1]),
              "i": problem.labels[k][2], "j": problem.labels[k][3],
              "pull": float(r[k]), "residual": float(problem.y[k] - fit["model"][k])}
             for k in order]
    return {"label": label, "chi2": fit["chi2"], "dof": int(dof),
            "chi2_dof": fit["chi2"] / max(dof, 1),
            "p_value": float(stats.chi2.sf(fit["chi2"], max(dof, 1))),
            "rms_pull": float(np.sqrt(np.mean(r**2))),
            "rms_residual": float(np.sqrt(np.mean((problem.y - fit["model"]) ** 2))),
            "largest_residuals": worst,
            "effects": [{"name": e.name,
                         "params": {p: float(v) for p, v in zip(e.param_names, t)},
                         "errors": {p: float(v) for p, v in zip(e.param_names, te)}}
                        for e, t, te in zip(effects, fit["thetas"], fit["theta_err"])],
            "base_params": {nm: float(v) for nm, v in zip(problem.names, fit["x"])},
            "base_errors": {nm: float(v) for nm, v in zip(problem.names, fit["err"])},
            "base_covariance": fit["base_cov"].tolist()}


def _per_lag(problem, fit):
    r = (problem.y - fit["model"]) / problem.sigma
    out = {}
    for k, (blk, lev, i, j) in enumerate(problem.labels):
        if blk == "P":  # the scales' prior: not data
            continue
        key = f"{blk}{i},{j}" if problem.obs.kind != "ptc" else f"C0,0@{lev}"
        d = out.setdefault(key, {"block": blk, "i": i, "j": j, "chi2": 0.0, "n": 0,
                                 "residual": [], "pull": []})
        d["chi2"] += float(r[k] ** 2)
        d["n"] += 1
        d["residual"].append(float(problem.y[k] - fit["model"][k]))
        d["pull"].append(float(r[k]))
    return out


def _cv_chi2(problem, effects, start, folds, rng_seed=0):
    """Held-out chi2 per fold (data points assigned to folds at random, seeded).

    The scales' prior (block 'P') is not data: it stays in every training set
    and is never held out."""
    n = problem.y.size
    data = np.array([lab[0] != "P" for lab in problem.labels])
    idx = np.flatnonzero(data)
    perm = idx[np.random.default_rng(rng_seed).permutation(idx.size)]
    out = np.zeros(folds)
    for f in range(folds):
        test = np.zeros(n, bool)
        test[perm[f::folds]] = True
        fit = problem.fit(effects, start=start, train=~test)
        out[f] = float(np.sum(((problem.y - fit["model"]) / problem.sigma)[test] ** 2))
    return out


def scaled_basis(basis, scales):
    """``basis`` with the scale directions of ``scales`` (groups of lags), as
    :func:`diagnose` uses it: the basis itself when ``scales`` is empty or
    the basis already has scales. Give a diagnosis' ``base_scales`` to
    rebuild the basis its ``base_params`` refer to."""
    if basis is None or not scales or any(nm.startswith("scale") for nm in basis.names):
        return basis
    return basis.with_scales([[tuple(ij) for ij in g] for g in scales], error=BASE_SCALE_PRIOR)


def diagnose(obs, basis=None, *, library=None, bic_threshold=10.0, p_threshold=1e-3,
             folds=5, max_effects=3, base_scales=BASE_SCALES):
    """Greedy search for the effects that explain the base model's residual.

    Parameters
    ----------
    obs : Observations
        The input.
    basis : LinearBasis, optional
        Electrostatic basis (needed for 'table' and 'flats').
    library : sequence of Effect, optional
        Candidates (default: the whole library).
    bic_threshold : float, optional
        Smallest BIC decrease that adds an effect.
    p_threshold : float, optional
        chi2 p-value below which the final residual is called unexplained.
    folds : int, optional
        Folds of the cross-validation over data points.
    max_effects : int, optional
        Largest number of effects added.
    base_scales : sequence of sequence of (int, int), optional
        For flat pairs, the groups of lags whose a_ij get a free scale in the
        base model (:meth:`~lsst_bfdrift.calibration.acoeff_model.LinearBasis.with_scales`;
        default :data:`BASE_SCALES`); ``()`` for the basis alone.

    Returns
    -------
    Diagnosis
        With ``effects_added``, ``chi2_dof_before``, ``chi2_dof_after``,
        ``steps`` (one summary per stage), ``candidates`` (scores per round),
        ``not_identifiable`` (effect -> reason), ``residuals_before``,
        ``residuals_after`` (per lag), ``verdict`` and ``unexplained``;
        ``observables`` (check name -> finding,
        :mod:`~lsst_bfdrift.diagnosis.findings`) and ``signatures`` (the
        significant findings as named in the verdict).
    """
    library = effect_library(max_lag=max(obs.max_lag, 0)) if library is None \
        else list(library)
    scales = [[list(map(int, ij)) for ij in g] for g in base_scales] \
        if obs.kind == "flats" and basis is not None else []
    basis = scaled_basis(basis, scales)
    problem = _Problem(obs, basis)
    n = problem.y.size
    usable, skipped = [], {}
    for e in library:
        ok, why = e.identifiable(obs.kind)
        if ok and e.name == "well_filling" and basis is None:
            skipped[e.name] = "needs d a_ij / d ln(channel depth) from an electrostatic basis"
        elif ok:
            usable.append(e)
        else:
            skipped[e.name] = why
    current, final_scores = [], []
    fit = problem.fit(current)
    bic = fit["chi2"] + fit["n_params"] * np.log(n)
    cv = _cv_chi2(problem, current, fit["x"], folds)
    first = fit
    steps = [_step_summary(problem, fit, current, "base model")]
    rounds = []
    while len(current) < max_effects:
        scores = []
        for e in usable:
            if e in current:
                continue
            f = problem.fit(current + [e], start=fit["x"])
            b = f["chi2"] + f["n_params"] * np.log(n)
            scores.append({"name": e.name, "chi2": f["chi2"], "delta_bic": float(b - bic),
                           "fit": f, "effect": e, "bic": float(b)})
        if not scores:
            break
        scores.sort(key=lambda s: s["bic"])
        best = scores[0]
        best_cv = _cv_chi2(problem, current + [best["effect"]], best["fit"]["x"], folds) \
            if best["delta_bic"] < -bic_threshold else None
        # held-out test: the candidate must predict the held-out points better in
        # most folds (median of the per-fold change < 0) and in all folds but the
        # worst together (an effect bent to an outlying block, e.g. one level's
        # mean, fails that sum); both are robust to one fold whose fit strays
        gain = None if best_cv is None else float(np.median(best_cv - cv))
        if gain is not None and np.sort(best_cv - cv)[:-1].sum() >= 0:
            gain = max(gain, 0.0)
        rounds.append([{"name": s["name"], "chi2": s["chi2"], "delta_bic": s["delta_bic"]}
                       for s in scores] + [{"cv_chi2_before": float(cv.sum()),
                                            "cv_chi2_best": None if best_cv is None
                                            else float(best_cv.sum()),
                                            "cv_median_fold_change": gain}])
        if best_cv is None or gain >= 0:
            final_scores = scores
            break
        current = current + [best["effect"]]
        fit, bic, cv = best["fit"], best["bic"], best_cv
        steps.append(_step_summary(problem, fit, current, f"+ {best['name']}"))
    last = steps[-1]
    per_lag = _per_lag(problem, fit)
    # a residual confined to a few lags is diluted in the global chi2: test each
    # lag's chi2 too, with the threshold divided by the number of lags (Bonferroni)
    lag_p = {k: float(stats.chi2.sf(v["chi2"], v["n"])) for k, v in per_lag.items()}
    worst_lag = min(lag_p, key=lag_p.get)
    lag_bad = lag_p[worst_lag] < p_threshold / len(lag_p)
    unexplained = last["p_value"] < p_threshold or lag_bad
    if unexplained:
        w = last["largest_residuals"][:3]
        where = ", ".join(f"{x['block']}({x['i']},{x['j']})" + (f"@{x['level']}"
                                                               if obs.kind != "table" else "")
                          + f" pull {x['pull']:+.1f}" for x in w)
        verdict = (f"unexplained residual: chi2/dof = {last['chi2_dof']:.2f} (p = "
                   f"{last['p_value']:.1e}; worst lag {worst_lag} p = {lag_p[worst_lag]:.1e}) "
                   "after "
                   + (", ".join(e.name for e in current) if current else "the base model alone")
                   + f"; nothing in the library explains what remains (largest: {where})")
    else:
        verdict = (f"residual consistent with noise: chi2/dof = {last['chi2_dof']:.2f} "
                   f"(p = {last['p_value']:.2f})"
                   + (" after adding " + ", ".join(e.name for e in current) if current
                      else " with the base model alone"))
    edge = None
    if getattr(obs, "edge_ratio", None) is not None:
        edge = edge_signature(obs.mu, obs.edge_ratio, obs.edge_sigma, p_threshold=p_threshold)
        if edge["detected"]:
            # a finding about pixels outside the fit: named in the verdict, but the
            # fit's own residual decides `unexplained`
            verdict += "; " + edge["description"]
    findings, signatures = _observable_checks(obs, problem, first, library, current,
                                              p_threshold)
    for sig in signatures:  # like the edge: named, outside the fit's own decision
        verdict += "; " + sig
    not_excluded = _not_excluded(problem, last, current, final_scores, basis)
    for r in rounds:
        for s in r:
            s.pop("fit", None)
            s.pop("effect", None)
    return Diagnosis(kind=obs.kind, effects_added=[e.name for e in current],
                     chi2_dof_before=steps[0]["chi2_dof"], chi2_dof_after=last["chi2_dof"],
                     steps=steps, candidates=rounds, not_identifiable=skipped,
                     tried=[e.name for e in usable], vocabulary=list(EFFECT_NAMES),
                     residuals_before=_per_lag(problem, first),
                     residuals_after=per_lag, verdict=verdict, worst_lag=worst_lag,
                     worst_lag_p=lag_p[worst_lag],
                     unexplained=bool(unexplained), n_points=int(n), note=obs.note,
                     base_scales=scales,
                     levels=[] if obs.kind == "table" else [float(v) for v in obs.mu],
                     edge=edge, observables=findings, signatures=signatures,
                     not_excluded=not_excluded)


def base_acoeffs(step, basis, max_lag):
    """The base model's a_ij of one diagnosis step, with errors.

    Parameters
    ----------
    step : dict
        One of ``Diagnosis.steps`` (``base_params`` and ``base_errors``).
    basis : LinearBasis
        The diagnosis' electrostatic basis.
    max_lag : int
        Largest lag.

    Returns
    -------
    a, sigma : ndarray, shape (max_lag + 1, max_lag + 1)
        a_ij (1/e) and their errors propagated through the basis from the
        parameters' covariance (``base_covariance``; from their errors alone
        when the step has none).
    """
    try:
        x = np.array([step["base_params"][n] for n in basis.names])
        e = np.array([step["base_errors"][n] for n in basis.names])
    except KeyError as exc:
        raise InputError(f"the diagnosis step has no base parameter {exc}") from None
    a = basis.a(x, max_lag)
    k = int(max_lag) + 1
    jac = basis.jacobian[:k, :k]
    cov = step.get("base_covariance")
    if cov is not None and np.shape(cov)[0] >= len(basis.names):
        # the base parameters come first, in the basis' order
        c = np.asarray(cov, float)[:len(basis.names), :len(basis.names)]
        sigma = np.sqrt(np.maximum(np.einsum("ijk,kl,ijl->ij", jac, c, jac), 0.0))
    else:
        sigma = np.sqrt(np.sum((jac * e) ** 2, axis=-1))
    return a, sigma


def _not_excluded(problem, last, current, scores, basis):
    """What each effect that was tried and not added would do to the base a00, a01.

    An effect below the detection threshold may still be there. Its
    candidate fit (the final model plus that effect) gives the base
    coefficients with it free: their shift from the final fit, in units of
    the final fit's errors, is the systematic the base a_ij carry if it is
    present (well filling below its threshold moves a00 by several sigma,
    ``docs/benchmarks.rst``). Sorted by the largest shift; empty without an
    electrostatic basis (PTC input).
    """
    if basis is None or problem.obs.kind == "ptc" or not scores:
        return []
    a, sd = base_acoeffs(last, basis, 1)  # the final step, already summarised
    out = []
    for sc in scores:
        e = sc["effect"]
        if e in current:
            continue
        step = _step_summary(problem, sc["fit"], current + [e], e.name)
        aw, sw = base_acoeffs(step, basis, 1)
        eff = step["effects"][-1]
        out.append({"effect": e.name, "delta_bic": float(sc["delta_bic"]),
                    "params": eff["params"], "errors": eff["errors"],
                    **{f"a{i}{j}": [float(aw[i, j]), float(sw[i, j])]
                       for i, j in ((0, 0), (0, 1))},
                    **{f"a{i}{j}_shift_sd": float((aw[i, j] - a[i, j]) / sd[i, j])
                       for i, j in ((0, 0), (0, 1))}})
    out.sort(key=lambda d: -max(abs(d["a00_shift_sd"]), abs(d["a01_shift_sd"])))
    return out


def _observable_checks(obs, problem, fit, library, added, p_threshold):
    """Findings of every observable beside the fit (base fit ``fit``), credited."""
    kw = {}
    if obs.kind == "flats":
        nc = obs.cov.size
        x = dict(zip(problem.names, fit["x"]))
        kw = dict(model=fit["model"][:nc].reshape(obs.cov.shape),
                  sigma=problem.sigma[:nc].reshape(obs.cov.shape), gain=x["gain"],
                  noise=x["noise"])
    elif obs.kind == "table" and obs.mask.all():
        kw = dict(model=fit["model"].reshape(obs.a.shape))
    findings = assess_observables(obs, p_threshold=p_threshold, **kw)
    return findings, credit_findings(findings, library, added)


def load_input(path, *, max_lag=3):
    """Observations from a path: a_ij table, PTC text file or directory of flat pairs.

    A directory's FITS files (``*.fits``, ``*.fit``, ``*.fits.gz``), sorted by
    name, form consecutive pairs; temporary files (``.tmp-*``, see
    :func:`~lsst_bfdrift.utils.io.data_files`) are ignored. A file's kind is
    found as ``bfdrift calibrate`` finds it
    (:func:`~lsst_bfdrift.ptc.inputs.detect_input_kind`): an a_ij table (text
    ``i j value sigma`` or ECSV with its units checked) is read by
    :func:`~lsst_bfdrift.ptc.inputs.read_amatrix_file`, a two-column PTC by
    :func:`~lsst_bfdrift.ptc.covariances.read_ptc_text`; FITS files are
    refused (flats go in a directory).

    Returns
    -------
    Observations
    """
    path = os.fspath(path)
    if os.path.isdir(path):
        full = data_files(path, (".fits", ".fit", ".fits.gz"))  # never a .tmp-* leftover
        if len(full) < 8 or len(full) % 2:
            raise InputError(f"{path}: need an even number (>= 8) of FITS flats forming "
                             f"consecutive pairs, found {len(full)}")
        return observations_from_pairs(list(zip(full[::2], full[1::2])), max_lag=max_lag)
    if not os.path.isfile(path):
        raise InputError(f"{path}: no such file or directory")
    kind = detect_input_kind(path)  # the one reader of calibrate: units, orientation
    if kind == "amatrix":
        return Observations.from_table(read_amatrix_file(path).acoeff_table())
    if kind == "ptc":
        mu, var = read_ptc_text(path)
        try:
            return Observations.from_ptc(mu, var)
        except InputError as err:
            raise InputError(f"{path}: {err}") from None
    what = "a flat" if kind == "flats" else "a cp_pipe PTC dataset"
    raise InputError(f"{path}: a FITS file ({what}); diagnose takes an a_ij table (text i j "
                     "value sigma, or ECSV), a PTC text file (mean, variance) or a directory "
                     "of flat pairs")
