"""A small Config/Task layer after lsst.pex.config and lsst.pipe.base.

Names and meaning follow the LSST packages (``Field`` with ``doc``,
``default`` and ``check``; ``ChoiceField``; ``ConfigurableField``;
``Config.validate()`` and ``Config.freeze()``; ``Task`` with ``ConfigClass``
and ``_DefaultName`` whose ``run()`` returns a ``Struct``), written small and
in-house so that the package does not depend on the LSST stack. Method names
are snake_case (``set_defaults``, ``to_dict``, ``make_subtask``).

Example
-------
>>> class MyConfig(Config):
...     n_iter = Field("number of iterations", int, default=3, check=lambda v: v > 0)
...     method = ChoiceField("method", str, default="a", allowed={"a": "first", "b": "second"})
>>> c = MyConfig(n_iter=5)
>>> c.validate(); c.freeze()
"""

import json
import logging
import math

from lsst_bfdrift.utils.io import atomic_output
from lsst_bfdrift.utils.errors import (FieldValidationError, InputAttributeError, InputError,
                                       InputTypeError)

__all__ = ["FieldValidationError", "Field", "ChoiceField", "ConfigurableField", "Config",
           "Struct", "Task"]


class _Descriptor:
    """Storage plumbing shared by fields: values live in the config's
    ``_storage``; setting a frozen config raises."""

    name = None

    def __set_name__(self, owner, name):
        self.name = name

    def __get__(self, instance, owner):
        if instance is None:
            return self
        return instance._storage[self.name]

    def __set__(self, instance, value):
        if instance._frozen:
            raise FieldValidationError(f"cannot set {self.name!r}: the config is frozen")
        instance._storage[self.name] = self._convert(value)


class Field(_Descriptor):
    """A typed configuration value.

    Parameters
    ----------
    doc : str
        What the field means (with units).
    dtype : type
        ``int``, ``float``, ``bool`` or ``str`` (ints are accepted for floats).
    default : optional
        Default value (``None`` only with ``optional=True``).
    check : callable, optional
        ``check(value) -> bool``; False makes :meth:`Config.validate` fail.
    optional : bool, optional
        Whether ``None`` is allowed.
    """

    def __init__(self, doc, dtype, default=None, check=None, optional=False):
        if dtype not in (int, float, bool, str):
            raise InputTypeError(f"unsupported field dtype {dtype!r}")
        if not doc:
            raise InputError("every field needs a doc string")
        self.doc, self.dtype, self.check, self.optional = doc, dtype, check, bool(optional)
        self.default = None if default is None else self._convert(default)

    def _convert(self, value):
        if value is None:
            if not self.optional:
                raise FieldValidationError(f"field {self.name!r} may not be None")
            return None
        if self.dtype is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise FieldValidationError(
                    f"field {self.name!r} takes a float, got {type(value).__name__} {value!r}")
            value = float(value)
            if not math.isfinite(value):
                raise FieldValidationError(f"field {self.name!r} must be finite, got {value!r}")
            return value
        if self.dtype is int and (isinstance(value, bool) or not isinstance(value, int)):
            raise FieldValidationError(
                f"field {self.name!r} takes an int, got {type(value).__name__} {value!r}")
        if not isinstance(value, self.dtype):
            raise FieldValidationError(f"field {self.name!r} takes a {self.dtype.__name__}, "
                                       f"got {type(value).__name__} {value!r}")
        return value

    def validate(self, instance):
        """Raise :class:`FieldValidationError` if the current value fails."""
        value = instance._storage[self.name]
        if value is None and not self.optional:
            raise FieldValidationError(f"field {self.name!r} is required")
        if value is not None and self.check is not None and not self.check(value):
            raise FieldValidationError(f"field {self.name!r} = {value!r} fails its check "
                                       f"({self.doc})")


class ChoiceField(Field):
    """A field whose value must be one of ``allowed`` (a dict value -> doc)."""

    def __init__(self, doc, dtype, default=None, allowed=None, optional=False):
        if not allowed:
            raise InputError("ChoiceField needs a non-empty 'allowed' mapping")
        self.allowed = dict(allowed)
        super().__init__(doc, dtype, default=default, optional=optional)

    def _convert(self, value):
        value = super()._convert(value)
        if value is not None and value not in self.allowed:
            raise FieldValidationError(f"field {self.name!r} = {value!r} is not one of "
                                       f"{sorted(self.allowed)}")
        return value


class ConfigurableField(_Descriptor):
    """A sub-config that configures a subtask (``target`` with its ConfigClass)."""

    def __init__(self, doc, target, ConfigClass=None):  # noqa: N803 (LSST name)
        self.doc, self.target = doc, target
        self.ConfigClass = ConfigClass or target.ConfigClass

    def _convert(self, value):
        if isinstance(value, dict):
            sub = self.ConfigClass()
            sub.update(**value)
            value = sub
        if not isinstance(value, self.ConfigClass):
            raise FieldValidationError(f"field {self.name!r} takes a "
                                       f"{self.ConfigClass.__name__} or a dict")
        return value

    def validate(self, instance):
        instance._storage[self.name].validate()


class Config:
    """Base class of configurations: declare fields as class attributes."""

    def __init__(self, **kwargs):
        object.__setattr__(self, "_frozen", False)
        object.__setattr__(self, "_storage", {})
        for name, f in self._fields().items():
            if isinstance(f, ConfigurableField):
                self._storage[name] = f.ConfigClass()
            else:
                self._storage[name] = f.default
        self.set_defaults()
        self.update(**kwargs)

    @classmethod
    def _fields(cls):
        out = {}
        for klass in reversed(cls.__mro__):
            for name, value in vars(klass).items():
                if isinstance(value, (Field, ConfigurableField)):
                    out[name] = value
        return out

    def set_defaults(self):
        """Hook for subclasses to change defaults (called by ``__init__``)."""

    def __setattr__(self, name, value):
        if name not in self._fields():
            raise InputAttributeError(f"{type(self).__name__} has no field {name!r}; fields: "
                                 f"{', '.join(sorted(self._fields()))}")
        object.__setattr__(self, name, value)

    def update(self, **kwargs):
        """Set several fields; unknown names raise ``AttributeError``."""
        for k, v in kwargs.items():
            if isinstance(self._fields().get(k), ConfigurableField) and isinstance(v, dict):
                getattr(self, k).update(**v)
            else:
                setattr(self, k, v)

    def validate(self):
        """Check every field (and sub-config); raise FieldValidationError."""
        for f in self._fields().values():
            f.validate(self)

    def freeze(self):
        """Make this config (and its sub-configs) read-only."""
        for name, f in self._fields().items():
            if isinstance(f, ConfigurableField):
                self._storage[name].freeze()
        object.__setattr__(self, "_frozen", True)

    @property
    def frozen(self):
        """Whether :meth:`freeze` was called."""
        return self._frozen

    def to_dict(self):
        """Plain nested dictionary of the values."""
        out = {}
        for name, f in self._fields().items():
            v = self._storage[name]
            out[name] = v.to_dict() if isinstance(f, ConfigurableField) else v
        return out

    @classmethod
    def from_dict(cls, mapping):
        """Config from a (nested) mapping; unknown keys raise AttributeError."""
        return cls(**dict(mapping))

    def save(self, path):
        """Write the values as JSON (atomically)."""
        with atomic_output(path) as tmp, open(tmp, "w") as fh:
            json.dump(self.to_dict(), fh, indent=2, sort_keys=True)

    @classmethod
    def load(cls, path):
        """Read a JSON or TOML file written by :meth:`save` or by hand."""
        import tomllib

        with open(path, "rb") as fh:
            raw = fh.read()
        toml = str(path).endswith(".toml")
        try:
            data = tomllib.loads(raw.decode()) if toml else json.loads(raw.decode())
        except (UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
            kind = "TOML" if toml else "JSON (name the file *.toml for TOML)"
            raise InputError(f"{path}: not valid {kind}: {exc}") from None
        if not isinstance(data, dict):
            raise InputError(f"{path}: expected a table of field names and values, "
                             f"got {type(data).__name__}")
        return cls.from_dict(data)

    def doc(self):
        """Field names with their docs and current values."""
        return {name: (f.doc, self.to_dict()[name]) for name, f in self._fields().items()}

    def __eq__(self, other):
        return type(self) is type(other) and self.to_dict() == other.to_dict()

    def __repr__(self):
        return f"{type(self).__name__}({self.to_dict()!r})"


class Struct:
    """Attribute container returned by ``Task.run`` (like lsst.pipe.base.Struct)."""

    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)

    def get_dict(self):
        """The attributes as a dict."""
        return dict(self.__dict__)

    def __repr__(self):
        return f"Struct({', '.join(sorted(self.__dict__))})"


class Task:
    """Base class of tasks: a validated, frozen config and a logger.

    Subclasses set ``ConfigClass`` and ``_DefaultName`` and implement ``run``.
    """

    ConfigClass = Config
    _DefaultName = "task"

    def __init__(self, config=None, *, name=None, parent=None):
        if config is None:
            config = self.ConfigClass()
        if not isinstance(config, self.ConfigClass):
            raise InputTypeError(f"config must be a {self.ConfigClass.__name__}, "
                            f"got {type(config).__name__}")
        config.validate()
        config.freeze()
        self.config = config
        self.name = name or self._DefaultName
        self.full_name = self.name if parent is None else f"{parent.full_name}.{self.name}"
        self.log = logging.getLogger(f"lsst_bfdrift.{self.full_name}")

    def make_subtask(self, name):
        """Build the subtask configured by ConfigurableField ``name``."""
        field = type(self.config)._fields().get(name)
        if not isinstance(field, ConfigurableField):
            raise InputAttributeError(f"{type(self.config).__name__} has no configurable field "
                                 f"{name!r}")
        sub = field.target(config=getattr(self.config, name), name=name, parent=self)
        setattr(self, name, sub)
        return sub

    def run(self, *args, **kwargs):  # pragma: no cover - abstract
        """Do the work and return a :class:`Struct`."""
        raise NotImplementedError
