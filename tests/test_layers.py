"""The package's import graph follows the data flow (a structural test).

Every import of a package module, at the top of a file or inside a function,
is parsed from the source. A subpackage may import only from subpackages
earlier in :data:`LAYERS`; private modules (``_name``) only from their own
subpackage; and no import cycle may exist between modules.
"""

import ast
import pathlib

import pytest

import lsst_bfdrift

#: Stages in data-flow order: each imports only from those before it.
LAYERS = ("utils", "images", "physics", "templates", "geometry", "correction", "simulation",
          "ptc", "catalogs", "calibration", "diagnosis", "validation", "pipeline", "cli")

ROOT = pathlib.Path(lsst_bfdrift.__file__).parent


def _module_name(path):
    rel = path.relative_to(ROOT.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path):
    """Package modules imported by the file at ``path`` (absolute names)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = _module_name(path)
    pkg = me if path.name == "__init__.py" else me.rpartition(".")[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("lsst_bfdrift"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[:len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if not mod.startswith("lsst_bfdrift"):
                continue
            out.add(mod)
            # "from lsst_bfdrift.sub import module" imports a module too
            for a in node.names:
                if (ROOT.parent / (mod.replace(".", "/") + f"/{a.name}.py")).exists():
                    out.add(f"{mod}.{a.name}")
    return out


def _graph():
    return {_module_name(p): _imports(p) for p in sorted(ROOT.rglob("*.py"))}


def _stage(module):
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_every_module_is_in_a_stage():
    top = [m for m in _graph() if m.count(".") == 1 and _stage(m) not in LAYERS]
    assert top == [], f"modules outside the stage subpackages: {top}"


def test_imports_follow_the_data_flow():
    wrong = []
    for mod, deps in _graph().items():
        src = _stage(mod)
        if src is None:  # the package's __init__ re-exports the entry points
            continue
        for dep in deps:
            dst = _stage(dep)
            if dst is None:  # the package top imports every stage: an arrow up
                wrong.append(f"{mod} -> {dep}")
                continue
            if dst == src:
                continue
            if LAYERS.index(dst) > LAYERS.index(src):
                wrong.append(f"{mod} -> {dep}")
    assert wrong == [], "imports against the data flow:\n" + "\n".join(wrong)


def test_private_modules_stay_in_their_subpackage():
    wrong = []
    for mod, deps in _graph().items():
        for dep in deps:
            last = dep.rpartition(".")[2]
            if last.startswith("_") and not last.startswith("__") \
                    and _stage(dep) != _stage(mod):
                wrong.append(f"{mod} -> {dep}")
    assert wrong == [], "private modules used outside their subpackage:\n" + "\n".join(wrong)


def find_cycles(graph):
    """Cycles of a module graph {module: imported modules}; an edge between a
    package and one of its own modules is not one (its __init__ re-exports)."""
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if d == m or d not in graph or d.startswith(m + ".") or m.startswith(d + "."):
                continue
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    return cycles


def test_no_import_cycle():
    cycles = find_cycles(_graph())
    assert cycles == [], "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_cycle_finder_sees_the_old_template_galsim_cycle():
    graph = {"p.templates.template": {"p.templates.galsim_io"},
             "p.templates.galsim_io": {"p.templates.template", "p.physics.drift"},
             "p.physics.drift": set(), "p.templates": {"p.templates.template"}}
    assert find_cycles(graph) == [["p.templates.galsim_io", "p.templates.template",
                                   "p.templates.galsim_io"]]
    del graph["p.templates.template"]
    assert find_cycles(graph) == []


@pytest.mark.parametrize("bad, expected", [
    ("physics", "templates"), ("templates", "geometry"), ("correction", "calibration"),
    ("images", "physics"), ("ptc", "catalogs"), ("calibration", "diagnosis")])
def test_checker_sees_a_wrong_import(tmp_path, monkeypatch, bad, expected):
    """The check has power: a file of stage ``bad`` importing a later stage
    is reported."""
    fake = tmp_path / "lsst_bfdrift"
    (fake / bad).mkdir(parents=True)
    (fake / expected).mkdir()
    (fake / "__init__.py").write_text("")
    (fake / bad / "__init__.py").write_text("")
    (fake / expected / "__init__.py").write_text("")
    (fake / expected / "later.py").write_text("x = 1\n")
    (fake / bad / "early.py").write_text(
        f"def f():\n    from lsst_bfdrift.{expected}.later import x\n    return x\n")
    monkeypatch.setattr(__import__(__name__, fromlist=["ROOT"]), "ROOT", fake)
    with pytest.raises(AssertionError, match=f"lsst_bfdrift.{bad}.early -> "
                                             f"lsst_bfdrift.{expected}.later"):
        test_imports_follow_the_data_flow()


def test_checker_sees_an_import_of_the_package_top(tmp_path, monkeypatch):
    """An import of ``lsst_bfdrift`` itself from a stage points up (the top
    imports every stage) and is reported."""
    fake = tmp_path / "lsst_bfdrift"
    (fake / "correction").mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    (fake / "correction" / "__init__.py").write_text("")
    (fake / "correction" / "task.py").write_text(
        "def f():\n    from lsst_bfdrift import __version__\n    return __version__\n")
    monkeypatch.setattr(__import__(__name__, fromlist=["ROOT"]), "ROOT", fake)
    with pytest.raises(AssertionError, match=r"lsst_bfdrift.correction.task -> lsst_bfdrift\n"):
        test_imports_follow_the_data_flow()
