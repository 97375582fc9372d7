"""Helpers shared by the ``bfdrift`` commands: templates in, JSON or text out,
the overwrite rule, the defaults taken from the library, SIGTERM.

A private module of :mod:`lsst_bfdrift.cli` whose names are public within it:
the command modules import them; nothing outside the ``cli`` package should.
"""

import contextlib
import inspect
import json
import math
import os
import signal
import sys
import threading

import numpy as np

from lsst_bfdrift.templates.template import (DistortionTemplate, default_template_path,
                                             load_default_template)
from lsst_bfdrift.utils.errors import OutputExistsError
from lsst_bfdrift.utils.io import check_output, remove_stale_temporaries

__all__ = ["library_default", "load_template", "print_json", "emit", "check_outputs",
           "template_input", "save_and_report", "save_plot", "check_output_dir",
           "OUTPUT_OPTIONS", "output_dirs", "remove_stale_outputs", "Terminated",
           "sigterm_raises", "add_common_options"]

#: Help of the options every command shares (:func:`add_common_options`).
COMMON_HELP = {"overwrite": "replace existing outputs",
               "json": "print the result as JSON on stdout",
               "quiet": "no progress on stderr"}


def library_default(func, name):
    """The default of the keyword ``name`` of ``func``: the one source of a
    command-line option's default that feeds it.

    Parameters
    ----------
    func : callable
        The library function the option is passed to.
    name : str
        Its parameter.

    Returns
    -------
    default : object
        ``inspect.signature(func).parameters[name].default``.

    Raises
    ------
    KeyError
        ``func`` has no parameter ``name``.
    ValueError
        The parameter has no default.
    """
    default = inspect.signature(func).parameters[name].default
    if default is inspect.Parameter.empty:
        raise ValueError(f"{func.__qualname__}({name}=...) has no default")
    return default


def add_common_options(parser, *names, **helps):
    """Add the shared flags ``--overwrite``, ``--json``, ``--quiet`` (those named).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        A subcommand's parser.
    *names : str
        Of ``'overwrite'``, ``'json'``, ``'quiet'``, in the order of the help.
    **helps : str
        A help text of the command's own for one of them (default
        :data:`COMMON_HELP`).
    """
    for name in names:
        parser.add_argument(f"--{name}", action="store_true",
                            help=helps.get(name, COMMON_HELP[name]))


def load_template(path):
    """The template of ``--template FILE`` (the bundled default when ``path`` is None).

    Parameters
    ----------
    path : str or None
        Template FITS file.

    Returns
    -------
    template : DistortionTemplate
    """
    return load_default_template() if path is None else DistortionTemplate.load(path)


def print_json(obj):
    """Print ``obj`` as strict JSON, indented, keys sorted (numpy scalars as floats,
    NaN and infinities as null).

    Parameters
    ----------
    obj : dict
        The command's result.
    """
    print(json.dumps(_finite(obj), indent=2, sort_keys=True, default=float, allow_nan=False))


def _finite(obj):
    """``obj`` with non-finite floats as None: strict JSON has no NaN or Infinity."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    return obj


def emit(obj, as_json, width=18):
    """Print ``obj`` as JSON, or as aligned ``key: value`` lines.

    Parameters
    ----------
    obj : dict
        The command's result.
    as_json : bool
        JSON (``--json``) or text.
    width : int, optional
        Width of the right-aligned keys of the text.

    Returns
    -------
    code : int
        0, the command's exit status.
    """
    if as_json:
        print_json(obj)
    else:
        for k, v in obj.items():
            print(f"{k:>{width}s}: {v}")
    return 0


def check_outputs(args, inputs, outputs):
    """The overwrite rule for every output of a command, checked before any work.

    Each output in ``outputs`` (option name -> path or None) goes through
    :func:`~lsst_bfdrift.utils.io.check_output`: never one of ``inputs``,
    an existing file only with ``--overwrite``; two options may not name one
    file.

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments (``overwrite``).
    inputs : sequence of str or None
        The command's inputs (None entries ignored).
    outputs : dict
        Option name -> output path or None.

    Raises
    ------
    OutputExistsError
        An output breaks the rule.
    """
    overwrite = bool(getattr(args, "overwrite", False))
    inputs = [os.fspath(x) for x in inputs if x is not None]
    seen = {}
    for option, path in outputs.items():
        if path is None:
            continue
        check_output(path, inputs, overwrite=overwrite, what=option)
        real = os.path.realpath(path)
        if real in seen:
            raise OutputExistsError(f"{option} {path} is also given to {seen[real]}; give "
                                    "each output its own file")
        seen[real] = option


def template_input(path):
    """The template file a command reads (the bundled one when ``path`` is None).

    Parameters
    ----------
    path : str or None
        ``--template FILE``.

    Returns
    -------
    path : str
    """
    return default_template_path() if path is None else path


def save_and_report(tpl, args):
    """Write the template to ``--out`` and print its summary (``--json``) or the path.

    Parameters
    ----------
    tpl : DistortionTemplate
        The template made by the command.
    args : argparse.Namespace
        The command's arguments (``out``, ``json``).

    Returns
    -------
    code : int
        0, the command's exit status.
    """
    tpl.save(args.out, overwrite=True)
    if args.json:
        print_json(tpl.summary())
    else:
        print(f"wrote {args.out}")
    return 0


def save_plot(fig, path, summary=None):
    """Write the figure of ``--plot``; its absolute path in ``summary['plot']``.

    Parameters
    ----------
    fig : matplotlib.figure.Figure
        The figure.
    path : str
        The PNG file.
    summary : dict, optional
        The command's result, given the key ``plot``.
    """
    # matplotlib: only when --plot is given
    from lsst_bfdrift.utils.plotting import save_figure
    save_figure(fig, path)
    if summary is not None:
        summary["plot"] = os.path.abspath(path)


def check_output_dir(args, path, option, inputs=()):
    """The overwrite rule for a directory output (``--report DIR``, ``reproduce --out``):
    a directory holding files is replaced only with ``--overwrite``, and it may never be
    an input (a directory of flats given as the input too).

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments (``overwrite``).
    path : str or None
        The directory; None: nothing to check.
    option : str
        The option naming it, for the message.
    inputs : sequence of str, optional
        The command's inputs.

    Raises
    ------
    OutputExistsError
        The directory breaks the rule.
    """
    if path is None:
        return
    path = os.path.abspath(os.fspath(path))
    for x in inputs:
        if x is not None and os.path.abspath(os.fspath(x)) == path:
            raise OutputExistsError(f"{option} {path}: is also an input; write the output "
                                    "elsewhere")
    if os.path.isdir(path) and os.listdir(path) and not getattr(args, "overwrite", False):
        raise OutputExistsError(f"{option} {path}: the directory exists and holds files; "
                                "use --overwrite to replace its outputs, or name another "
                                "directory")
    if os.path.exists(path) and not os.path.isdir(path):
        raise OutputExistsError(f"{option} {path}: exists and is not a directory")


#: Options naming an output file or directory (the directories written into).
OUTPUT_OPTIONS = ("out", "out_dir", "plot", "catalog", "report", "prefix")


def output_dirs(args):
    """The directories a command writes into (absolute, without repeats).

    The directory of each output option's path, and the path itself when it is
    a directory (``--out-dir``, ``--report``, ``reproduce --out``); for
    ``correct IN OUT`` the directory of OUT.

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments.

    Returns
    -------
    dirs : list of str
    """
    paths = [getattr(args, name, None) for name in OUTPUT_OPTIONS]
    inputs = getattr(args, "inputs", None)
    if hasattr(args, "out_dir") and not args.out_dir and inputs and len(inputs) == 2:
        paths.append(inputs[1])  # correct IN OUT
    dirs = []
    for p in paths:
        if not isinstance(p, (str, os.PathLike)):
            continue
        p = os.path.abspath(os.fspath(p))
        for d in ((p, os.path.dirname(p)) if os.path.isdir(p) else (os.path.dirname(p),)):
            if d not in dirs:
                dirs.append(d)
    return dirs


def _input_dirs(args):
    """Directories given as inputs (``bfdrift ptc DIR``, ``diagnose DIR``): a killed
    run may have written into them too, and their readers skip partial files."""
    out = []
    for name in ("files", "input", "inputs"):
        for p in getattr(args, name, None) or ():
            if isinstance(p, (str, os.PathLike)) and os.path.isdir(p):
                d = os.path.abspath(os.fspath(p))
                if d not in out:
                    out.append(d)
    return out


def remove_stale_outputs(args, stream=None):
    """Remove the partial files of killed runs (``.tmp-*`` of
    :func:`~lsst_bfdrift.utils.io.atomic_output` whose process is gone) from
    the directories the command writes into and from directories given as
    inputs (whose readers skip such files: without this they would stay
    forever), and say so on ``stream`` (stderr).

    Parameters
    ----------
    args : argparse.Namespace
        The command's arguments.
    stream : file, optional
        Where the removal is reported (default: stderr).

    Returns
    -------
    list of str
        The files removed.
    """
    removed = []
    for d in output_dirs(args) + _input_dirs(args):
        try:
            removed += remove_stale_temporaries(d)
        except OSError as exc:  # e.g. a directory we may not list: not this run's concern
            print(f"bfdrift: warning: could not check {d} for partial files: {exc}",
                  file=sys.stderr if stream is None else stream)
    if removed:
        print(f"bfdrift: removed {len(removed)} stale partial file"
              f"{'s' if len(removed) > 1 else ''} of killed runs: {', '.join(removed)}",
              file=sys.stderr if stream is None else stream)
    return removed


class Terminated(SystemExit):
    """SIGTERM received: raised in the main thread so that ``finally`` blocks
    (the removal of a partial output) run; exit status 128 + 15."""


@contextlib.contextmanager
def sigterm_raises():
    """Within the block, SIGTERM raises ``Terminated`` (a SystemExit) instead
    of ending the process at once, so that temporary files are removed. The
    previous handler comes back after; outside the main thread nothing changes.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def _raise(signum, frame):
        raise Terminated(128 + signum)

    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
