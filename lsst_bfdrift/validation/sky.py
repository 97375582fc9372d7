"""Sky validation without truth: is there a brighter-fatter slope in a star field?

The brighter-fatter effect makes bright stars larger (and slightly more
elongated along the parallel axis) than faint stars with the same PSF. On a
real image there is no BF-free truth, but every star samples the same PSF
field, so the BF signature is a dependence of star size and shape on flux at
fixed position, fitted by
:func:`~lsst_bfdrift.catalogs.slopes.shape_flux_relations`.

:func:`validate_sky` measures the slopes before and after correction: the
catalog-level correction (:func:`~lsst_bfdrift.validation.shape_correction.correct_catalog`),
the pixel-level Task (:class:`~lsst_bfdrift.correction.task.BrighterFatterDriftTask`)
followed by a new catalog, or both. ``residual_bf_detected`` is True when
any after-correction slope (size, e1 or e2) differs from zero by more than
``z_crit`` standard errors (default 3: a false-alarm probability of about
0.8 % for the three tests together under Gaussian errors).
"""

import numpy as np
from astropy import units as u
from astropy.nddata import CCDData

from lsst_bfdrift.utils.progress import ProgressBar

from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.catalogs.slopes import shape_flux_relations
from lsst_bfdrift.catalogs.catalog import measure_stars
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.templates.template import load_default_template
from lsst_bfdrift.validation.shape_correction import correct_catalog

__all__ = ["validate_sky", "sky_verdict", "SkyValidation"]


class SkyValidation:
    """Result of :func:`validate_sky`.

    Attributes
    ----------
    summary : dict
        JSON-ready: ``before`` and ``after`` (per route) relations, and the
        verdict fields of :func:`sky_verdict`: ``bf_detected_before``,
        ``residual_bf_detected``, ``significance_before`` and
        ``significance_after`` (signed z of the size slope, the number the
        verdict prints; positive: bright stars larger), ``max_significance_after``
        (largest ``|z|`` of the size, e1 and e2 slopes), ``removed_fraction``
        and ``verdict`` (a sentence).
    catalog : QTable
        Catalog of the recorded image.
    corrected : dict of QTable
        Corrected catalog per route (``catalog``, ``pixel``).
    fits : dict
        Relations per catalog name (``before``, and each route).
    """

    def __init__(self, summary, catalog, corrected, fits):
        self.summary = summary
        self.catalog = catalog
        self.corrected = corrected
        self.fits = fits


def _compact(rel):
    out = {}
    for k in ("size", "e1", "e2", "size_mag"):
        r = rel[k]
        out[k] = {"slope": r["slope"], "slope_err": r["slope_err"], "z": r["z"],
                  "err_formal": r["err_formal"], "err_boot": r["err_boot"], "tau": r["tau"],
                  "alpha": r["alpha"], "beta": r["beta"],
                  "chi2_dof": r["chi2_dof"], "n_downweighted": r["n_downweighted"],
                  "poly_order": r["poly_order"]}
    out["n_stars"] = rel["n_stars"]
    out["flux_range_e"] = rel["flux_range"]
    return out


def validate_sky(exposure, *, gain=None, mask=None, saturation=None, template=None,
                 route="catalog", method="drift", z_crit=3.0, min_snr=30.0, poly_order=2,
                 noise_term=True, n_boot=200, seed=20151, history=0.5, catalog_kwargs=None,
                 progress=False):
    """Size- and ellipticity-flux slopes of the stars of an image, before and after correction.

    Parameters
    ----------
    exposure : ndarray, CCDData, NDData or path
        The image (electrons, or ADU with ``gain`` / GAIN keyword). Never modified.
    gain : float, optional
        e/ADU.
    mask : array_like of bool, optional
        Bad pixels.
    saturation : float, optional
        Saturation level in the image unit (default: SATURATE keyword).
    template : DistortionTemplate, optional
        Green's function of the corrections (default: the bundled template).
    route : {'catalog', 'pixel', 'both', 'none'}, optional
        Correction route(s) to validate.
    method : str, optional
        Task method for the pixel route.
    z_crit : float, optional
        Significance (standard errors) at which a slope counts as detected.
    min_snr, poly_order, noise_term, n_boot, seed
        See :func:`shape_flux_relations`.
    history : float, optional
        History factor of the catalog-level correction.
    catalog_kwargs : dict, optional
        Extra options of :func:`~lsst_bfdrift.catalogs.catalog.measure_stars`.
    progress : bool, optional
        Progress messages on stderr.

    Returns
    -------
    SkyValidation
    """
    if route not in ("catalog", "pixel", "both", "none"):
        raise InputError(f"route must be catalog, pixel, both or none, got {route!r}")
    if not z_crit > 0:
        raise InputError(f"z_crit must be positive, got {z_crit}")
    image = to_electrons(exposure, gain=gain, mask=mask, saturation=saturation)
    image.warn()
    data, bad, sat_e, g, sat_pix = (image.data, image.bad, image.saturation, image.gain,
                                    image.sat_plane)
    ckw = dict(catalog_kwargs or {})
    cat = measure_stars(data, mask=bad, saturation=sat_e, saturated=sat_pix, progress=progress,
                        **ckw)
    ny, nx = data.shape
    frame = (0.5 * (nx - 1), 0.5 * (ny - 1), 0.5 * nx, 0.5 * ny)
    kw = dict(min_snr=min_snr, poly_order=poly_order, noise_term=noise_term, n_boot=n_boot,
              seed=seed, frame=frame)
    steps = 1 + {"none": 0, "catalog": 2, "pixel": 3, "both": 5}.get(route, 0)
    bar = ProgressBar(steps, "validate-sky fits", enabled=progress)
    fits = {"before": shape_flux_relations(cat, **kw)}
    bar(1)
    corrected = {}
    if route != "none" and template is None:
        template = load_default_template()
    if route in ("catalog", "both"):
        corrected["catalog"] = correct_catalog(cat, data, template=template, mask=bad,
                                               history=history)
        bar(1)
        fits["catalog"] = shape_flux_relations(corrected["catalog"], **kw)
        bar(1)
    if route in ("pixel", "both"):
        cfg = BrighterFatterDriftConfig(method=method, compute_geometry=False,
                                        saturation=sat_e)
        res = BrighterFatterDriftTask(config=cfg, template=template).run(
            CCDData(data, unit=u.electron, mask=bad))
        bar(1)
        corrected["pixel"] = measure_stars(np.asarray(res.exposure.data), mask=bad,
                                           saturation=sat_e, **ckw)
        bar(1)
        fits["pixel"] = shape_flux_relations(corrected["pixel"], **kw)
        bar(1)
    if progress:
        bar._draw(final=True)
    before = fits["before"]
    summary = {"image_shape": [int(ny), int(nx)], "gain": g, "route": route,
               "z_crit": float(z_crit), "min_snr": float(min_snr),
               "n_detections": len(cat), "n_stars_used": before["n_stars"],
               "units": {"size": "fractional change of T = Ixx + Iyy per 1e5 e",
                         "e1": "change of e1 per 1e5 e", "e2": "change of e2 per 1e5 e",
                         "size_mag": "fractional change of T per magnitude"},
               "before": _compact(before)}
    routes = [r for r in ("catalog", "pixel") if r in fits]
    summary["after"] = {r: _compact(fits[r]) for r in routes}
    summary.update(sky_verdict(fits, z_crit=z_crit))
    return SkyValidation(summary, cat, corrected, fits)


def sky_verdict(fits, *, z_crit=3.0):
    """The verdict fields of :func:`validate_sky` from the slopes before and after correction.

    Every significance is the signed ``z = slope / slope_err`` of a slope,
    the number the verdict sentence prints: positive for the size slope
    means bright stars larger than faint ones (the sign of the
    brighter-fatter effect), negative smaller. A BF slope before correction
    is detected when the size slope's ``z > z_crit`` (one-sided: a slope of
    the opposite sign is not brighter-fatter, and the verdict says so); a
    residual slope after correction when any of the size, e1 and e2 slopes
    has ``|z| > z_crit`` (an over-correction counts).

    Parameters
    ----------
    fits : dict
        Relations (:func:`~lsst_bfdrift.catalogs.slopes.shape_flux_relations`)
        under ``before`` and each route done (``catalog``, ``pixel``); each
        has ``size``, ``e1`` and ``e2`` with ``slope``, ``slope_err`` and ``z``.
    z_crit : float, optional
        Significance (standard errors) at which a slope counts as detected.

    Returns
    -------
    dict
        ``bf_detected_before`` (bool), ``significance_before`` (signed z of
        the size slope before correction), ``residual_bf_detected`` (bool;
        without a route, whether BF is detected before), and with a route:
        ``significance_after`` (route -> signed z of the size slope after),
        ``max_significance_after`` (route -> largest ``|z|`` of the size, e1
        and e2 slopes after: what is compared with ``z_crit``),
        ``removed_fraction`` (route -> 1 - size slope after / before) and
        ``verdict`` (a sentence).
    """
    before = fits["before"]["size"]
    z_before = float(before["z"])
    routes = [r for r in ("catalog", "pixel") if r in fits]
    out = {"bf_detected_before": bool(z_before > z_crit), "significance_before": z_before}
    if not routes:
        out["residual_bf_detected"] = out["bf_detected_before"]
        out["verdict"] = (("BF slope detected (uncorrected image)" if z_before > z_crit else
                           "size-flux slope of the opposite sign to BF (uncorrected image; "
                           "bright stars smaller)" if z_before < -z_crit else
                           "no BF slope detected (uncorrected image)")
                          + f": size slope z = {z_before:+.1f}")
        return out
    zs = {r: max(abs(float(fits[r][k]["z"])) for k in ("size", "e1", "e2")) for r in routes}
    out["residual_bf_detected"] = bool(max(zs.values()) > z_crit)
    out["significance_after"] = {r: float(fits[r]["size"]["z"]) for r in routes}
    out["max_significance_after"] = zs
    s0 = before["slope"]
    out["removed_fraction"] = {r: (1 - fits[r]["size"]["slope"] / s0) if s0 else None
                               for r in routes}
    out["verdict"] = _verdict(fits, routes, z_crit)
    return out


def _verdict(fits, routes, z_crit):
    before = fits["before"]["size"]
    parts = []
    if before["z"] > z_crit:
        parts.append(f"BF size-flux slope detected before correction "
                     f"({before['slope']:+.2e} +- {before['slope_err']:.1e} per 1e5 e, "
                     f"z = {before['z']:+.1f})")
    elif before["z"] < -z_crit:
        parts.append(f"size-flux slope of the opposite sign to BF before correction (bright "
                     f"stars smaller: {before['slope']:+.2e} +- {before['slope_err']:.1e} per "
                     f"1e5 e, z = {before['z']:+.1f}); the stars cannot show whether a BF "
                     "correction works")
    else:
        parts.append(f"no significant BF slope before correction (z = {before['z']:+.1f}); "
                     "the stars cannot show whether a correction works")
    for r in routes:
        s = fits[r]["size"]
        bad = [k for k in ("size", "e1", "e2") if abs(fits[r][k]["z"]) > z_crit]
        if bad:
            what = ", ".join(f"{k} z = {fits[r][k]['z']:+.1f}" for k in bad)
            # BF makes stars grow with flux: a positive residual size slope is BF left over
            kind = ("under-corrected" if s["slope"] > 0 else "over-corrected") \
                if "size" in bad else "residual shape slope"
            parts.append(f"{r} route: residual BF slope remains ({what}; {kind})")
        else:
            parts.append(f"{r} route: BF removed, residual size slope {s['slope']:+.2e} +- "
                         f"{s['slope_err']:.1e} (z = {s['z']:+.1f}) and e1/e2 slopes within "
                         f"{z_crit:g} sigma")
    return "; ".join(parts)
