"""BrighterFatterDriftTask: correct exposures with the template as Green's function.

The Task only wires plain functions (:mod:`lsst_bfdrift.correction.steps`):
the image in electrons (:func:`~lsst_bfdrift.images.electrons.to_electrons`),
the flux redistribution
(:func:`~lsst_bfdrift.correction.solvers.correct_image` and the baselines)
and the final pixel geometry predicted from the recorded image
(:func:`~lsst_bfdrift.geometry.linear.linear_moment_maps` or
:func:`~lsst_bfdrift.geometry.superpose.moment_maps`).
"""

import math

import numpy as np

import lsst.pex.config as pexConfig

from lsst_bfdrift.correction.checks import input_warnings
from lsst_bfdrift.correction.settings import RECOMMENDED
from lsst_bfdrift.correction.steps import (BF_PLANE_DOC, FLAG_BLOCKED, FLAG_EDGE,  # noqa: F401
                                           apply_method, blocked_pixels, edge_flags, exact_maps,
                                           first_order_pass, flux_moved, flux_moved_error,
                                           linear_maps, masked_aggressors, package_output,
                                           result_header)
from lsst_bfdrift.images.electrons import to_electrons
from lsst_bfdrift.images.exposure import BLOCKING_PLANES
from lsst_bfdrift.templates.bands import MultiBandTemplate, band_key, load_templates
from lsst_bfdrift.templates.swept import OperatorCache, refuse_out_of_range
from lsst_bfdrift.templates.template import DistortionTemplate, load_default_template
from lsst_bfdrift.utils.config import Struct, Task
from lsst_bfdrift.utils.errors import InputError, InputTypeError

__all__ = ["BAND_KEYWORDS", "BrighterFatterDriftConfig", "BrighterFatterDriftTask",
           "exposure_band", "stage_order"]

#: Header keywords that give an exposure's band, in the order they are read.
BAND_KEYWORDS = ("BAND", "FILTER")

_METHODS = {
    "drift": "time-history series of the template's swept areas (order >= 3), inverted by "
             "a third-order series",
    "astier23": "Astier & Regnault 2023: per-electron boundary shifts (the template's swept "
                "areas), half the final shift, two-pixel flux density, one pass",
    "coulton18": "Coulton et al. 2018: kernel with Laplacian equal to the template's a_ij, "
                 "I = F + 1/2 div(F grad(K * F)), iterated",
}

#: How messages name the Task's gain and saturation (the CLI sets them from its options).
_GAIN_NAME = "--gain / config.gain"
_SATURATION_NAME = "--saturation / config.saturation"


class BrighterFatterDriftConfig(pexConfig.Config):
    """Configuration of :class:`BrighterFatterDriftTask` (an ``lsst.pex.config`` Config).

    Field names are snake_case, as everywhere in the package. A config file is
    a pex_config override file (``config.method = "astier23"``), read with
    :func:`~lsst_bfdrift.utils.config.load_config`.
    """

    template = pexConfig.Field(
        doc="template FITS file, one template or one per band (bfdrift template build "
            "--band, bfdrift calibrate); None uses the bundled default", dtype=str,
        default=None, optional=True)
    band = pexConfig.Field(
        doc="band of the exposures ('u' .. 'y' or a physical filter such as 'r_57') for a "
            "multi-band template; None: the exposure's BAND or FILTER keyword (the Butler's "
            "physical_filter in the PipelineTask). A band read from the exposure must agree; "
            "the template must hold it", dtype=str, default=None, optional=True)
    method = pexConfig.ChoiceField(
        doc="correction method", dtype=str, default="drift", allowed=_METHODS, optional=False)
    order = pexConfig.Field(
        doc="terms of the time-history series for method 'drift' (2 = half shift)",
        dtype=int, default=RECOMMENDED.order, check=lambda v: 2 <= v <= 8)
    density = pexConfig.ChoiceField(
        doc="flux density at pixel edges (drift)", dtype=str, default=RECOMMENDED.density,
        optional=False,
        allowed={"mean2": "mean of the two pixels beside the edge",
                 "cubic4": "four-point interpolation along the normal",
                 "fv4": "four-point finite-volume reconstruction from pixel averages"})
    max_iter = pexConfig.Field(
        doc="largest number of solver iterations", dtype=int, default=RECOMMENDED.max_iter,
        check=lambda v: v >= 1)
    rtol = pexConfig.Field(
        doc="convergence: max |I - R(F)| / max |I| (when noise_tol is None)", dtype=float,
        default=RECOMMENDED.rtol, check=lambda v: 0 < v < 1)
    noise_tol = pexConfig.Field(
        doc="convergence: |I - R(F)| <= noise_tol * sqrt(I) in every pixel (fraction of the "
            "Poisson noise); None: use rtol", dtype=float, default=RECOMMENDED.noise_tol,
        optional=True,
        check=lambda v: 0 < v < 1)
    start = pexConfig.ChoiceField(
        doc="first guess of the drift solver", dtype=str, default=RECOMMENDED.start,
        optional=False,
        allowed={"series": "third-order inverse series (three operator calls), iterated only "
                           "if an a-priori bound requires",
                 "image": "the recorded image"})
    fft_precision = pexConfig.ChoiceField(
        doc="precision of the FFT convolutions", dtype=str,
        default=RECOMMENDED.fft_precision, optional=False,
        allowed={"float32": "single (half the time and memory); the linear centroid and "
                            "ellipticity maps are returned in float32 too",
                 "float64": "double"})
    strip = pexConfig.Field(
        doc="rows per block for the drift and astier23 solvers (bounded memory); None: whole "
            "image", dtype=int, default=RECOMMENDED.strip, optional=True,
        check=lambda v: v >= 16)
    sparse = pexConfig.Field(
        doc="drift with start='series': second- and third-order terms only in windows around "
            "the sources that need them (bounded error; dense fallback)", dtype=bool,
        default=RECOMMENDED.sparse)
    gain = pexConfig.Field(
        doc="e/ADU: the image is in ADU (None: its BUNIT or GAIN keyword says; the unit "
            "rule of lsst_bfdrift.images.electrons)", dtype=float,
        default=None, optional=True, check=lambda v: math.isfinite(v) and v > 0)
    saturation = pexConfig.Field(
        doc="level at and above which pixels are blocked, in the image's units (e, or ADU for "
            "an image in ADU); None: the SATURATE keyword of the header if present, else the "
            "image's largest value when three or more unblocked pixels share it exactly, 10 "
            "sigma above the sky (a flat top, images.levels.plateau_level; with a warning), else no "
            "limit", dtype=float,
        default=None, optional=True, check=lambda v: math.isfinite(v) and v > 0)
    compute_geometry = pexConfig.Field(
        doc="compute area, centroid and ellipticity maps", dtype=bool, default=True)
    geometry_method = pexConfig.ChoiceField(
        doc="how the geometry maps are computed", dtype=str, default="linear", optional=False,
        allowed={"linear": "first order in the charge (FFT convolutions with the template's "
                           "moment kernels), exact polygon moments where an a-priori bound "
                           "exceeds geometry_tolerance (geometry.linear)",
                 "exact": "exact polygon moments of every pixel (geometry.superpose)"})
    geometry_tolerance = pexConfig.Field(
        doc="geometry_method 'linear': largest error against the exact maps in any pixel, as a "
            "fraction of each map's signal (its largest abs(map - nominal) over the image)",
        dtype=float, default=1e-3, check=lambda v: 0 < v < 1)
    geometry_samples = pexConfig.Field(
        doc="samples per pixel edge for the geometry maps (template edges resampled keeping "
            "swept areas and moments to first order: ~1e-5 of the signal for area and "
            "centroid, ~2e-4 for e2, 4x less CPU than the 32-sample default; "
            "superpose.resample_template); templates with no more samples are used as they "
            "are; None: the template's own", dtype=int, default=8, optional=True,
        check=lambda v: v >= 1)
    workers = pexConfig.Field(doc="FFT threads", dtype=int, default=RECOMMENDED.workers,
                              check=lambda v: v >= 1)
    uncertainty_draws = pexConfig.Field(
        doc="templates drawn from the calibration uncertainty stored in a calibrated template "
            "(bfdrift calibrate) to give flux_moved_err, the rms difference of "
            "their flux_moved from the template's own; each costs one more correction; 0: off", dtype=int, default=0,
        check=lambda v: v == 0 or v >= 2)
    uncertainty_seed = pexConfig.Field(doc="seed of the template draws", dtype=int, default=0)
    blocking_mask_planes = pexConfig.ListField(
        doc="mask planes whose pixels neither give nor receive charge (where the exposure "
            "declares them; other planes, e.g. DETECTED, never block)", dtype=str,
        default=list(BLOCKING_PLANES))
    masked_aggressors = pexConfig.ChoiceField(
        doc="charge of masked pixels as aggressors (they never exchange flux)", dtype=str,
        default="keep", optional=False,
        allowed={"keep": "their recorded value (a saturated core's charge is real); a masked "
                         "pixel beyond the model's range is interpolated all the same",
                 "interpolate": "the mean of the unmasked pixels in the 5 x 5 box around "
                                "them, as ip_isr interpolates defects before BF; recorded "
                                "values restored after"})
    on_input_warning = pexConfig.ChoiceField(
        doc="what an input that looks wrong (input_warnings: a bias pedestal, a mask over "
            "the sources, undeclared mask bits) gives", dtype=str, default="warn",
        optional=False,
        allowed={"warn": "logged, counted in BFWARN and returned as Struct.warnings; the "
                         "image is corrected (noiseless simulations look like a pedestal)",
                 "raise": "an InputError naming the warnings; nothing is returned"})
    bf_mask_plane = pexConfig.Field(
        doc="mask plane added to exposures with bit-plane masks for the pixels the correction "
            "flags (flags != 0: blocked, or within the template's reach of the border)",
        dtype=str, default="BF")


def stage_order(config=None):
    """The stages :meth:`BrighterFatterDriftTask.run` reports, in their order.

    ``('correct',)`` without ``compute_geometry``; ``('maps', 'correct')``
    with the exact maps (computed before the correction: their working
    arrays are freed before the solver's outputs exist); ``('correct',
    'maps')`` with the linear ones (computed after it, from its first pass).

    Parameters
    ----------
    config : BrighterFatterDriftConfig or dict, optional
        Default: the defaults.
    """
    defaults = BrighterFatterDriftConfig()
    if config is None:
        config = defaults
    get = config.get if isinstance(config, dict) else \
        (lambda key, default: getattr(config, key))
    if not get("compute_geometry", defaults.compute_geometry):
        return ("correct",)
    if get("geometry_method", defaults.geometry_method) == "linear":
        return ("correct", "maps")
    return ("maps", "correct")


class BrighterFatterDriftTask(Task):
    """Correct the brighter-fatter effect with an electrostatic template.

    ``run(exposure)`` predicts the final pixel boundaries from the recorded
    image with the template as Green's function, returns the pixel geometry
    maps and the flux-conserving correction.

    Examples
    --------
    A bright star (4e5 e) on a sky of 1000 e, in electrons. The correction
    moves the charge the star pushed into its neighbours back to its core,
    and conserves the flux:

    >>> import numpy as np
    >>> from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask
    >>> yy, xx = np.mgrid[:48, :48] - 24.0
    >>> img = 1000.0 + 4e5 / (2 * np.pi * 1.5**2) * np.exp(-0.5 * (xx**2 + yy**2) / 1.5**2)
    >>> res = BrighterFatterDriftTask().run(img)
    >>> bool(np.isclose(res.exposure.sum(), img.sum(), rtol=1e-12))
    True
    >>> bool(res.exposure[24, 24] > img[24, 24])
    True
    >>> res.area.shape, res.header["BFMETHOD"]
    ((48, 48), 'drift')

    The astier23 correction with the same template, without the maps:

    >>> config = BrighterFatterDriftConfig(method="astier23", compute_geometry=False)
    >>> res = BrighterFatterDriftTask(config=config).run(img)
    >>> res.area is None, bool(np.isclose(res.exposure.sum(), img.sum(), rtol=1e-12))
    (True, True)
    """

    ConfigClass = BrighterFatterDriftConfig
    _DefaultName = "brighterFatterDrift"

    def __init__(self, config=None, *, template=None, **kwargs):
        if config is not None and not isinstance(config, self.ConfigClass):
            raise InputTypeError(f"config must be a {self.ConfigClass.__name__}, got "
                                 f"{type(config).__name__}")
        super().__init__(config=config, **kwargs)
        self.config.validate()
        self.config.freeze()
        if template is None:
            template = load_default_template() if self.config.template is None else \
                load_templates(self.config.template)
        if isinstance(template, MultiBandTemplate) and template.single is not None:
            template = template.single
        if isinstance(template, MultiBandTemplate):
            #: One template per band (None: one template for every band).
            self.templates = template
            #: The template of the last run (of the config's band before any run).
            self.template = None
            if self.config.band is not None:
                self.template = template.select(self.config.band, where="config.band")
        elif isinstance(template, DistortionTemplate):
            self.templates = None
            self.template = template
        else:
            raise InputTypeError(f"template must be a DistortionTemplate or a "
                                 f"MultiBandTemplate, got {type(template).__name__}")
        if self.config.band is not None:
            band_key(self.config.band)  # an unknown band is refused here, not at run()
        self._caches, self._cache = {}, None

    def _operators(self, dtype, template=None):
        """Swept-area operators of ``template`` (default: the Task's), kept between runs."""
        template = self.template if template is None else template
        c = self._caches.get(id(template))
        if c is None or not c.matches(template, self.config.workers, dtype):
            if len(self._caches) >= 6:  # one per band at most
                self._caches.clear()
            c = self._caches[id(template)] = OperatorCache(template, workers=self.config.workers,
                                                           dtype=dtype)
        self._cache = c  # the last used
        return c

    def select_template(self, meta=None, *, band=None):
        """The template for an exposure and the band it was chosen for.

        Parameters
        ----------
        meta : mapping, optional
            The exposure's header (its :data:`BAND_KEYWORDS` are read).
        band : str, optional
            The band given by the caller (the PipelineTask's physical_filter).

        Returns
        -------
        template : DistortionTemplate
        band : str or None
            The band key (None with a single template for every band).
        source : str or None
            Where the band came from (``'BAND'``, ``'FILTER'``, ``'config'``,
            ``'caller'``).

        Raises
        ------
        InputError
            Multi-band template: no band (naming the keywords read), sources
            that disagree, or a band the template does not hold.
        """
        if self.templates is None:
            return self.template, None, None
        key, source = exposure_band(meta, band=band, config_band=self.config.band)
        if key is None:
            raise InputError(f"the exposure gives no band (read header keywords "
                             f"{', '.join(BAND_KEYWORDS)}; no config.band, no band from the "
                             f"caller), and the template holds several "
                             f"({', '.join(self.templates.bands)}): set config.band or the "
                             "exposure's BAND/FILTER keyword")
        return self.templates.select(key, where=source), key, source

    def run(self, exposure, *, band=None, progress=None):
        """Correct ``exposure``.

        Parameters
        ----------
        exposure : CCDData, NDData, numpy.ma.MaskedArray, ndarray or path
            Image in electrons (or ADU with ``config.gain`` / a GAIN keyword).
            Masked pixels (NDData and MaskedArray masks) neither give nor
            receive charge and are flagged. A FITS file's BUNIT must say
            electron or ADU (other units, e.g. e/s or MJy/sr, are refused).
            Never modified.
        band : str, optional
            The exposure's band from its context (the PipelineTask passes the
            Butler's physical_filter); with a multi-band template it must
            agree with the exposure's BAND/FILTER keyword and
            ``config.band`` when they are given (:meth:`select_template`).
        progress : callable, optional
            Called as ``progress(stage, fraction)`` while the run goes on:
            stages ``'correct'`` and, with ``compute_geometry``, ``'maps'``
            (the geometry maps), in the order they run (:func:`stage_order`:
            the exact maps before the correction, the linear ones after it,
            from its first pass), each with the fraction (0 to 1) of that
            stage done, never decreasing, from 0 to 1, e.g. a
            :class:`~lsst_bfdrift.utils.progress.StageProgress`. It does not
            change the result.

        Returns
        -------
        Struct
            ``exposure`` (corrected, same type as given; mask and uncertainty
            carried; a MaskedArray's mask gains the blocked pixels), ``area``,
            ``centroid_x``, ``centroid_y`` (shift from the pixel centre, px),
            ``e1``, ``e2`` (None if ``compute_geometry`` is off), ``flux_moved`` (e;
            sums to zero), ``flux_moved_err`` (e; its rms difference with
            templates drawn from the calibration uncertainty, None unless
            ``uncertainty_draws``), ``flags`` (uint8, bits FLAG_BLOCKED, FLAG_EDGE),
            ``iterations``, ``converged``, ``warnings`` (what looks wrong with the
            input: :func:`input_warnings`; also logged). With a multi-band
            template the result header's ``BFBAND`` records the band used.
        """
        cfg = self.config

        def report(stage, fraction):
            if progress is not None:
                progress(stage, fraction)

        image = to_electrons(exposure, gain=cfg.gain, saturation=cfg.saturation,
                             blocking=tuple(cfg.blocking_mask_planes), gain_name=_GAIN_NAME,
                             saturation_name=_SATURATION_NAME)
        template, band_used, band_source = self.select_template(image.meta, band=band)
        if band_used is not None:
            self.template = template
        data = image.data
        finite = np.isfinite(data)
        finite_data = data if finite.all() else np.where(finite, data, 0.0)
        del finite
        blocked = blocked_pixels(image)
        dtype = np.float32 if cfg.fft_precision == "float32" else np.float64
        ops = self._operators(dtype, template)
        # pixels masked as blocking (a hot pixel, a saturated core) never stop a run
        refuse_out_of_range(
            finite_data if image.mask is None or not image.mask.any()
            else np.where(image.mask, 0.0, finite_data), ops.kernel_abs_sum,
            f"; the image was converted with gain {image.gain} e/ADU" if image.gain != 1.0
            else "; is the image in ADU without a gain?")
        recorded = data  # not modified: masked_aggressors makes new arrays
        data, finite_data, fill = masked_aggressors(
            data, finite_data, image.mask, blocked, how=cfg.masked_aggressors,
            kernel_abs_sum=ops.kernel_abs_sum)
        # what looks wrong with the input, before the maps and the correction
        # allocate (peak memory: its temporaries are gone by then)
        warnings = input_warnings(finite_data if fill is None else
                                  np.where(fill, 0.0, finite_data), blocked) + image.warnings
        ns = cfg.geometry_samples
        samples = None if ns is None else min(ns, template.edge_samples)
        geom = dict(area=None, centroid_x=None, centroid_y=None, e1=None, e2=None)
        first = first_order_pass(template, finite_data, cfg, samples=samples, dtype=dtype,
                                 filled=data is not finite_data)
        # exact maps first: their working arrays are freed before the solver's
        # outputs exist (peak memory, docs/benchmarks.rst)
        if stage_order(cfg)[0] == "maps":
            geom = exact_maps(template, finite_data, cfg, samples=samples, dtype=dtype,
                              report=report)
        report("correct", 0.0)
        flux, iterations, converged, order, density, solver = apply_method(
            data, template, blocked, cfg, dtype, ops, maps=first,
            progress=lambda f: report("correct", f))
        report("correct", 1.0)
        if stage_order(cfg)[-1] == "maps":  # the linear maps, from the first pass
            geom = linear_maps(template, finite_data, cfg, samples=samples, dtype=dtype,
                               first=first, ops=ops, report=report)
        del first
        flux, moved, finite_data = flux_moved(flux, finite_data, blocked, fill, recorded)
        moved_err = None
        if cfg.uncertainty_draws:
            moved_err = flux_moved_error(template, data, finite_data, blocked, moved, cfg,
                                         dtype)
        flags = edge_flags(blocked, template.center)
        if not converged:
            self.log.warning("brighter-fatter correction did not converge in %d iterations",
                             iterations)
        if warnings and cfg.on_input_warning == "raise":
            raise InputError("input refused (on_input_warning='raise'): " + "; ".join(warnings))
        for w in warnings:
            self.log.warning("%s", w)
        header = result_header(image.meta, cfg, template, warnings=len(warnings),
                               order=order, density=density, iterations=iterations,
                               converged=converged, solver=solver,
                               filled=0 if fill is None else int(fill.sum()), gain=image.gain,
                               saturation=image.saturation)
        if band_used is not None:
            header["BFBAND"] = (band_used, f"band of the BF template (from {band_source})")
        if moved_err is not None:
            header["BFUNCN"] = (cfg.uncertainty_draws, "template draws of flux_moved_err")
        out = package_output(image, flux, blocked, flags, header, moved_err,
                             plane=cfg.bf_mask_plane)
        return Struct(exposure=out, warnings=warnings, flux_moved=moved, flux_moved_err=moved_err,
                      flags=flags, iterations=iterations, converged=bool(converged),
                      header=header, **geom)


def exposure_band(meta=None, *, band=None, config_band=None):
    """The band of an exposure: (band key, where it came from), or (None, None).

    Read from ``config_band``, ``band`` (the caller, e.g. the Butler's
    physical_filter) and the header keywords :data:`BAND_KEYWORDS` of
    ``meta``; LSST physical filters (``'r_57'``) give their band. A caller's
    or header value that names no band (``'unknown'``, ``'SDSSr~empty'``)
    is ignored when another source gives one.

    Raises
    ------
    InputError
        The sources name different bands (all are named), or the caller's or
        the config's band is unknown, or the only band values name no band.
    """
    found, unknown = [], []
    if config_band is not None:
        found.append((band_key(config_band), "config"))
    get = (lambda k: None) if meta is None else meta.get
    for key in ("caller",) + BAND_KEYWORDS:
        value = band if key == "caller" else get(key)
        if value is None or (isinstance(value, str) and not value.strip()):
            continue
        try:
            found.append((band_key(value if isinstance(value, str) else str(value)), key))
        except InputError:
            unknown.append(f"{key}={value!r}")  # e.g. a physical filter 'unknown' 
    if len({k for k, _ in found}) > 1:
        raise InputError("the exposure's band is ambiguous: " + ", ".join(
            f"{s} says {k!r}" for k, s in found) + "; they must agree")
    if found:
        return found[0]
    if unknown:
        raise InputError(f"the exposure's band value(s) {', '.join(unknown)} name no LSST "
                         f"band (u, g, r, i, z, y, or a physical filter such as 'r_57'); set "
                         "config.band")
    return None, None
