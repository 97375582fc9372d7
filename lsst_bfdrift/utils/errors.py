"""The package's exceptions: one base class, subclasses that are also builtins.

Every error the package raises on purpose derives from :class:`BfdriftError`,
so ``except BfdriftError`` catches all of them and nothing else (a bug
elsewhere still shows its traceback). Each subclass also derives from the
builtin exception a caller would have caught before, so ``except ValueError``
(or ``FileExistsError``, ``TypeError``, ...) keeps working:

=============================  =====================================  =====================
class                          also a                                 ``bfdrift`` exit code
=============================  =====================================  =====================
:class:`InputError`            ``ValueError``                         2
:class:`InputTypeError`        ``ValueError``, ``TypeError``          2
:class:`InputKeyError`         ``ValueError``, ``KeyError``           2
:class:`InputFileError`        ``ValueError``                         2
:class:`InputNotFoundError`    ``ValueError``, ``FileNotFoundError``  2
:class:`TemplateFileError`     ``ValueError``                         2
:class:`FieldValidationError`  ``ValueError`` (pex_config's)           2
:class:`OutputExistsError`     ``FileExistsError``                    3
:class:`FitError`              ``ValueError``                         4
:class:`ComputationError`      ``RuntimeError``                       4
=============================  =====================================  =====================

Any other ``OSError`` (permission denied, disk full) gives exit code 1 in the
command line; see ``docs/cli.rst``.
"""

import os

import lsst.pex.config as _pexConfig

__all__ = ["BfdriftError", "InputError", "InputTypeError", "InputKeyError",
           "InputAttributeError", "InputFileError",
           "InputNotFoundError", "TemplateFileError", "FieldValidationError",
           "OutputExistsError", "FitError", "ComputationError"]


class BfdriftError(Exception):
    """Base class of every error raised on purpose by lsst_bfdrift."""


class InputError(BfdriftError, ValueError):
    """An argument, a value or an input's content is not accepted.

    The message names the argument (or file) and what would be accepted.
    """


class InputTypeError(InputError, TypeError):
    """An argument is of the wrong type (also a ``TypeError``)."""


class InputKeyError(InputError, KeyError):
    """An unknown name, key or column (also a ``KeyError``).

    Unlike ``KeyError``, ``str()`` gives the message without quotes.
    """

    def __str__(self):
        return str(self.args[0]) if len(self.args) == 1 else super().__str__()


class InputAttributeError(InputError, AttributeError):
    """An unknown field or attribute was set (also an ``AttributeError``)."""


class InputFileError(InputError):
    """An input file cannot be used: truncated, malformed, missing a column.

    Parameters
    ----------
    message : str
        What is wrong and what would be accepted; it should name the file.
    path : str or os.PathLike, optional
        The file; prepended to ``message`` when the message does not already
        contain it.

    Attributes
    ----------
    path : str or None
        The file.
    """

    def __init__(self, message, path=None):
        self.path = None if path is None else os.fspath(path)
        if self.path is not None and self.path not in str(message):
            message = f"{self.path}: {message}"
        super().__init__(message)


class InputNotFoundError(InputFileError, FileNotFoundError):
    """An input file does not exist (also a ``FileNotFoundError``)."""


class TemplateFileError(InputFileError):
    """A template file is corrupt, truncated, inconsistent or of another version."""


#: A config value is of the wrong type, out of range, or set on a frozen config:
#: ``lsst.pex.config.FieldValidationError`` itself (a ``ValueError``, not a
#: :class:`BfdriftError`; ``bfdrift`` maps it to exit status 2 all the same).
FieldValidationError = _pexConfig.FieldValidationError


class OutputExistsError(BfdriftError, FileExistsError):
    """An output would replace an existing file (without ``overwrite``) or one
    of the inputs (always refused)."""


class FitError(BfdriftError, ValueError):
    """The fit is unusable: bad input, or a poor fit when one was refused."""


class ComputationError(BfdriftError, RuntimeError):
    """A computation did not converge or became degenerate on valid-looking input."""
