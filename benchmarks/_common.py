"""The results-writing tail shared by the benchmark scripts.

A benchmark script, run as ``python benchmarks/<folder>/<script>.py`` from the
repository root, puts this folder on the import path with one line after its
``HERE``::

    sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common

then ends with::

    from _common import write_results
    write_results(args.out, lines, record, script=__file__)

which writes ``<prefix>.txt`` (first line ``# command: python
benchmarks/<folder>/<script>.py ...``, then the lines) and ``<prefix>.json``
(``{"command": ..., **record}``), both atomically.
"""

import os
import shlex
import sys

import numpy as np

from lsst_bfdrift.utils.io import write_json, write_text

__all__ = ["REPO", "Lines", "command_line", "settings_record", "to_json", "write_results"]

#: The repository root: the folder that holds ``benchmarks/``.
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


class Lines(list):
    """The lines of a run: each printed when said and kept for the results file.

    Calling it says a line (``say = Lines(); say("...")``); as a list it is
    the ``lines`` of :func:`write_results`. A new ``Lines`` opens with the
    machine line (cores, 1-minute load average; ``note`` appended) unless
    ``machine=False``.
    """

    def __init__(self, *, machine=True, note=""):
        super().__init__()
        if machine:
            load = os.getloadavg()
            self(f"machine: {os.cpu_count()} cores, load average {load[0]:.1f} (1 min) at "
                 "the start" + (f"; {note}" if note else ""))

    def __call__(self, line):
        print(line, flush=True)
        self.append(line)


def settings_record(args, *, leave=("out",)):
    """The parsed options as a record's ``settings`` (``--out`` and the like left out)."""
    return {k: v for k, v in vars(args).items() if k not in leave}


def command_line(script):
    """This run's command as typed from the repository root.

    Parameters
    ----------
    script : str or path-like
        The running script's file (pass ``__file__``), so that a script that
        imports another one still names itself.

    Returns
    -------
    str
        ``python <script path relative to the repository root> <sys.argv[1:]>``,
        each word quoted for a POSIX shell (:func:`shlex.join`).
    """
    path = os.path.relpath(os.path.abspath(os.fspath(script)), REPO)
    return shlex.join(["python", path] + sys.argv[1:])


def to_json(obj):
    """JSON ``default`` for numpy values: arrays as lists, numpy scalars as floats.

    Parameters
    ----------
    obj : object
        A value :mod:`json` cannot write itself.

    Returns
    -------
    list or float

    Raises
    ------
    TypeError
        ``obj`` is neither an array nor a number.
    """
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    try:
        return float(obj)
    except (TypeError, ValueError):
        raise TypeError(f"Object of type {type(obj).__name__} is not JSON serializable") from None


def write_results(prefix, lines, record=None, *, script, json_default=None, indent=1):
    """Write a benchmark's results files, each starting with the command that wrote it.

    Parameters
    ----------
    prefix : str or path-like
        Output path without suffix (e.g. ``benchmarks/stars/validate_sky_results``).
    lines : iterable of str
        The text lines (without newlines); ``<prefix>.txt`` is
        ``"# command: <command>\\n" + "\\n".join(lines) + "\\n"``.
    record : dict, optional
        When given, ``<prefix>.json`` is written as ``{"command": <command>,
        **record}``. ``record`` itself is not modified.
    script : str or path-like
        The running script's file (pass ``__file__``); see :func:`command_line`.
    json_default : callable, optional
        :func:`json.dump`'s ``default`` (default :func:`to_json`).
    indent : int, optional
        :func:`json.dump`'s indent (default 1).

    Returns
    -------
    str
        The command written on the first line.

    Raises
    ------
    TypeError
        ``lines`` is a single string, or ``record`` is not a dict.
    """
    if isinstance(lines, (str, bytes)):
        raise TypeError("lines must be a sequence of strings, not one string")
    if record is not None and not isinstance(record, dict):
        raise TypeError(f"record must be a dict, got {type(record).__name__}")
    prefix = os.fspath(prefix)
    command = command_line(script)
    write_text(prefix + ".txt", f"# command: {command}\n" + "\n".join(lines) + "\n")
    if record is not None:
        write_json(prefix + ".json", {"command": command, **record}, indent=indent,
                   default=to_json if json_default is None else json_default)
    return command
