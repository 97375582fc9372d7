"""Helpers shared by the ``bfdrift`` commands: templates in, JSON or text out, the overwrite rule."""

import json
import os

from lsst_bfdrift.utils.errors import OutputExistsError
from lsst_bfdrift.utils.io import check_output

__all__ = []


def _load_template(path):
    from lsst_bfdrift.templates.template import DistortionTemplate, load_default_template
    return load_default_template() if path is None else DistortionTemplate.load(path)


def _print_json(obj):
    print(json.dumps(obj, indent=2, sort_keys=True, default=float))


def _emit(obj, as_json, width=18):
    """Print ``obj`` as JSON, or as aligned ``key: value`` lines."""
    if as_json:
        _print_json(obj)
    else:
        for k, v in obj.items():
            print(f"{k:>{width}s}: {v}")
    return 0


def _check_outputs(args, inputs, outputs):
    """The overwrite rule for every output of a command, checked before any work.

    Each output in ``outputs`` (option name -> path or None) goes through
    :func:`~lsst_bfdrift.utils.io.check_output`: never one of ``inputs``,
    an existing file only with ``--overwrite``; two options may not name one
    file.

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


def _template_input(path):
    """The template file a command reads (the bundled one when ``path`` is None)."""
    from lsst_bfdrift.templates.template import default_template_path
    return default_template_path() if path is None else path


def _save_and_report(tpl, args):
    tpl.save(args.out, overwrite=True)
    if args.json:
        _print_json(tpl.summary())
    else:
        print(f"wrote {args.out}")
    return 0


def _save_plot(fig, path, summary=None):
    """Write the figure of ``--plot``; its absolute path in ``summary['plot']``."""
    from lsst_bfdrift.utils.plotting import save_figure
    save_figure(fig, path)
    if summary is not None:
        summary["plot"] = os.path.abspath(path)


def _check_output_dir(args, path, option, inputs=()):
    """The overwrite rule for a directory output (``--report DIR``, ``reproduce --out``):
    a directory holding files is replaced only with ``--overwrite``, and it may never be
    an input (a directory of flats given as the input too).

    Raises
    ------
    OutputExistsError
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

