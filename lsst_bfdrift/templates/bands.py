"""Templates per band: conversions at the depths a band's photons reach.

A drift line starts where its photon converts (:mod:`lsst_bfdrift.physics.depth`):
blue photons at the entrance window, red ones all through the silicon. A
template's boundary displacements are linear in the weights of the
conversion heights, so :func:`build_band_templates` builds templates at one
shared grid of heights (:func:`~lsst_bfdrift.physics.depth.conversion_nodes`)
and gives each band (or wavelength) the weighted mean of them: all six bands
cost as many template builds as the grid has heights above the wells (7 by
default), not six times that.

Two depth responses (``depth_response``):

``'drift'`` (the physics)
    Drift lines start at the conversion height: the band's template is
    ``sum_k w_k T(z_k)``, the photon-weighted mean over the depth
    distribution.
``'galsim'`` (GalSim's rule)
    galsim.SiliconSensor scales its sensor file's displacements by
    ``tanh(zconv / 12 um)`` for each photon
    (:func:`~lsst_bfdrift.physics.depth.galsim_depth_factor`); the band's
    template is the entrance-window template (or ``base``, e.g. a GalSim
    sensor file read by
    :func:`~lsst_bfdrift.templates.galsim_io.import_galsim_sensor`) times the
    band's mean of that factor. For correcting GalSim-simulated images.

:class:`MultiBandTemplate` holds one template per band and reads and writes
them in one FITS file (a ``TEMPLATE_<BAND>`` table per band, each with its
schema version, SHA-256 and FITS checksums; the primary header lists the
bands in ``BFBANDS``). :func:`load_templates` reads that file or a
single-band one (which then serves every band).
"""

import dataclasses
from collections.abc import Mapping

import numpy as np
from astropy.io import fits

from lsst_bfdrift.physics.absorption import TABLE_TEMPERATURE, check_temperature
from lsst_bfdrift.physics.depth import (BANDS, GALSIM_ZFIT, conversion_nodes,
                                        depth_distribution, galsim_depth_factor)
from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import (TEMPLATE_SCHEMA_VERSION, DistortionTemplate,
                                             TemplateSettings, _set_meta, build_template)
from lsst_bfdrift.templates.template_io import (band_key, read_template_fits,
                                                template_file_bands)
from lsst_bfdrift.utils.errors import InputError, InputTypeError, TemplateFileError
from lsst_bfdrift.utils.io import atomic_output, check_output
from lsst_bfdrift.utils.progress import ProgressBar

__all__ = ["DEPTH_RESPONSES", "MULTIBAND_LAYOUT_VERSION", "MultiBandTemplate",
           "build_band_templates", "band_weights", "combine_templates", "load_templates"]

#: The depth responses of :func:`build_band_templates`.
DEPTH_RESPONSES = {
    "drift": "drift lines start at the conversion height (the physics; real sensors)",
    "galsim": "the entrance-window template scaled by GalSim's mean tanh(zconv / 12 um) "
              "(to correct galsim.SiliconSensor images)",
}

#: Version of the multi-band file layout (primary BFBANDS, one TEMPLATE_<BAND> per band).
MULTIBAND_LAYOUT_VERSION = 1


def _source(key):
    """The depth_distribution source of a band key (band letter or wavelength)."""
    return float(key[:-2]) if key.endswith("nm") else key


def combine_templates(templates, weights, *, meta=None):
    """Weighted sum of templates (same size, edge samples and charge).

    ``None`` in ``templates`` is a template of zero displacement.
    """
    pairs = [(t, float(w)) for t, w in zip(templates, weights) if t is not None]
    if not pairs:
        raise InputError("combine_templates needs at least one template")
    t0 = pairs[0][0]
    for t, _ in pairs[1:]:
        if t.size != t0.size or t.edge_samples != t0.edge_samples or \
                not np.allclose(t.fractions, t0.fractions) or not np.isclose(t.charge, t0.charge):
            raise InputError("templates to combine differ in size, edge samples or charge")
    out = {}
    for name in ("corner_d", "vedge_d", "hedge_d", "vedge_t", "hedge_t"):
        arrays = [(getattr(t, name), w) for t, w in pairs]
        if all(a is None for a, _ in arrays):
            out[name] = None
            continue
        out[name] = sum(w * (np.zeros_like(getattr(t0, name.replace("_t", "_d"))) if a is None
                             else a) for a, w in arrays)
    return DistortionTemplate(out["corner_d"], out["vedge_d"], out["hedge_d"], t0.fractions,
                              t0.charge, vedge_t=out["vedge_t"], hedge_t=out["hedge_t"],
                              meta=dict(t0.meta if meta is None else meta))


def band_weights(bands=BANDS, *, thickness=100.0, z_stop=0.5, sed=None, nodes=8,
                 temperature=None):
    """Conversion-height grid and each band's weights on it.

    Parameters
    ----------
    bands : sequence of str or float
        Band names or wavelengths (nm).
    thickness, z_stop : float, optional
        Silicon thickness and collection height (um).
    sed : optional
        Source spectrum (:func:`~lsst_bfdrift.physics.depth.sed_photons`).
    nodes : int or array_like, optional
        Number of heights of :func:`~lsst_bfdrift.physics.depth.conversion_nodes`,
        or the heights themselves (um, increasing, last = thickness).
    temperature : float, optional
        Temperature of the silicon (K) for the absorption lengths; None:
        300 K, the table's (:func:`~lsst_bfdrift.physics.absorption.absorption_length`).

    Returns
    -------
    z : ndarray
        Heights (um).
    weights : dict
        band key -> weights (sum 1) of the heights.
    distributions : dict
        band key -> :class:`~lsst_bfdrift.physics.depth.DepthDistribution`.
    """
    z = (conversion_nodes(thickness, z_stop, nodes) if np.ndim(nodes) == 0
         else np.asarray(nodes, float))
    keys = [band_key(b) for b in bands]
    if not keys or len(set(keys)) != len(keys):
        raise InputError(f"bands must be given once each, got {list(bands)}")
    dists = {k: depth_distribution(_source(k), thickness, sed=sed, temperature=temperature)
             for k in keys}
    return z, {k: d.node_weights(z) for k, d in dists.items()}, dists


def build_band_templates(params=None, bands=BANDS, *, sed=None, settings=None,
                         depth_response="drift", nodes=8, base=None, temperature=None,
                         progress=False):
    """Templates for bands (or wavelengths) of one sensor, on one shared grid of heights.

    Parameters
    ----------
    params : SensorParameters, optional
        The sensor (default: the package defaults).
    bands : sequence of str or float, optional
        LSST bands and/or wavelengths (nm); default all six bands.
    sed : optional
        Spectrum of the light (:func:`~lsst_bfdrift.physics.depth.sed_photons`):
        None/'flat' (flat in photons per nm, e.g. a flat field's lamp seen
        through the band), a temperature in K, or a GalSim SED name.
    settings : TemplateSettings, optional
        Settings of each build (``conversion_height`` must be None: the
        heights are the grid's).
    depth_response : {'drift', 'galsim'}, optional
        See the module docstring.
    nodes : int or array_like, optional
        The shared grid of heights (``'drift'`` only; :func:`band_weights`);
        8 heights: 7 builds (the lowest, the collection height, needs none).
        Heights without weight in any band are not built (the u band alone
        needs two).
    base : DistortionTemplate, optional
        ``'galsim'`` only: the entrance-window template to scale (default:
        built from ``params`` and ``settings``).
    temperature : float, optional
        Temperature of the silicon (K) where the photons convert; None: 300
        K, the absorption table's and galsim.SiliconSensor's. An LSST sensor
        runs at about 173 K, where z and y photons convert deeper
        (:func:`~lsst_bfdrift.physics.absorption.absorption_length`).
    progress : bool or callable, optional
        True: a bar on stderr; a callable gets the fraction done (0 to 1).

    Returns
    -------
    MultiBandTemplate
        One template per band; each template's ``meta['depth']`` records the
        response, the heights and their weights, the mean conversion height
        and the fraction of photons converted.
    """
    params = SensorParameters() if params is None else params
    settings = TemplateSettings() if settings is None else settings
    if not isinstance(params, SensorParameters):
        raise InputTypeError(f"params must be SensorParameters, got {type(params).__name__}")
    if not isinstance(settings, TemplateSettings):
        raise InputTypeError(f"settings must be TemplateSettings, got "
                             f"{type(settings).__name__}")
    if depth_response not in DEPTH_RESPONSES:
        raise InputError(f"depth_response must be one of {sorted(DEPTH_RESPONSES)}, got "
                         f"{depth_response!r}")
    if settings.conversion_height is not None:
        raise InputError("settings.conversion_height must be None for band templates (the "
                         f"heights follow the band), got {settings.conversion_height}")
    if base is not None and depth_response != "galsim":
        raise InputError("base is the template GalSim's rule scales: depth_response='galsim' "
                         "only")
    kelvin = TABLE_TEMPERATURE if temperature is None else check_temperature(temperature)
    z, weights, dists = band_weights(bands, thickness=params.thickness,
                                     z_stop=params.z_collect, sed=sed, nodes=nodes,
                                     temperature=temperature)
    if depth_response == "galsim":
        z = np.array([params.thickness])
        needed = [] if base is not None else [0]
    else:
        if z[0] != params.z_collect or not np.isclose(z[-1], params.thickness):
            raise InputError(f"conversion nodes must run from the collection height "
                             f"{params.z_collect} um to the thickness {params.thickness} um")
        total = np.sum(list(weights.values()), axis=0)
        needed = [k for k in range(1, z.size) if total[k] > 1e-12]
    built = {}
    with _fraction_reporter(progress, "band templates") as report:
        for n, k in enumerate(needed):
            s = dataclasses.replace(settings, conversion_height=float(z[k]))
            built[k] = build_template(params, s, progress=lambda f, n=n: report(
                (n + f) / len(needed)))
    out = {}
    for key, w in weights.items():
        d = dists[key]
        info = {"response": depth_response, "band": key, "sed": _sed_label(sed),
                "mean_height": d.mean_height, "converted_fraction": d.converted_fraction,
                "thickness": params.thickness, "z_stop": params.z_collect,
                "absorption_table": "GalSim share/sensors/abs_length.dat (Green 2008, 300 K)"
                + ("" if temperature is None else ", scaled to the temperature by Rajkanan, "
                   "Singh & Shewchun 1979"),
                "temperature": kelvin}
        if depth_response == "galsim":
            factor = galsim_depth_factor(d)
            tpl = base if base is not None else built[0]
            info.update(zfit=GALSIM_ZFIT, factor=factor)
            meta = dict(tpl.meta, depth=info)
            out[key] = combine_templates([tpl], [factor], meta=meta)
        else:
            info.update(nodes=z.tolist(), weights=w.tolist())
            meta = {"source": "lsst_bfdrift.build_band_templates", "params": params.to_dict(),
                    "settings": settings.to_dict(), "depth": info}
            temps = [built.get(k) for k in range(z.size)]
            out[key] = combine_templates(temps, w, meta=meta)
    return MultiBandTemplate(out, meta={"depth_response": depth_response,
                                        "sed": _sed_label(sed),
                                        "temperature": kelvin})


class _fraction_reporter:
    """``with _fraction_reporter(progress, label) as report: report(fraction)``.

    ``progress``: False (silent), True (a bar on stderr) or a callable that
    gets the fraction (0 to 1, never decreasing).
    """

    _STEPS = 1000

    def __init__(self, progress, label):
        self.call = progress if callable(progress) else None
        self.bar = None if self.call else ProgressBar(self._STEPS, label,
                                                      enabled=bool(progress))
        self.last = 0.0

    def __call__(self, fraction):
        f = min(max(float(fraction), self.last), 1.0)
        self.last = f
        if self.call is not None:
            self.call(f)
        else:
            self.bar(int(round(f * self._STEPS)) - self.bar.done)

    def __enter__(self):
        self(0.0)
        if self.bar is not None:
            self.bar.show()
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            self(1.0)
        if self.bar is not None:
            self.bar.__exit__(*exc)
        return False


def _sed_label(sed):
    if sed is None:
        return "flat"
    return sed if isinstance(sed, (str, int, float)) else type(sed).__name__


class MultiBandTemplate(Mapping):
    """Templates of one sensor for several bands (a mapping band -> DistortionTemplate).

    Parameters
    ----------
    templates : dict
        band key (:func:`~lsst_bfdrift.templates.template_io.band_key`) ->
        :class:`DistortionTemplate`.
    meta : dict, optional
        What the bands share (the calibration, the depth response).
    single : DistortionTemplate, optional
        Instead of ``templates``: one template for every band (a single-band
        file, as :func:`load_templates` reads it); ``bands`` is then empty.
    """

    def __init__(self, templates=None, *, meta=None, single=None):
        if single is not None and templates:
            raise InputError("give either templates per band or one single template")
        if single is None and not templates:
            raise InputError("a MultiBandTemplate needs at least one band")
        self.single = single
        self._t = {}
        for k, t in (templates or {}).items():
            if not isinstance(t, DistortionTemplate):
                raise InputTypeError(f"template of band {k!r} is a {type(t).__name__}, not a "
                                     "DistortionTemplate")
            self._t[band_key(k)] = t
        self.meta = dict(meta or {})

    def __getitem__(self, band):
        return self._t[band_key(band)]

    def __iter__(self):
        return iter(self._t)

    def __len__(self):
        return len(self._t)

    @property
    def bands(self):
        """Band keys held, in order (empty for a single template)."""
        return tuple(self._t)

    def select(self, band, *, where="the exposure"):
        """The template for ``band``: the single one for any band, else that band's.

        Raises InputError for an unknown band or one without a template,
        naming the bands held and ``where`` the band came from.
        """
        if self.single is not None:
            return self.single
        if band is None:
            raise InputError(f"{where} gives no band, and the template holds several "
                             f"({', '.join(self.bands)}): say the band")
        key = band_key(band)
        if key not in self._t:
            raise InputError(f"no template for band {key!r} (from {where}); the template holds "
                             f"bands {', '.join(self.bands)}")
        return self._t[key]

    def save(self, path, *, overwrite=False):
        """Write all bands to one FITS file, atomically (a single template: its own layout).

        Primary header: ``BFBANDS`` (comma-separated band keys),
        ``BFMBVER`` (:data:`MULTIBAND_LAYOUT_VERSION`), ``BFSCHEMA`` and the
        shared metadata ``BFMETA``. Per band ``<B>`` (upper case): the
        ``TEMPLATE_<B>`` table of :meth:`DistortionTemplate.to_hdus` with its
        own ``BFMETA``, ``BFBAND``, SHA-256 and, like every HDU, FITS
        checksums.
        """
        if self.single is not None:
            return self.single.save(path, overwrite=overwrite)
        check_output(path, overwrite=overwrite)
        primary = fits.PrimaryHDU()
        primary.header["ORIGIN"] = "lsst_bfdrift"
        primary.header["BFSCHEMA"] = TEMPLATE_SCHEMA_VERSION
        primary.header["BFMBVER"] = (MULTIBAND_LAYOUT_VERSION, "lsst_bfdrift multi-band layout")
        primary.header["BFBANDS"] = (",".join(self.bands), "bands with a template")
        _set_meta(primary.header, self.meta)
        hdus = [primary]
        for k, t in self._t.items():
            ext = t.to_hdus(suffix="_" + k.upper(), meta_here=True)
            ext[0].header["BFBAND"] = (k, "band of this template")
            hdus += ext
        with atomic_output(path) as tmp:
            fits.HDUList(hdus).writeto(tmp, overwrite=True, checksum=True)

    @classmethod
    def load(cls, path):
        """Read a multi-band file, or a single-band one (then ``single`` serves every band)."""
        import json

        path, hdus = read_template_fits(path)
        bands = template_file_bands(path, hdus)
        if not bands:
            return cls(single=DistortionTemplate._from_hdus(path, hdus), meta={"path": path})
        version = hdus["PRIMARY"][0].get("BFMBVER")
        if version != MULTIBAND_LAYOUT_VERSION:
            raise TemplateFileError(f"{path}: multi-band layout version {version!r}; this "
                                    f"lsst_bfdrift reads {MULTIBAND_LAYOUT_VERSION}", path)
        templates = {}
        for b in bands:
            templates[b] = DistortionTemplate._from_hdus(path, hdus, suffix="_" + b.upper())
            if hdus["TEMPLATE_" + b.upper()][0].get("BFBAND") != b:
                raise TemplateFileError(f"{path}: extension TEMPLATE_{b.upper()} is not marked "
                                        f"as band {b!r} (BFBAND)", path)
        try:
            meta = json.loads(hdus["PRIMARY"][0].get("BFMETA", "{}"))
        except ValueError as exc:
            raise TemplateFileError(f"{path}: BFMETA is not JSON ({exc})", path) from exc
        return cls(templates, meta=dict(meta, path=path))

    def summary(self):
        """Per band: A00, A01, A10 and the depth statistics (dict of dicts)."""
        items = {"any": self.single} if self.single is not None else self._t
        out = {}
        for k, t in items.items():
            s = t.summary()
            d = t.meta.get("depth", {})
            out[k] = {"A00": s["A00"], "A01": s["A01"], "A10": s["A10"], "A11": s["A11"],
                      "mean_height": d.get("mean_height"),
                      "converted_fraction": d.get("converted_fraction")}
        return out

    def __repr__(self):
        if self.single is not None:
            return "MultiBandTemplate(single template for every band)"
        return f"MultiBandTemplate(bands={', '.join(self.bands)})"


def load_templates(path):
    """Read a template file: a :class:`MultiBandTemplate` (single-band files serve every band)."""
    return MultiBandTemplate.load(path)
