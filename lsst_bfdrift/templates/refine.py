"""Refinement of a template so that its pixel areas follow measured a_ij.

A template computed from fitted model parameters reproduces a measured
a-matrix only as well as the model can. :func:`match_area_coefficients` adds
the smallest boundary change that makes the template's linear area response
equal the measured a_ij at every measured lag: each edge's samples move
along its normal by one amount (the model's profile along the edge is kept),
and the amounts are the minimum-norm solution of the linearised area
equations, iterated on the exact polygon areas. A minimum-norm set of edge
shifts whose divergence is given is the gradient of a potential, so the
added displacement field is curl-free, like an electrostatic one.
Unmeasured lags keep the model's areas; the outer boundary of the template
does not move.
"""

import numpy as np

from lsst_bfdrift.templates.template import DistortionTemplate
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["template_alpha", "lag_multiplicity", "match_area_coefficients", "curl_free_template",
           "area_response_directions", "draw_templates", "combine_templates",
           "template_difference", "without_parameter_modes"]


def lag_multiplicity(max_lag):
    """Number of signed lags each quadrant lag stands for: 1 at (0, 0), 2 on the
    axes, 4 off them; shape (L + 1, L + 1)."""
    m = np.full((max_lag + 1, max_lag + 1), 4.0)
    m[0, :] = 2.0
    m[:, 0] = 2.0
    m[0, 0] = 1.0
    return m


def template_alpha(template):
    """Linear area response d A / d Q at Q = 0 of every pixel (1/e), shape (N, N).

    Displacements scale linearly with the charge and areas are quadratic in
    them, so alpha = (4 (A(Q/2) - 1) - (A(Q) - 1)) / Q exactly.
    """
    q = template.charge
    full = template.moments(charge=q).area
    half = template.moments(charge=0.5 * q).area
    return (4.0 * (half - 1.0) - (full - 1.0)) / q


def _with_edges(template, vedge_d, hedge_d, meta=None):
    return DistortionTemplate(template.corner_d, vedge_d, hedge_d, template.fractions,
                              template.charge, vedge_t=template.vedge_t,
                              hedge_t=template.hedge_t,
                              meta=template.meta if meta is None else meta)


def _incidence(n):
    """Sparse-free incidence of interior edges on pixel areas: (n*n, n_edges).

    Vertical edge (j, i) (1 <= i <= n - 1) is the right edge of pixel
    (j, i - 1) and the left edge of pixel (j, i); moving it by +u in x adds
    u to the first and removes it from the second. Horizontal edges likewise
    in y.
    """
    cols = []
    for j in range(n):
        for i in range(1, n):
            col = np.zeros((n, n))
            col[j, i - 1] += 1.0
            col[j, i] -= 1.0
            cols.append(col.ravel())
    for j in range(1, n):
        for i in range(n):
            col = np.zeros((n, n))
            col[j - 1, i] += 1.0
            col[j, i] -= 1.0
            cols.append(col.ravel())
    return np.stack(cols, axis=1)


def _matched(template, a, L):
    """Pixels [J, I] of the template whose lag (|I - c|, |J - c|) is matched."""
    n, c = template.size, template.center
    jj, ii = np.mgrid[0:n, 0:n]
    di, dj = np.abs(ii - c), np.abs(jj - c)
    matched = (di <= L) & (dj <= L)
    matched[matched] = np.isfinite(a[di[matched], dj[matched]])
    return matched


def _edge_solver(template, matched, free_weight):
    """solve(d_alpha, vedge_d, hedge_d) -> (vedge_d', hedge_d', largest shift): the
    minimum-norm uniform edge shifts whose area change is d_alpha (1/e per pixel)."""
    n, c, q = template.size, template.center, template.charge
    M = _incidence(n)
    # one unit shift of all samples of an edge (corners fixed) sweeps an
    # area h_eff (px^2 per px of shift): measured on the template itself
    probe = np.zeros_like(template.vedge_d)
    probe[c, c] = 1.0
    base = template.moments(charge=q).area
    h_eff = (_with_edges(template, template.vedge_d + probe, template.hedge_d)
             .moments(charge=q).area - base)[c, c - 1]
    w = np.where(matched, 1.0, float(free_weight)).ravel()
    pinv = np.linalg.pinv(M * h_eff * w[:, None])
    nv = n * (n - 1)

    def solve(d_alpha, vd, hd):
        u = pinv @ (np.asarray(d_alpha).ravel() * q * w)
        vd, hd = vd.copy(), hd.copy()
        vd[:, 1:n, :] += u[:nv].reshape(n, n - 1)[:, :, None]
        hd[1:n, :, :] += u[nv:].reshape(n - 1, n)[:, :, None]
        return vd, hd, float(np.abs(u).max())
    return solve


def match_area_coefficients(template, a, *, max_lag=None, iterations=3, free_weight=0.05):
    """Template whose linear area response equals measured a_ij.

    Parameters
    ----------
    template : DistortionTemplate
        Starting template (e.g. built from fitted sensor parameters).
    a : array_like, shape (L + 1, L + 1)
        Measured a_ij (1/e), indexed [i serial, j parallel], lags >= 0 (the
        template's four quadrants get the same value); NaN marks a lag that
        is not matched.
    max_lag : int, optional
        Match lags with max(i, j) <= ``max_lag`` only (default all of ``a``
        that fit in the template).
    iterations : int, optional
        Newton iterations on the exact polygon areas.
    free_weight : float, optional
        Weight of the unmatched pixels' equations (keep their areas) relative
        to the matched ones. The outer boundary is fixed, so the areas sum
        to a constant: where the measured a_ij and the model's unmatched
        lags do not sum to zero (the sum rule, which measured tables obey
        only within their errors), the unmatched pixels take up the
        difference instead of the matched ones.

    Returns
    -------
    DistortionTemplate
        A copy with shifted edge samples; ``meta['area_refined']`` records
        the largest shift (px at the template's charge) and the lags matched.
    """
    if not isinstance(template, DistortionTemplate):
        raise InputTypeError("template must be a DistortionTemplate, "
                             f"got {type(template).__name__}")
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or np.all(np.isnan(a)) or np.any(np.isinf(a)):
        raise InputError(f"a_ij must be a square array with finite values, got shape {a.shape}")
    n, c = template.size, template.center
    if max_lag is not None and not 0 <= int(max_lag) <= c - 1:
        raise InputError(f"max_lag must be in [0, {c - 1}] for a template of size {n}, "
                         f"got {max_lag!r}")
    L = min(a.shape[0] - 1, c - 1 if max_lag is None else int(max_lag))
    matched = _matched(template, a, L)
    target_alpha = template_alpha(template)
    jj, ii = np.mgrid[0:n, 0:n]
    di, dj = np.abs(ii - c), np.abs(jj - c)
    target_alpha[matched] = a[di[matched], dj[matched]]
    solve = _edge_solver(template, matched, free_weight)
    vd, hd = template.vedge_d, template.hedge_d
    total = 0.0
    for _ in range(int(iterations)):
        cur = template_alpha(_with_edges(template, vd, hd))
        vd, hd, big = solve(target_alpha - cur, vd, hd)
        total = max(total, big)
    meta = dict(template.meta)
    meta["area_refined"] = {"max_lag": int(L), "largest_shift_px": total}
    return _with_edges(template, vd, hd, meta)


def curl_free_template(template, a=None, *, iterations=4):
    """The curl-free template with a given area response: what the a-matrix alone says.

    Flats measure a pixel's area change, the divergence of the boundary
    shifts; they do not see how that change divides between its serial and
    parallel edges (a divergence-free, 'curl', part of the shifts). This
    template has no such part: its edge shifts are the minimum-norm
    (gradient) field with the area response ``a``, starting from straight,
    unmoved boundaries (corners fixed, each edge's samples moved by one
    amount). ``template - curl_free_template(template)`` is the part of the
    template's boundary field that flats cannot see; the star calibration
    uses it as a direction (:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`).

    Parameters
    ----------
    template : DistortionTemplate
        Gives the grid (size, edge samples, charge) and, when ``a`` is None,
        the area response.
    a : array_like, shape (L + 1, L + 1), optional
        a_ij (1/e), [i serial, j parallel]; default the template's own linear
        area response at every lag it holds (``L = center - 1``).
    iterations : int, optional
        Newton iterations on the exact polygon areas.

    Returns
    -------
    DistortionTemplate
        Same grid; ``meta['area_refined']`` as in :func:`match_area_coefficients`.
    """
    if not isinstance(template, DistortionTemplate):
        raise InputTypeError("template must be a DistortionTemplate, "
                             f"got {type(template).__name__}")
    c = template.center
    if a is None:
        a = template_alpha(template)[c:2 * c, c:2 * c].T
    a = np.asarray(a, dtype=float)
    zero = DistortionTemplate(np.zeros_like(template.corner_d), np.zeros_like(template.vedge_d),
                              np.zeros_like(template.hedge_d), template.fractions,
                              template.charge, meta=dict(template.meta))
    return match_area_coefficients(zero, a, max_lag=min(a.shape[0] - 1, c - 1),
                                   iterations=iterations)


def area_response_directions(template, sigma, *, max_lag=None, sum_rule=True):
    """The template changes the a-matrix's errors allow: the flats' uncertainty as directions.

    Each direction is a set of minimum-norm (curl-free) edge shifts (the
    solution :func:`match_area_coefficients` and :func:`draw_templates` use)
    whose linear area response changes the measured a_ij by one standard
    deviation of their errors along one axis, so that a template drawn from
    the errors is ``template`` plus the directions times independent
    standard normal numbers, and a step along a direction costs one unit of
    the a-matrix's chi2. The star calibration
    (:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`) moves
    the template along them.

    Pixel areas sum to a constant (the sum rule: sum over all lags of
    n_ij a_ij = 0, n_ij the number of pixels at lag (i, j): 1, 2 or 4). An
    error of one measured lag alone would push its area into the unmeasured
    far lags, where it weighs most on star sizes. With ``sum_rule`` (and a00
    measured) the errors are conditioned on the measured lags' area sum
    staying fixed (covariance C - C n n^T C / n^T C n, C = diag(sigma^2)):
    the directions are its eigenvectors times the square roots of its
    eigenvalues, one fewer than the lags, named ``mode0``, ``mode1``, ...
    by decreasing variance; the far lags do not move. Without it (or
    without a00), one direction per lag, ``a{i}{j}``, changes that a_ij by
    its error and no other measured lag.

    Parameters
    ----------
    template : DistortionTemplate
        Gives the grid (size, edge samples, charge); its own shifts are not
        used (the directions are changes).
    sigma : array_like, shape (L + 1, L + 1)
        Error of each a_ij (1/e), [i serial, j parallel]; NaN, zero or
        negative where the lag is not measured.
    max_lag : int, optional
        Lags with max(i, j) <= ``max_lag`` only (default all of ``sigma``
        that fit in the template).
    sum_rule : bool, optional
        Keep the measured lags' area sum (above).

    Returns
    -------
    dict
        name -> ``{"delta": displacement change (corner_d, vedge_d,
        hedge_d, vedge_t, hedge_t; pixel units at the template's charge;
        corners and transverse shifts do not move), "a_change": the a_ij
        change, shape (L + 1, L + 1), 1/e, NaN where not measured}``.
    """
    if not isinstance(template, DistortionTemplate):
        raise InputTypeError("template must be a DistortionTemplate, "
                             f"got {type(template).__name__}")
    sigma = np.asarray(sigma, dtype=float)
    if sigma.ndim != 2 or sigma.shape[0] != sigma.shape[1]:
        raise InputError(f"sigma must be a square array, got shape {sigma.shape}")
    c = template.center
    L = min(sigma.shape[0] - 1, c - 1 if max_lag is None else int(max_lag))
    good = np.isfinite(sigma) & (sigma > 0)
    good[L + 1:, :] = good[:, L + 1:] = False
    matched = _matched(template, np.where(good, 0.0, np.nan), L)
    solve = _edge_solver(template, matched, 0.05)
    jj, ii = np.mgrid[0:template.size, 0:template.size]
    di, dj = np.abs(ii - c), np.abs(jj - c)
    zv, zh = np.zeros_like(template.vedge_d), np.zeros_like(template.hedge_d)
    lags = [(i, j) for i in range(L + 1) for j in range(L + 1) if good[i, j]]
    sig = np.array([sigma[k] for k in lags])
    # the edge shifts of a unit (1/e) change of each lag; the solver is linear
    basis = []
    for i, j in lags:
        vd, hd, _ = solve(np.where(matched & (di == i) & (dj == j), 1.0, 0.0), zv, zh)
        basis.append((vd, hd))
    if sum_rule and (0, 0) in lags:
        n = lag_multiplicity(L)[tuple(np.array(lags).T)]
        cn = sig ** 2 * n
        cov = np.diag(sig ** 2) - np.outer(cn, cn) / float(n @ cn)
        w, u = np.linalg.eigh(cov)
        order = np.argsort(-w)
        keep = order[w[order] > 1e-12 * w.max()]
        modes = u[:, keep] * np.sqrt(w[keep])
        names = [f"mode{k}" for k in range(modes.shape[1])]
    else:
        modes = np.diag(sig)
        names = [f"a{i}{j}" if max(i, j) < 10 else f"a{i},{j}" for i, j in lags]
    out = {}
    for name, m in zip(names, modes.T):
        vd = sum(v * b[0] for v, b in zip(m, basis))
        hd = sum(v * b[1] for v, b in zip(m, basis))
        da = np.full((L + 1, L + 1), np.nan)
        for k, v in zip(lags, m):
            da[k] = v
        out[name] = {"delta": {"corner_d": np.zeros_like(template.corner_d), "vedge_d": vd,
                               "hedge_d": hd, "vedge_t": None, "hedge_t": None},
                     "a_change": da}
    return out


def combine_templates(base, deltas, coefficients, *, meta=None):
    """``base`` plus ``sum_k coefficients[k] * deltas[k]`` (displacement arrays).

    Parameters
    ----------
    base : DistortionTemplate
    deltas : sequence of dict
        Displacement changes: ``corner_d``, ``vedge_d``, ``hedge_d``,
        ``vedge_t``, ``hedge_t`` arrays (pixel units at ``base.charge``).
    coefficients : sequence of float
    meta : dict, optional
        Metadata of the result (default: the base's).

    Returns
    -------
    DistortionTemplate
    """
    arr = {}
    for name in ("corner_d", "vedge_d", "hedge_d", "vedge_t", "hedge_t"):
        b = getattr(base, name)
        has = b is not None or any(d.get(name) is not None for d in deltas)
        if not has:
            arr[name] = None
            continue
        a = np.zeros_like(base.vedge_d if name == "vedge_t" else base.hedge_d) \
            if b is None else np.array(b, float)
        for d, c in zip(deltas, coefficients):
            if d.get(name) is not None and c != 0:
                a = a + float(c) * d[name]
        arr[name] = a
    return DistortionTemplate(arr["corner_d"], arr["vedge_d"], arr["hedge_d"], base.fractions,
                              base.charge, vedge_t=arr["vedge_t"], hedge_t=arr["hedge_t"],
                              meta=dict(base.meta if meta is None else meta))


def template_difference(t1, t0):
    """Displacement difference ``t1 - t0`` of two templates of the same grid.

    Parameters
    ----------
    t1, t0 : DistortionTemplate
        Same size, edge samples and charge.

    Returns
    -------
    dict
        ``corner_d``, ``vedge_d``, ``hedge_d``, ``vedge_t``, ``hedge_t``
        differences (pixel units at the templates' charge; None where
        neither template has the array), as :func:`combine_templates` takes.
    """
    if t1.size != t0.size or t1.fractions.size != t0.fractions.size \
            or not np.isclose(t1.charge, t0.charge):
        raise InputError("templates differ in size, edge samples or charge")
    out = {}
    for name in ("corner_d", "vedge_d", "hedge_d", "vedge_t", "hedge_t"):
        a, b = getattr(t1, name), getattr(t0, name)
        if a is None and b is None:
            out[name] = None
            continue
        a = np.zeros_like(getattr(t1 if b is None else t0, name)) if a is None else a
        b = np.zeros_like(a) if b is None else b
        out[name] = a - b
    return out


def draw_templates(template, n, *, seed=0):
    """Templates drawn from the calibration uncertainty stored in ``template``.

    The uncertainty is that of the template's linear area response at the
    calibrated lags, ``template.meta['calibration']['uncertainty']``, written
    by :func:`~lsst_bfdrift.calibration.tuning.calibrate`:

    * ``kind='data'`` (a refined template, whose areas are the measured
      a_ij): independent Gaussian errors ``sigma`` [i, j] (1/e) per lag;
    * ``kind='parameters'``: d a_ij / d parameter (``jacobian``, [i, j, k])
      times a Gaussian draw of the fitted parameters (``covariance``).

    Each draw of the a_ij change is turned into edge shifts by the same
    minimum-norm curl-free solution as :func:`match_area_coefficients`, so
    that the draws differ from ``template`` by exactly the drawn area
    response (to first order). Where the record holds ``parameter_modes``
    (:func:`~lsst_bfdrift.calibration.tuning.parameter_modes`: what the
    fitted parameters' uncertainty does beyond the areas, how area changes
    divide between column and row edges), each draw adds every mode times
    an independent standard normal number (drawn after the area change).

    Parameters
    ----------
    template : DistortionTemplate
        A calibrated template.
    n : int
        Number of draws.
    seed : int, optional
        Seed of the random generator.

    Returns
    -------
    list of DistortionTemplate

    Raises
    ------
    ValueError
        The template carries no calibration uncertainty.
    """
    unc = (template.meta.get("calibration") or {}).get("uncertainty")
    if not unc:
        raise InputError("the template carries no calibration uncertainty (meta['calibration']"
                         "['uncertainty']): calibrate it with lsst_bfdrift.calibration.calibrate")
    if int(n) < 1:
        raise InputError(f"n must be a positive number of draws, got {n!r}")
    rng = np.random.default_rng(seed)
    c = template.center
    if unc["kind"] == "data":
        sigma = np.asarray(unc["sigma"], float)

        def delta():
            return np.where(np.isfinite(sigma), rng.normal(0.0, np.nan_to_num(sigma)), np.nan)
    elif unc["kind"] == "parameters":
        jac = np.asarray(unc["jacobian"], float)
        cov = np.asarray(unc["covariance"], float)
        sigma = jac[..., 0]

        def delta():
            return jac @ rng.multivariate_normal(np.zeros(cov.shape[0]), cov)
    else:
        raise InputError(f"unknown uncertainty kind {unc['kind']!r}")
    L = min(sigma.shape[0] - 1, c - 1)
    matched = _matched(template, np.where(np.isfinite(sigma), 0.0, np.nan), L)
    solve = _edge_solver(template, matched, 0.05)
    jj, ii = np.mgrid[0:template.size, 0:template.size]
    di, dj = np.abs(ii - c), np.abs(jj - c)
    modes = _padded_modes(template, unc.get("parameter_modes"))
    out = []
    for k in range(int(n)):
        d = delta()
        full = np.zeros((template.size, template.size))
        full[matched] = d[di[matched], dj[matched]]
        vd, hd, _ = solve(full, template.vedge_d, template.hedge_d)
        cd = template.corner_d
        if modes is not None:
            z = rng.standard_normal(modes[0].shape[0])
            cd = cd + np.tensordot(z, modes[0], axes=1)
            vd = vd + np.tensordot(z, modes[1], axes=1)[..., None]
            hd = hd + np.tensordot(z, modes[2], axes=1)[..., None]
        meta = dict(template.meta)
        meta["draw"] = {"index": k, "seed": int(seed)}
        out.append(DistortionTemplate(cd, vd, hd, template.fractions, template.charge,
                                      vedge_t=template.vedge_t, hedge_t=template.hedge_t,
                                      meta=meta))
    return out


def without_parameter_modes(calibration):
    """A copy of a template's ``meta['calibration']`` whose stored uncertainty
    has no parameter modes (the a_ij errors alone; the input is not modified).

    Parameters
    ----------
    calibration : dict or None

    Returns
    -------
    dict
    """
    calib = dict(calibration or {})
    if isinstance(calib.get("uncertainty"), dict):
        calib["uncertainty"] = {k: v for k, v in calib["uncertainty"].items()
                                if k != "parameter_modes"}
    return calib


def _padded_modes(template, record):
    """Parameter modes of a calibration record on the template's grid: (corner
    shifts (m, N + 1, N + 1, 2), column edge means (m, N, N + 1), row edge
    means (m, N + 1, N)), or None without modes."""
    if not record or not record.get("vedge_d"):
        return None
    size = int(record["size"])
    if size > template.size or size % 2 != 1:
        raise InputError(f"parameter modes of size {size} do not fit a template of size "
                         f"{template.size}")
    n, m = template.size, len(record["vedge_d"])
    o = template.center - size // 2
    cd, vd, hd = np.zeros((m, n + 1, n + 1, 2)), np.zeros((m, n, n + 1)), np.zeros((m, n + 1, n))
    cd[:, o:o + size + 1, o:o + size + 1] = np.asarray(record["corner_d"], float)
    vd[:, o:o + size, o:o + size + 1] = np.asarray(record["vedge_d"], float)
    hd[:, o:o + size + 1, o:o + size] = np.asarray(record["hedge_d"], float)
    return cd, vd, hd
