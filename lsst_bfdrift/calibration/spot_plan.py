"""How many spots a lab needs: the acquisition plan from a spot fit's own stated precision.

A spot series pins the e1 slope that flats cannot see
(:mod:`~lsst_bfdrift.calibration.spot_fit`), as well as it measures it.
:func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots` states how
well the corrected slopes are known from the a-matrix's errors alone
(``flats``) and with the spots (``joint``)
(``StarCalibrationResult.uncertainty``: ``e1_slope_sigma`` in % of the e1
slope the flats template removes, ``size_slope_sigma`` in % of the
uncorrected size slope). The fit is a Gaussian update of the flats'
estimate, and the spots' information adds up over spots, so that for N
spots of one design

.. math::

    \\sigma^{-2}(N) = \\sigma_f^{-2} + \\frac{N}{N_0}\\,
        \\frac{I(D)}{I(D_0)} \\left(\\sigma_j^{-2} - \\sigma_f^{-2}\\right)

where the fitted series had :math:`N_0` spots of design :math:`D_0` and
stated :math:`\\sigma_j`, and :math:`I(D)` is the information one spot of
design D gives on the slope in % of itself: :func:`design_information`
times the square of the slope the flats template predicts for that design
(:func:`information_ratio`; a wider spot has a smaller slope). Solving for the
goal gives the spots needed (:func:`spots_for_precision`; the same update
as :func:`~lsst_bfdrift.calibration.star_result.fields_for_precision` for
star fields). Along one direction of the fit this is exact; with several
directions it is the rate along the one the spots fix best, so it can
understate the spots needed when the goal asks for directions the fitted
series hardly constrained (the benchmark
``benchmarks/calibration/spots_stars.py`` compares the plan with the fit
of more spots).

A design (:class:`SpotDesign`) is the spot sigma, the mean spot flux of
each exposure, the read noise and background. The information of one spot
on a slope (per 1e5 e) is that of a weighted straight line with its own
intercept,

.. math::

    I = \\sum_i w_i (g_i - \\bar g_w)^2, \\quad w_i = 1 / \\sigma_q^2(F_i),
    \\quad g_i = F_i / 10^5\\ {\\rm e},

with the row errors :math:`\\sigma_q(F)` those the measurement propagates
for a pixel-integrated Gaussian spot of flux F with Poisson noise, read
noise and background (:func:`spot_row_errors`: the same fixed weight,
:func:`~lsst_bfdrift.catalogs.spots.fixed_weight_moments`). Photon noise
makes :math:`\\sigma_q^2 \\propto 1 / F` at high flux, so the weights grow
with the flux and the information as the cube of the largest flux: the
lever arm is best spent where the photons are (three exposures at 0.3 of
the top flux and three at the top carry 1.5 times the information of six
geometric levels from 1e4 e). A spot of sigma s saturates at about
``peak / p(s)`` e (:func:`gaussian_peak_fraction`, ``p`` the peak pixel's
share), so a wider spot carries more information per spot on its slope in
absolute terms, but its slope is smaller (:func:`information_ratio`).
"""

import dataclasses

import numpy as np
from scipy.special import erf

from lsst_bfdrift.catalogs.slopes import FLUX_UNIT
from lsst_bfdrift.catalogs.spots import RADIUS_FACTOR, WEIGHT_FACTOR, fixed_weight_moments
from lsst_bfdrift.correction.solvers import recorded_image
from lsst_bfdrift.templates.swept import SweptAreas
from lsst_bfdrift.utils.errors import InputError

__all__ = ["SpotDesign", "gaussian_peak_fraction", "spot_row_errors", "design_information",
           "predicted_slope", "information_ratio",
           "spots_for_precision", "precision_for_spots", "series_design",
           "plan_spot_acquisition",
           "PLAN_QUANTITIES", "PLAN_GOALS"]

#: Slopes planned for, and the key of their stated precision in ``uncertainty``.
PLAN_QUANTITIES = {"e1": "e1_slope_sigma", "size": "size_slope_sigma"}
#: Default goals (% standard deviation): the issue-42 target (e1 5 %, size 2 %
#: left on stars) at one and two standard deviations.
PLAN_GOALS = {"e1": (5.0, 2.5), "size": (2.0, 1.0)}


def gaussian_peak_fraction(sigma):
    """Share of a pixel-centred Gaussian spot's flux in its peak pixel.

    Parameters
    ----------
    sigma : float
        Spot sigma (px).

    Returns
    -------
    float
    """
    return float(erf(0.5 / (np.sqrt(2.0) * float(sigma))) ** 2)


@dataclasses.dataclass(frozen=True)
class SpotDesign:
    """A spot series' design: what one spot of it is seen as.

    Parameters
    ----------
    sigma : float
        Spot sigma (px), without the pixel.
    levels : sequence of float
        Mean spot flux of each exposure (e); repeat a level for repeated
        exposures.
    read_noise : float, optional
        Read noise (e rms per pixel).
    background : float, optional
        Background (e per pixel, Poisson).
    weight_sigma : float, optional
        Sigma of the measurement's fixed weight (px); default the
        measurement's (:data:`~lsst_bfdrift.catalogs.spots.WEIGHT_FACTOR`
        times the pixel-convolved spot sigma).

    Raises
    ------
    InputError
        A sigma not positive, fewer than two levels or two distinct ones, a
        level not positive, or a negative noise.
    """

    sigma: float = 1.5
    levels: tuple = (1e4, 2.4e4, 5.9e4, 1.4e5, 3.5e5, 8.5e5)
    read_noise: float = 5.0
    background: float = 0.0
    weight_sigma: float = None

    def __post_init__(self):
        levels = tuple(float(v) for v in np.ravel(self.levels))
        object.__setattr__(self, "levels", levels)
        if not (np.isfinite(self.sigma) and self.sigma > 0):
            raise InputError(f"spot sigma must be a positive number of px, got {self.sigma!r}")
        if len(levels) < 2 or len(set(levels)) < 2 or not all(
                np.isfinite(v) and v > 0 for v in levels):
            raise InputError(f"levels must be two or more positive fluxes (e), two of them "
                             f"distinct, got {self.levels!r}")
        for name in ("read_noise", "background"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise InputError(f"{name} must be >= 0 (e), got {v!r}")
        if self.weight_sigma is not None and not self.weight_sigma > 0:
            raise InputError(f"weight_sigma must be positive (px), got {self.weight_sigma!r}")

    @property
    def weight(self):
        """The fixed weight's sigma (px)."""
        if self.weight_sigma is not None:
            return float(self.weight_sigma)
        return WEIGHT_FACTOR * float(np.sqrt(self.sigma ** 2 + 1.0 / 12.0))

    @classmethod
    def saturating(cls, sigma, n_images, *, flux_min=1e4, peak_max=8e4, **kwargs):
        """``n_images`` levels spaced geometrically from ``flux_min`` to the flux whose
        pixel-centred peak pixel is ``peak_max`` e (:func:`gaussian_peak_fraction`)."""
        top = float(peak_max) / gaussian_peak_fraction(sigma)
        if not top > flux_min:
            raise InputError(f"peak_max {peak_max:g} e is reached at {top:.3g} e, below "
                             f"flux_min {flux_min:g} e")
        return cls(sigma=sigma, levels=tuple(np.geomspace(flux_min, top, int(n_images))),
                   **kwargs)


def _unit_spot(design, extra=0):
    """Unit-flux pixel-integrated Gaussian, pixel-centred, and the measurement's radius."""
    ws = design.weight
    radius = max(RADIUS_FACTOR * ws, 3.0)
    half = int(np.ceil(radius)) + 1 + int(extra)
    edges = np.arange(-half, half + 2) - 0.5
    p1 = np.diff(0.5 * (1.0 + erf(edges / (np.sqrt(2.0) * design.sigma))))
    return np.outer(p1, p1) / np.sum(p1) ** 2, half, ws, radius


def spot_row_errors(flux, design, *, quantity="e1"):
    """Error of one spot row's ``quantity`` at each flux, as the measurement propagates it.

    A pixel-integrated, pixel-centred Gaussian of the design's sigma, its
    variance the spot's own (Poisson) plus read noise squared and
    background, measured with the design's fixed weight
    (:func:`~lsst_bfdrift.catalogs.spots.fixed_weight_moments`).

    Parameters
    ----------
    flux : array_like
        Spot fluxes (e).
    design : SpotDesign
    quantity : {'sigma_x', 'sigma_y', 'size', 'e1', 'e2'}, optional

    Returns
    -------
    ndarray
        Errors (the quantity's unit: px for sigma_x and sigma_y).
    """
    unit, half, ws, radius = _unit_spot(design)
    out = []
    for f in np.ravel(np.asarray(flux, float)):
        img = f * unit
        var = img + design.read_noise ** 2 + design.background
        m = fixed_weight_moments(img, weight_sigma=ws, radius=radius, center=(half, half),
                                 variance=var, tol=1e-6)
        out.append(m[f"{quantity}_err"])
    return np.asarray(out)


def design_information(design, *, quantity="e1"):
    """Information one spot of ``design`` gives on the slope of ``quantity`` per 1e5 e.

    Parameters
    ----------
    design : SpotDesign
    quantity : str, optional
        As :func:`spot_row_errors`.

    Returns
    -------
    float
        ``sum w (g - g_w)^2`` (module docstring), in 1 / (quantity per 1e5 e)^2:
        the inverse variance of one spot's slope with its own intercept.
    """
    g = np.asarray(design.levels) / FLUX_UNIT
    w = 1.0 / spot_row_errors(design.levels, design, quantity=quantity) ** 2
    return float(np.sum(w * (g - np.sum(w * g) / np.sum(w)) ** 2))


def _line_slope(design, values, quantity):
    """Slope per 1e5 e of ``values`` at the design's levels, weighted by its row errors."""
    g = np.asarray(design.levels) / FLUX_UNIT
    w = 1.0 / spot_row_errors(design.levels, design, quantity=quantity) ** 2
    gb = np.sum(w * g) / np.sum(w)
    return float(np.sum(w * (g - gb) * values) / np.sum(w * (g - gb) ** 2))


def predicted_slope(template, design, *, quantity="e1"):
    """The slope a template predicts for one spot of ``design`` (drift forward model).

    The design's round Gaussian spot at each level is put through
    :func:`~lsst_bfdrift.correction.solvers.recorded_image` and measured with
    the design's fixed weight; the slope is fitted with the design's row
    weights, as the spot fit does.

    Parameters
    ----------
    template : DistortionTemplate
    design : SpotDesign
    quantity : {'sigma_x', 'sigma_y', 'size', 'e1', 'e2'}, optional

    Returns
    -------
    float
        Slope per 1e5 e (the quantity's unit).
    """
    unit, half, ws, radius = _unit_spot(design, extra=template.center + 1)
    swept = SweptAreas(template, unit.shape)
    values = []
    for f in design.levels:
        m = fixed_weight_moments(recorded_image(f * unit, swept), weight_sigma=ws,
                                 radius=radius, center=(half, half), tol=1e-6)
        values.append(m[quantity])
    return _line_slope(design, np.asarray(values), quantity)


def spots_for_precision(flats_percent, joint_percent, n_spots, goal_percent, *,
                        information_ratio=1.0):
    """Spots needed to state a slope to a goal, from a fitted series' stated precision.

    Parameters
    ----------
    flats_percent, joint_percent : float
        Stated standard deviation of the corrected slope from the a-matrix's
        errors alone and with the fitted series (%).
    n_spots : int
        Spots in the fitted series.
    goal_percent : float
        The standard deviation wanted (%).
    information_ratio : float, optional
        Information per spot of the planned design over the fitted one's
        (:func:`design_information`).

    Returns
    -------
    int or None
        Spots of the planned design (0 when the flats meet the goal); None
        when the fitted series adds no measurable information or an input is
        not finite.

    Raises
    ------
    InputError
        A precision, the goal or the ratio not positive, or ``n_spots`` < 1.
    """
    f, j, g, r = (float(v) for v in (flats_percent, joint_percent, goal_percent,
                                     information_ratio))
    if not all(np.isfinite(v) for v in (f, j, g, r)):
        return None
    if min(f, j, g, r) <= 0 or int(n_spots) < 1:
        raise InputError(f"precisions, goal and information ratio must be > 0 and n_spots >= "
                         f"1, got flats {f}, joint {j}, goal {g}, ratio {r}, n_spots {n_spots}")
    if f <= g:
        return 0
    per_spot = (1.0 / j ** 2 - 1.0 / f ** 2) / int(n_spots) * r
    if per_spot <= 1e-12 / f ** 2:
        return None
    return int(np.ceil((1.0 / g ** 2 - 1.0 / f ** 2) / per_spot - 1e-9))


def precision_for_spots(flats_percent, joint_percent, n_spots, n_planned, *,
                        information_ratio=1.0):
    """The precision a series of ``n_planned`` spots would state (the inverse of
    :func:`spots_for_precision`).

    Parameters
    ----------
    flats_percent, joint_percent : float
        Stated standard deviation of the corrected slope from the a-matrix's
        errors alone and with the fitted series (%).
    n_spots : int
        Spots in the fitted series.
    n_planned : float
        Spots of the planned design (a sum over designs: each design's
        spots times its information ratio, with ``information_ratio`` 1).
    information_ratio : float, optional
        Information per spot of the planned design over the fitted one's.

    Returns
    -------
    float
        Standard deviation (%): ``(1/f^2 + n_planned r (1/j^2 - 1/f^2) / n_spots)^-1/2``;
        nan when an input is not finite.

    Raises
    ------
    InputError
        A precision or the ratio not positive, ``n_spots`` < 1 or
        ``n_planned`` < 0.
    """
    f, j, r, n = (float(v) for v in (flats_percent, joint_percent, information_ratio,
                                     n_planned))
    if not all(np.isfinite(v) for v in (f, j, r, n)):
        return float("nan")
    if min(f, j, r) <= 0 or int(n_spots) < 1 or n < 0:
        raise InputError(f"precisions and information ratio must be > 0, n_spots >= 1 and "
                         f"n_planned >= 0, got flats {f}, joint {j}, ratio {r}, n_spots "
                         f"{n_spots}, n_planned {n}")
    per_spot = max(1.0 / j ** 2 - 1.0 / f ** 2, 0.0) / int(n_spots)
    return float((1.0 / f ** 2 + n * r * per_spot) ** -0.5)


def information_ratio(template, design, reference, *, quantity="e1"):
    """Information per spot of ``design`` over ``reference``'s, on a slope in % of itself.

    ``I(D) s(D)^2 / (I(D0) s(D0)^2)``: the information on the slope
    (:func:`design_information`) times the square of the slope the template
    predicts for that design (:func:`predicted_slope`), since a precision in
    % of the slope is what the plan asks for, and wider spots have smaller
    slopes. This assumes a template change moves every design's slope in
    proportion to the slope itself.

    Parameters
    ----------
    template : DistortionTemplate
        The template whose slopes scale the information (the flats template).
    design, reference : SpotDesign
    quantity : str, optional

    Returns
    -------
    float
    """
    def weighted(d):
        return design_information(d, quantity=quantity) * predicted_slope(
            template, d, quantity=quantity) ** 2
    return float(weighted(design) / weighted(reference))


def series_design(series, *, read_noise=5.0, background=0.0):
    """The design of a measured spot series, and its usable spots.

    Parameters
    ----------
    series : SpotSeries
        The measured series (:class:`~lsst_bfdrift.catalogs.spot_series.SpotSeries`).
    read_noise, background : float, optional
        As :class:`SpotDesign` (e).

    Returns
    -------
    design : SpotDesign
        The spot sigma from the grid's median adaptive sigma (the pixel's
        1/12 px^2 taken out), the mean flux of each image's usable rows as
        its levels, the series' fixed weight.
    n_spots : int
        Spots with at least one usable row.

    Raises
    ------
    InputError
        Fewer than two images with usable rows, or no finite adaptive sigma.
    """
    cat = series.catalog
    use = np.asarray(cat["use"], bool)
    flux = np.asarray(getattr(cat["flux"], "value", cat["flux"]), float)
    image = np.asarray(cat["image"])
    used = np.unique(image[use])
    if used.size < 2:
        raise InputError(f"a spot series needs usable spots in 2 or more images to plan "
                         f"from, got {used.size}")
    adaptive = float(series.grid.adaptive_sigma)
    if not (np.isfinite(adaptive) and adaptive ** 2 > 1.0 / 12.0):
        raise InputError(f"the series' spots have no measured size (adaptive sigma "
                         f"{adaptive!r} px)")
    levels = tuple(float(np.mean(flux[use & (image == i)])) for i in used)
    design = SpotDesign(sigma=float(np.sqrt(adaptive ** 2 - 1.0 / 12.0)), levels=levels,
                        read_noise=read_noise, background=background,
                        weight_sigma=float(series.grid.weight_sigma))
    return design, int(np.unique(np.asarray(cat["spot"])[use]).size)


def plan_spot_acquisition(result, name, *, fitted_design, n_spots, designs=None, goals=None,
                          template=None):
    """Spots and exposures that state the corrected e1 and size slopes to goals.

    Parameters
    ----------
    result : StarCalibrationResult or dict
        From :func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`,
        or its ``summary()`` (the ``spots`` of ``bfdrift calibrate --json``).
    name : str
        The fitted spot series (its name in the result).
    fitted_design : SpotDesign
        The design of that series (its levels, spot sigma and read noise).
    n_spots : int
        Spots of that series in the fit.
    designs : dict, optional
        Label -> SpotDesign planned for (default the fitted design). Their
        information relative to the fitted design's is
        :func:`information_ratio` with ``template``.
    goals : dict, optional
        Quantity -> goals (% standard deviation; default :data:`PLAN_GOALS`).
    template : DistortionTemplate, optional
        The template whose slopes scale the information of other designs
        (default the result's flats template; needed only for designs other
        than the fitted one).

    Returns
    -------
    dict
        ``stated`` (per quantity: ``flats_percent``, ``joint_percent``),
        ``n_spots_fitted`` and ``rows``: per design, quantity and goal,
        ``spots`` (0 when the flats meet the goal, None when the series adds
        nothing measurable), ``exposures`` (spot images: spots times
        levels), ``information_ratio`` and a one-line ``text``.

    Raises
    ------
    InputError
        A goal for a quantity not in :data:`PLAN_QUANTITIES`, ``name``
        without a stated precision in ``result`` (not a fitted series, or a
        fit without the a-matrix's error directions), or another design
        without a template.
    """
    unc = (result.get("uncertainty") if isinstance(result, dict)
           else result.uncertainty) or {}
    if template is None and not isinstance(result, dict):
        template = result.flats_template
    goals = dict(goals or PLAN_GOALS)
    designs = dict(designs or {"as fitted": fitted_design})
    if template is None and any(d != fitted_design for d in designs.values()):
        raise InputError("designs other than the fitted one need a template to scale their "
                         "information (information_ratio)")
    stated = {}
    for q in goals:
        if q not in PLAN_QUANTITIES:
            raise InputError(f"goals may name {tuple(PLAN_QUANTITIES)}, got {q!r}")
        per = unc.get(PLAN_QUANTITIES[q]) or {}
        if name not in per:
            raise InputError(f"no stated {q} precision for spot series {name!r} in the result "
                             f"(fitted: {sorted(per) or 'none'}); fit with flats_uncertainty")
        stated[q] = {k: float(per[name][k]) for k in ("flats_percent", "joint_percent")}
    rows = []
    for label, d in designs.items():
        for q, gs in goals.items():
            ratio = 1.0 if d == fitted_design else information_ratio(
                template, d, fitted_design, quantity=q)
            for g in np.ravel(gs):
                n = spots_for_precision(stated[q]["flats_percent"], stated[q]["joint_percent"],
                                        n_spots, g, information_ratio=ratio)
                exp = None if n is None else n * len(d.levels)
                text = (f"{label} (sigma {d.sigma:g} px, {len(d.levels)} levels "
                        f"{d.levels[0]:.3g}-{d.levels[-1]:.3g} e, read noise {d.read_noise:g} "
                        f"e; information per spot x {ratio:.3g}): {q} to +- {g:g} %: " + (
                            "no measurable information from the fitted spots" if n is None
                            else f"{n} spots ({exp} spot images)"))
                rows.append({"design": label, "quantity": q, "goal_percent": float(g),
                             "spots": n, "exposures": exp, "information_ratio": ratio,
                             "sigma": d.sigma, "levels": list(d.levels), "text": text})
    return {"stated": stated, "n_spots_fitted": int(n_spots), "rows": rows}
