"""The template build configuration as an ``lsst.pex.config`` Config.

:class:`TemplateBuildConfig` has two sub-configs, ``sensor`` (the fields of
:class:`~lsst_bfdrift.physics.sensor.SensorParameters`) and ``template`` (those
of :class:`~lsst_bfdrift.templates.template.TemplateSettings`). Their fields are
made from the dataclasses themselves (name, type, default and the doc of the
class's numpydoc ``Parameters`` section), so there is one definition of each
parameter; the dataclasses keep doing the physical checks, which
``validate()`` runs. A build config file is a pex_config override file::

    # my_sensor.py
    config.sensor.v_bss = -60.0
    config.sensor.column_overrides = [100, 2.0]   # flat: boundary, delta_xi, ...
    config.template.edge_samples = 16

The JSON/TOML files with ``sensor`` and ``template`` tables that earlier
releases used are still read (:func:`read_build_config`).
"""

import dataclasses
import json
import os
import re
import tomllib

import lsst.pex.config as pexConfig

from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.template import TemplateSettings
from lsst_bfdrift.utils.config import load_config
from lsst_bfdrift.utils.errors import InputError, InputFileError, InputKeyError

__all__ = ["SensorConfig", "TemplateSettingsConfig", "TemplateBuildConfig",
           "read_build_config"]

#: Width of the tuples of the list-valued sensor parameters (stored flat).
_TUPLE_WIDTH = {"column_overrides": 2, "row_overrides": 2, "row_shifts": 2, "truncations": 4}


def _parameter_docs(cls):
    """name -> description from the numpydoc Parameters section of ``cls``."""
    doc = cls.__doc__ or ""
    section = doc.split("Parameters\n", 1)[-1]
    docs, names, lines = {}, [], []
    for line in section.splitlines()[1:]:
        m = re.match(r"^    (\w[\w, ]*) : ", line)
        if m:
            for n in names:
                docs[n] = " ".join(lines)
            names, lines = [s.strip() for s in m.group(1).split(",")], []
        elif line.startswith("        "):
            lines.append(line.strip())
        elif line.strip() and not line.startswith(" "):
            break
    for n in names:
        docs[n] = " ".join(lines)
    return docs


def _fields_of(cls):
    """pex_config fields mirroring the dataclass ``cls`` (name -> Field)."""
    docs = _parameter_docs(cls)
    out = {}
    for f in dataclasses.fields(cls):
        doc = docs.get(f.name) or f.name
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if f.name in _TUPLE_WIDTH:
            doc += (f" Flat list: each entry is {_TUPLE_WIDTH[f.name]} numbers in a row.")
            out[f.name] = pexConfig.ListField(doc=doc, dtype=float, default=[], optional=True)
            continue
        dtype = {"float": float, "int": int, "bool": bool, "str": str}[
            f.type if isinstance(f.type, str) else f.type.__name__]
        out[f.name] = pexConfig.Field(doc=doc, dtype=dtype, default=default,
                                      optional=default is None)
    return out


class _DataclassConfig(pexConfig.Config):
    """A Config whose fields mirror a dataclass; ``build()`` makes the dataclass."""

    _target = None

    def build(self):
        """The dataclass with these values (its own checks run; InputError if they fail)."""
        values = {}
        for name in self._fields:
            v = getattr(self, name)
            width = _TUPLE_WIDTH.get(name)
            if width is not None:
                v = list(v or [])
                if len(v) % width:
                    raise InputError(f"{name} needs groups of {width} numbers, got {len(v)}")
                v = [tuple(v[k:k + width]) for k in range(0, len(v), width)]
            values[name] = v
        return self._target(**values)

    def validate(self):
        super().validate()
        try:
            self.build()
        except (InputError, ValueError, TypeError) as exc:
            name = next((n for n in self._fields if f"'{n}'" in str(exc) or
                         str(exc).startswith(n)), next(iter(self._fields)))
            raise pexConfig.FieldValidationError(self._fields[name], self,
                                                 f"{type(self).__name__}: {exc}") from exc

    @classmethod
    def from_object(cls, obj):
        """A config holding the values of dataclass instance ``obj``."""
        cfg = cls()
        for name in cfg._fields:
            v = getattr(obj, name)
            if name in _TUPLE_WIDTH:
                v = [float(x) for item in v for x in item]
            setattr(cfg, name, v)
        return cfg


SensorConfig = type("SensorConfig", (_DataclassConfig,),
                    {"__doc__": "Sensor parameters (SensorParameters) as a pex_config Config.",
                     "__module__": __name__, "_target": SensorParameters,
                     **_fields_of(SensorParameters)})
TemplateSettingsConfig = type(
    "TemplateSettingsConfig", (_DataclassConfig,),
    {"__doc__": "How a template is computed (TemplateSettings) as a pex_config Config.",
     "__module__": __name__, "_target": TemplateSettings, **_fields_of(TemplateSettings)})


class TemplateBuildConfig(pexConfig.Config):
    """Configuration of ``bfdrift template build``: a sensor and the template settings."""

    sensor = pexConfig.ConfigField(doc="the sensor model (SensorParameters)", dtype=SensorConfig)
    template = pexConfig.ConfigField(doc="how the template is computed (TemplateSettings)",
                                     dtype=TemplateSettingsConfig)
    provenance = pexConfig.DictField(doc="free-form notes (e.g. how the values were obtained)",
                                     keytype=str, itemtype=str, default={}, optional=True)

    def parameters(self):
        """(SensorParameters, TemplateSettings) of this config."""
        return self.sensor.build(), self.template.build()


def read_build_config(path):
    """Read a build configuration file.

    Parameters
    ----------
    path : str, path-like or None
        A pex_config override file of :class:`TemplateBuildConfig`, or a JSON
        (TOML if the name ends in ``.toml``) file with ``sensor`` and
        ``template`` tables (and a free-form ``provenance``). None: defaults.

    Returns
    -------
    params : SensorParameters
    settings : TemplateSettings
    """
    if path is None:
        return SensorParameters(), TemplateSettings()
    path = os.fspath(path)
    if not path.endswith((".json", ".toml")):
        return load_config(TemplateBuildConfig, path).parameters()
    with open(path, "rb") as fh:
        raw = fh.read()
    try:
        if path.endswith(".toml"):
            data = tomllib.loads(raw.decode())
        else:
            data = json.loads(raw.decode())
    except Exception as exc:
        raise InputFileError(f"{path}: cannot parse configuration ({exc})", path) from exc
    if not isinstance(data, dict):
        raise InputFileError(f"{path}: configuration must be a table/object", path)
    unknown = sorted(set(data) - {"sensor", "template", "provenance"})
    if unknown:
        raise InputKeyError(f"{path}: unknown configuration section(s) {unknown}; "
                            "expected 'sensor' and/or 'template' (and 'provenance')")
    return (SensorParameters.from_dict(data.get("sensor", {})),
            TemplateSettings.from_dict(data.get("template", {})))
