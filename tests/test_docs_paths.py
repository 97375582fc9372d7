"""The docs and the README name only repository files that exist (issue 19, item 9).

Every path under one of the repository's own top-level directories
(``benchmarks/``, ``docs/``, ``lsst_bfdrift/``, ``scripts/``, ``tests/``) that
``docs/*.rst`` or ``README.md`` mentions, in an example command or in the
text, must exist; so must ``../``-relative and ``_static/`` paths of the
docs (relative to ``docs/``). User placeholders (``flat_*.fits``,
``in.fits``, ``/tmp/...``) are not under those directories and are not
checked. A path may be an output prefix (``--out benchmarks/x_results``
writes ``x_results.txt`` and ``.json``) or a glob; build products
(``docs/_build``) are generated, not stored.
"""

import glob
import os
import re

import pytest

__all__ = []

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TOP = ("benchmarks", "docs", "lsst_bfdrift", "scripts", "tests")
GENERATED = ("docs/_build",)
# a path starts a token: not preceded by a path character (so that /tmp/x/tests/y
# and https://host/docs/y are not taken); sphinx-relative forms in docs/ too
_PATH = re.compile(r"(?<![\w./:-])(?P<path>(?:\.\./)?(?:" + "|".join(TOP + ("_static",))
                   + r")/[\w./*-]*[\w*/])")


def _doc_files():
    return sorted(glob.glob(os.path.join(ROOT, "docs", "*.rst"))) + \
        [os.path.join(ROOT, "README.md")]


def mentioned_paths(text, doc):
    """(line, path as written, repository-relative path) of the paths in ``text``.

    ``doc`` is the file's path relative to the repository: ``../x`` and
    ``_static/x`` in ``docs/`` are relative to ``docs/``.
    """
    base = os.path.dirname(doc)
    found = []
    for lineno, line in enumerate(text.splitlines(), 1):
        for m in _PATH.finditer(line):
            path = m["path"]
            if path.startswith(("../", "_static/")):
                if base != "docs":
                    continue  # only the docs are built from docs/
                rel = os.path.normpath(os.path.join(base, path))
            else:
                rel = os.path.normpath(path)
            found.append((lineno, path, rel))
    return found


def exists(rel):
    """Whether ``rel`` (repository-relative) names a file or directory, a glob
    that matches one, or an output prefix of existing files (``rel.*``)."""
    full = os.path.join(ROOT, rel)
    if any(ch in rel for ch in "*?["):
        return bool(glob.glob(full))
    return os.path.exists(full) or bool(glob.glob(glob.escape(full) + ".*"))


@pytest.mark.parametrize("doc", [os.path.relpath(p, ROOT) for p in _doc_files()])
def test_paths_in_the_docs_exist(doc):
    with open(os.path.join(ROOT, doc), encoding="utf-8") as fh:
        text = fh.read()
    missing = [f"{doc}:{n}: {path}" for n, path, rel in mentioned_paths(text, doc)
               if not rel.startswith(GENERATED) and not exists(rel)]
    assert not missing, "paths that do not exist in the repository:\n" + "\n".join(missing)


def test_the_scan_finds_repository_paths_and_skips_placeholders():
    text = ("$ python benchmarks/performance/bench_task.py --size 64\n"
            "$ bfdrift correct in.fits out.fits --out-dir /tmp/x/tests/y\n"
            "see https://example.org/docs/z.html and flat_*.fits, my.fits\n"
            "``lsst_bfdrift/data/default_template.fits``. tests/test_layers.py,\n"
            ".. image:: _static/flat_sim.png\n"
            ".. literalinclude:: ../benchmarks/performance/bench_engine_results.txt\n")
    got = [(n, rel) for n, _, rel in mentioned_paths(text, "docs/x.rst")]
    assert got == [(1, "benchmarks/performance/bench_task.py"),
                   (4, "lsst_bfdrift/data/default_template.fits"),
                   (4, "tests/test_layers.py"),
                   (5, "docs/_static/flat_sim.png"),
                   (6, "benchmarks/performance/bench_engine_results.txt")]
    assert all(exists(rel) for _, rel in got)
    assert not exists("benchmarks/no_such_script.py")
    assert exists("benchmarks/correction/validate_stars_400_results")  # an output prefix
    assert exists("tests/*/test_*.py")
    assert mentioned_paths("_static/a.png ../benchmarks/b.txt", "README.md") == []
