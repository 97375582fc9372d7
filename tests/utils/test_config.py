"""Tests of lsst_bfdrift.utils.config: configs on lsst.pex.config, Task and Struct
from lsst.pipe.base or the in-house fallback, config files.

These check the package's glue against the real pex_config / pipe_base
behaviour (round trips, refusals), not against a physical reference.
"""

import json
import subprocess
import sys
import textwrap

import lsst.pex.config as pexConfig
import pytest

from lsst_bfdrift.utils import config as config_mod
from lsst_bfdrift.utils.config import (FieldValidationError, config_from_dict, load_config,
                                       save_config)
from lsst_bfdrift.utils.errors import InputError, InputFileError, InputNotFoundError


class SubConfig(pexConfig.Config):
    scale = pexConfig.Field(doc="a scale factor (dimensionless)", dtype=float, default=2.0,
                            check=lambda v: v > 0)


def _classes(task_base, struct):
    class SubTask(task_base):
        ConfigClass = SubConfig
        _DefaultName = "sub"

        def run(self, x):
            return struct(y=x * self.config.scale)

    class TopConfig(pexConfig.Config):
        n_iter = pexConfig.Field(doc="iterations", dtype=int, default=3, check=lambda v: v > 0)
        method = pexConfig.ChoiceField(doc="how", dtype=str, default="drift", optional=False,
                                       allowed={"drift": "ours", "kernel": "K"})
        sub = pexConfig.ConfigurableField(doc="the subtask", target=SubTask)

    class TopTask(task_base):
        ConfigClass = TopConfig
        _DefaultName = "top"

        def __init__(self, **kw):
            super().__init__(**kw)
            self.makeSubtask("sub")

        def run(self, x):
            return struct(out=self.sub.run(x).y + self.config.n_iter)

    return TopConfig, TopTask


class TopConfig(pexConfig.Config):
    n_iter = pexConfig.Field(doc="iterations", dtype=int, default=3, check=lambda v: v > 0)
    label = pexConfig.Field(doc="an optional label", dtype=str, default=None, optional=True)
    method = pexConfig.ChoiceField(doc="how", dtype=str, default="drift", optional=False,
                                   allowed={"drift": "ours", "kernel": "K"})
    sub = pexConfig.ConfigField(doc="a sub-config", dtype=SubConfig)


@pytest.mark.parametrize("which", ["installed", "fallback"])
def test_task_with_subtask_returns_struct(which):
    """The same task code runs on lsst.pipe.base (when installed) and on the fallback."""
    if which == "installed":
        base, struct = config_mod.Task, config_mod.Struct
    else:
        base, struct = config_mod._Task, config_mod._Struct
    top_config, top_task = _classes(base, struct)
    cfg = top_config()
    cfg.n_iter = 1
    cfg.sub.scale = 3.0
    t = top_task(config=cfg)
    r = t.run(2.0)
    assert r.out == 7.0
    assert r.getDict() == {"out": 7.0}
    assert t.sub.getFullName() == "top.sub"
    assert t.log.name.endswith("top")


def test_fallback_is_used_without_pipe_base():
    """Without lsst.pipe.base the package imports and the Task runs (the core install)."""
    code = textwrap.dedent("""
        import sys
        sys.modules["lsst.pipe.base"] = None  # import fails as if not installed
        import numpy as np
        from lsst_bfdrift.utils import config
        from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask
        assert not config.HAVE_PIPE_BASE and config.Task is config._Task
        cfg = BrighterFatterDriftConfig(method="astier23", compute_geometry=False)
        img = np.full((40, 40), 100.0)
        img[20, 20] = 2e5
        res = BrighterFatterDriftTask(config=cfg).run(img)
        assert abs(res.flux_moved.sum()) < 1e-6 * 2e5 and np.abs(res.flux_moved).max() > 1.0
        print(type(res).__name__, res.converged)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["_Struct", "True"]


def test_pex_config_refusals():
    c = TopConfig()
    with pytest.raises(FieldValidationError, match="n_iter.*incorrect type float"):
        c.n_iter = 2.5
    with pytest.raises(FieldValidationError, match="method.*not allowed"):
        c.method = "magic"
    with pytest.raises(FieldValidationError, match="n_iter"):
        c.n_iter = 0
    c.freeze()
    with pytest.raises(FieldValidationError, match="frozen"):
        c.label = "x"


def test_config_from_dict_nested_and_unknown():
    c = config_from_dict(TopConfig, {"n_iter": 7, "sub": {"scale": 0.5}})
    assert (c.n_iter, c.sub.scale, c.label) == (7, 0.5, None)
    with pytest.raises(InputError, match="no field 'n_iters'.*fields: label, method, n_iter"):
        config_from_dict(TopConfig, {"n_iters": 3})
    with pytest.raises(InputError, match=r"here\.sub: .*no field 'scal'"):
        config_from_dict(TopConfig, {"sub": {"scal": 1.0}}, source="here")
    with pytest.raises(FieldValidationError, match="scale"):
        config_from_dict(TopConfig, {"sub": {"scale": -1.0}})


def test_override_file_round_trip(tmp_path):
    """save_config writes a pex_config override file; load_config reads it back."""
    c = config_from_dict(TopConfig, {"n_iter": 7, "label": "x", "sub": {"scale": 0.5}})
    path = tmp_path / "c.py"
    save_config(c, path)
    assert "config.n_iter=7" in path.read_text().replace(" ", "")
    d = load_config(TopConfig, path)
    assert d.toDict() == c.toDict()
    (tmp_path / "hand.py").write_text("config.method = 'kernel'\nconfig.sub.scale = 4.0\n")
    d = load_config(TopConfig, tmp_path / "hand.py")
    assert (d.method, d.sub.scale, d.n_iter) == ("kernel", 4.0, 3)
    assert not list(tmp_path.glob(".tmp*")) and not list(tmp_path.glob("*.tmp*"))


def test_json_and_toml_still_read(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps({"n_iter": 9, "sub": {"scale": 4.0}}))
    assert load_config(TopConfig, tmp_path / "c.json").n_iter == 9
    (tmp_path / "c.toml").write_text('n_iter = 9\nmethod = "kernel"\n[sub]\nscale = 4.0\n')
    d = load_config(TopConfig, tmp_path / "c.toml")
    assert (d.n_iter, d.method, d.sub.scale) == (9, "kernel", 4.0)


def test_load_reports_unreadable_files(tmp_path):
    """A config file in the wrong format names the file and what is wrong."""
    with pytest.raises(InputNotFoundError, match="no such config file"):
        load_config(TopConfig, tmp_path / "none.py")
    (tmp_path / "c.py").write_text("method = 'kernel'\nconfig.n_iters = 3\n")
    with pytest.raises(InputFileError, match=r"c\.py: not a valid TopConfig override file"):
        load_config(TopConfig, tmp_path / "c.py")
    (tmp_path / "bad.py").write_text("config.n_iter = 'many'\n")
    with pytest.raises(InputFileError, match=r"bad\.py.*n_iter"):
        load_config(TopConfig, tmp_path / "bad.py")
    (tmp_path / "c.toml").write_text("n_iter = = 3\n")
    with pytest.raises(InputFileError, match=r"c\.toml: not valid TOML"):
        load_config(TopConfig, tmp_path / "c.toml")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="expected a table.*got list"):
        load_config(TopConfig, tmp_path / "list.json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(InputFileError, match="bin.json: not valid JSON"):
        load_config(TopConfig, tmp_path / "bin.json")
    (tmp_path / "v.json").write_text('{"n_iter": 0}')
    with pytest.raises(FieldValidationError, match="n_iter"):
        load_config(TopConfig, tmp_path / "v.json")
