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

Every results file of ``benchmarks/`` (and so every one that
``docs/benchmarks.rst`` includes) starts with the command that wrote it, a
``# command: python SCRIPT ...`` line naming an existing script whose name
the results file carries (``SCRIPT_results``, or ``SCRIPT_VARIANT_results``);
its JSON twin has the same command under ``"command"``; and
``benchmarks/README.md`` lists each of them with its script.
"""

import glob
import json
import os
import re
import sys

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


_INCLUDE = re.compile(r"^\.\. literalinclude:: \.\./(?P<path>benchmarks/\S+)", re.M)
_COMMAND = "# command: "


def included_results():
    """The results files (repository-relative) that docs/benchmarks.rst includes."""
    with open(os.path.join(ROOT, "docs", "benchmarks.rst"), encoding="utf-8") as fh:
        return sorted(set(_INCLUDE.findall(fh.read())))


def all_results():
    return sorted(os.path.relpath(p, ROOT) for p in glob.glob(
        os.path.join(ROOT, "benchmarks", "**", "*_results*.*"), recursive=True))


def commands_of(rel):
    """The commands a results file says it was written by."""
    with open(os.path.join(ROOT, rel), encoding="utf-8") as fh:
        if rel.endswith(".json"):
            cmd = json.load(fh).get("command")
            return cmd.split(" && ") if isinstance(cmd, str) else []
        out = []
        for line in fh:
            if not line.startswith(_COMMAND):
                break
            out.append(line[len(_COMMAND):].strip())
        return out


def producer_problems(rel):
    """Why the command(s) of results file ``rel`` do not name its producer ([] if they do)."""
    cmds = commands_of(rel)
    if not cmds:
        return [f"{rel}: does not start with '{_COMMAND}...' (or has no 'command' key)"]
    name = os.path.basename(rel)
    problems = []
    for cmd in cmds:
        words = cmd.split()
        if len(words) < 2 or words[0] != "python" or not words[1].endswith(".py"):
            problems.append(f"{rel}: {cmd!r} is not 'python SCRIPT.py ...'")
            continue
        script = words[1]
        stem = os.path.splitext(os.path.basename(script))[0]
        if not os.path.isfile(os.path.join(ROOT, script)):
            problems.append(f"{rel}: {script} does not exist")
        if not re.fullmatch(re.escape(stem) + r"(_\w+)?_results\.(txt|json)", name):
            problems.append(f"{rel}: not named after its script {script}")
    return problems


def test_the_docs_include_results_files():
    got = included_results()
    assert len(got) >= 30 and all(p.endswith("_results.txt") for p in got), got
    assert "benchmarks/performance/bench_task_results.txt" in got


@pytest.mark.parametrize("rel", included_results())
def test_included_results_name_their_producer(rel):
    assert os.path.isfile(os.path.join(ROOT, rel)), rel
    assert not producer_problems(rel), "\n".join(producer_problems(rel))


@pytest.mark.parametrize("rel", all_results())
def test_every_results_file_names_its_producer(rel):
    assert not producer_problems(rel), "\n".join(producer_problems(rel))
    twin = rel[:-len(".txt")] + ".json" if rel.endswith(".txt") else None
    if twin and os.path.isfile(os.path.join(ROOT, twin)):
        assert commands_of(twin) == commands_of(rel), (rel, twin)


def test_the_benchmarks_readme_lists_every_results_file():
    with open(os.path.join(ROOT, "benchmarks", "README.md"), encoding="utf-8") as fh:
        rows = [ln.split("|") for ln in fh if ln.startswith("| ") and "_results`" in ln]
    listed = {}
    for row in rows:
        script, results = (c.strip().strip("`") for c in row[-3:-1])
        listed[results] = script
        path = script if script.startswith("scripts/") else os.path.join("benchmarks", script)
        assert os.path.isfile(os.path.join(ROOT, path)), script
    stems = {os.path.relpath(os.path.splitext(p)[0], "benchmarks") for p in all_results()}
    assert set(listed) == stems, set(listed) ^ stems
    for results, script in listed.items():
        txt = os.path.join("benchmarks", results + ".txt")
        first = commands_of(txt if os.path.isfile(os.path.join(ROOT, txt)) else txt[:-4] + ".json")
        assert first and first[0].split()[1].endswith(os.path.basename(script)), results


def test_the_producer_check_finds_wrong_headers(tmp_path, monkeypatch):
    monkeypatch.setattr(sys.modules[__name__], "ROOT", str(tmp_path))
    (tmp_path / "benchmarks" / "x").mkdir(parents=True)
    (tmp_path / "benchmarks" / "x" / "run.py").write_text("")
    files = {"run_results.txt": "# command: python benchmarks/x/run.py --n 2\n1\n",
             "run_e2v_results.txt": "# command: python benchmarks/x/run.py\n",
             "other_results.txt": "# command: python benchmarks/x/run.py\n",
             "gone_results.txt": "# command: python benchmarks/x/gone.py\n",
             "bare_results.txt": "figures\n",
             "run_results.json": json.dumps({"command": "python benchmarks/x/run.py --n 2"})}
    for name, text in files.items():
        (tmp_path / "benchmarks" / "x" / name).write_text(text)
    bad = {name for name in files if producer_problems(f"benchmarks/x/{name}")}
    assert bad == {"other_results.txt", "gone_results.txt", "bare_results.txt"}
    assert commands_of("benchmarks/x/run_results.json") == ["python benchmarks/x/run.py --n 2"]


def test_readme_says_how_to_build_the_docs_and_how_long_the_tests_take():
    """Issue 43 item 6: the docs extra is installed before the build, and the test
    suite's duration is stated."""
    with open(os.path.join(ROOT, "README.md")) as fh:
        text = fh.read()
    assert 'pip install ".[docs]" && python3 -m sphinx' in text
    assert re.search(r"suite takes about \d+(\.\d+)? minutes on 2 cores", text)
