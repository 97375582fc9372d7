"""Configs with ``lsst.pex.config``; ``Task`` and ``Struct`` from ``lsst.pipe.base``.

Configs are :class:`lsst.pex.config.Config` classes (``Field``,
``ChoiceField``, ``ListField``, ``validate()``, ``freeze()``, ``toDict()``),
so a config file is a pex_config override file, as LSST users write them::

    # bf.py
    config.method = "astier23"
    config.order = 4

:func:`load_config` reads such a file, and also the JSON and TOML tables of
field names and values that earlier releases of this package used.

``Task`` and ``Struct`` are :class:`lsst.pipe.base.Task` and
:class:`lsst.pipe.base.Struct` when ``lsst-pipe-base`` is installed (the
``[lsst]`` extra). The core package does not depend on it: pipe_base pulls in
daf_butler, SQLAlchemy and pydantic and doubles the import time of the package
(0.7 s to 1.3 s on the 2-core reference machine, ``python -c "import
lsst_bfdrift"``), which every ``bfdrift`` command would pay. Without it, a
fallback of the same names does what the package's tasks use: the
constructor signature ``(config=None, *, name=None, parentTask=None,
log=None)``, ``config``, ``log``, ``makeSubtask`` and ``Struct.getDict``.
:data:`HAVE_PIPE_BASE` says which one is in use.

Example
-------
>>> import lsst.pex.config as pexConfig
>>> class MyConfig(pexConfig.Config):
...     n_iter = pexConfig.Field(doc="number of iterations", dtype=int, default=3,
...                              check=lambda v: v > 0)
>>> c = MyConfig()
>>> c.n_iter = 5
>>> c.validate(); c.freeze()
"""

import json
import logging
import os
import tomllib

import lsst.pex.config as pexConfig

from lsst_bfdrift.utils.errors import (FieldValidationError, InputError, InputFileError,
                                       InputNotFoundError, InputTypeError)
from lsst_bfdrift.utils.io import atomic_output

__all__ = ["FieldValidationError", "Struct", "Task", "HAVE_PIPE_BASE", "load_config",
           "save_config", "config_from_dict"]



class _Struct:
    """Attribute container returned by ``Task.run`` (fallback of
    :class:`lsst.pipe.base.Struct`)."""

    def __init__(self, **kwargs):
        self.__dict__.update(kwargs)

    def getDict(self):  # noqa: N802 (LSST name)
        """The attributes as a dict."""
        return dict(self.__dict__)

    def __repr__(self):
        return f"Struct({', '.join(sorted(self.__dict__))})"


class _Task:
    """Base class of tasks (fallback of :class:`lsst.pipe.base.Task`).

    Subclasses set ``ConfigClass`` and ``_DefaultName`` and implement ``run``.
    """

    ConfigClass = pexConfig.Config
    _DefaultName = "task"

    def __init__(self, config=None, *, name=None, parentTask=None, log=None):  # noqa: N803
        if parentTask is not None:
            if name is None:
                raise InputError("name is required for a subtask")
            if config is None:
                config = getattr(parentTask.config, name)
            self._fullName = f"{parentTask._fullName}.{name}"
        else:
            name = name or self._DefaultName
            self._fullName = name
            if config is None:
                config = self.ConfigClass()
        self._name = name
        self.config = config
        base = log.getChild(self._fullName).name if log is not None else \
            f"lsst_bfdrift.{self._fullName}"
        self.log = logging.getLogger(base)

    def getName(self):  # noqa: N802 (LSST name)
        """The task's name."""
        return self._name

    def getFullName(self):  # noqa: N802 (LSST name)
        """The task's name with its parents', dot-separated."""
        return self._fullName

    def makeSubtask(self, name, **kwargs):  # noqa: N802 (LSST name)
        """Build the subtask configured by ``ConfigurableField`` ``name``."""
        field = getattr(self.config, name)
        sub = field.apply(name=name, parentTask=self, **kwargs)
        setattr(self, name, sub)
        return sub


try:
    from lsst.pipe.base import Struct, Task
    HAVE_PIPE_BASE = True
except ImportError:  # the core install: no [lsst] extra
    Struct, Task = _Struct, _Task
    HAVE_PIPE_BASE = False


def config_from_dict(config_class, mapping, *, source="config"):
    """A ``config_class`` with the values of ``mapping`` (nested for sub-configs).

    Parameters
    ----------
    config_class : type
        A :class:`lsst.pex.config.Config` subclass.
    mapping : dict
        Field names and values, as ``Config.toDict()`` gives them.
    source : str, optional
        What the values came from (for messages).

    Raises
    ------
    InputError
        An unknown field name (the known ones are listed).
    FieldValidationError
        A value of the wrong type or out of range.
    """
    config = config_class()
    _update(config, mapping, source)
    return config


def _update(config, mapping, source):
    if not isinstance(mapping, dict):
        raise InputError(f"{source}: expected a table of field names and values, got "
                         f"{type(mapping).__name__}")
    known = set(config._fields)
    for key, value in mapping.items():
        if key not in known:
            raise InputError(f"{source}: {type(config).__name__} has no field {key!r}; "
                             f"fields: {', '.join(sorted(known))}")
        current = getattr(config, key)
        if isinstance(current, pexConfig.Config) and isinstance(value, dict):
            _update(current, value, f"{source}.{key}")
        else:
            setattr(config, key, value)


def load_config(config_class, path):
    """Read a config file.

    Parameters
    ----------
    config_class : type
        A :class:`lsst.pex.config.Config` subclass.
    path : str or path-like
        A pex_config override file (Python: ``config.<field> = value``, any
        name but ``.json``/``.toml``), or a JSON table, or a TOML table (the
        name ending in ``.toml``) of field names and values.

    Returns
    -------
    lsst.pex.config.Config
        A validated ``config_class`` instance (not frozen).

    Raises
    ------
    InputNotFoundError, InputFileError
        Missing or unreadable file.
    InputError, FieldValidationError
        Unknown field or bad value.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputNotFoundError(f"{path}: no such config file", path)
    if path.endswith((".json", ".toml")):
        with open(path, "rb") as fh:
            raw = fh.read()
        toml = path.endswith(".toml")
        try:
            data = tomllib.loads(raw.decode()) if toml else json.loads(raw.decode())
        except (UnicodeDecodeError, json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
            raise InputFileError(f"{path}: not valid {'TOML' if toml else 'JSON'}: {exc}",
                                 path) from None
        config = config_from_dict(config_class, data, source=path)
    else:
        config = config_class()
        try:
            config.load(path)
        except (pexConfig.FieldValidationError, AttributeError, NameError, SyntaxError,
                TypeError) as exc:
            raise InputFileError(f"{path}: not a valid {config_class.__name__} override file "
                                 f"({type(exc).__name__}: {exc})", path) from exc
    config.validate()
    return config


def save_config(config, path, *, overwrite=True):
    """Write ``config`` as a pex_config override file (atomically).

    Parameters
    ----------
    config : lsst.pex.config.Config
    path : str or path-like
    overwrite : bool, optional
        Replace an existing file.
    """
    if not isinstance(config, pexConfig.Config):
        raise InputTypeError(f"config must be an lsst.pex.config.Config, got "
                             f"{type(config).__name__}")
    with atomic_output(path, overwrite=overwrite) as tmp:
        config.save(tmp)
