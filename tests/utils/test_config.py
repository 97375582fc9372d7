"""Tests of lsst_bfdrift.utils.config: the pex.config / pipe.base-like layer."""

import pytest

from lsst_bfdrift.utils.config import (ChoiceField, Config, ConfigurableField, Field,
                                 FieldValidationError, Struct, Task)


class SubConfig(Config):
    scale = Field("a scale factor (dimensionless)", float, default=2.0, check=lambda v: v > 0)


class SubTask(Task):
    ConfigClass = SubConfig
    _DefaultName = "sub"

    def run(self, x):
        return Struct(y=x * self.config.scale)


class TopConfig(Config):
    n_iter = Field("iterations", int, default=3, check=lambda v: v > 0)
    tol = Field("tolerance (px)", float, default=1e-4)
    label = Field("an optional label", str, default=None, optional=True)
    method = ChoiceField("how", str, default="drift", allowed={"drift": "ours", "kernel": "K"})
    sub = ConfigurableField("the subtask", target=SubTask)

    def set_defaults(self):
        self.tol = 2e-4


class TopTask(Task):
    ConfigClass = TopConfig
    _DefaultName = "top"

    def __init__(self, **kw):
        super().__init__(**kw)
        self.make_subtask("sub")

    def run(self, x):
        return Struct(out=self.sub.run(x).y + self.config.n_iter)


def test_defaults_and_set_defaults():
    c = TopConfig()
    assert (c.n_iter, c.tol, c.label, c.method) == (3, 2e-4, None, "drift")
    assert c.sub.scale == 2.0


def test_types_are_checked():
    c = TopConfig()
    c.tol = 1  # int accepted for float
    assert isinstance(c.tol, float)
    with pytest.raises(FieldValidationError, match="takes an int"):
        c.n_iter = 2.5
    with pytest.raises(FieldValidationError, match="takes an int"):
        c.n_iter = True
    with pytest.raises(FieldValidationError, match="finite"):
        c.tol = float("nan")
    with pytest.raises(FieldValidationError, match="not one of"):
        c.method = "magic"
    with pytest.raises(FieldValidationError, match="may not be None"):
        c.n_iter = None


def test_unknown_field():
    with pytest.raises(AttributeError, match="no field 'n_iters'"):
        TopConfig(n_iters=3)


def test_validate_runs_checks_and_subconfigs():
    c = TopConfig(n_iter=0)
    with pytest.raises(FieldValidationError, match="n_iter"):
        c.validate()
    c = TopConfig(sub={"scale": -1.0})
    with pytest.raises(FieldValidationError, match="scale"):
        c.validate()


def test_freeze():
    c = TopConfig()
    c.freeze()
    with pytest.raises(FieldValidationError, match="frozen"):
        c.n_iter = 4
    with pytest.raises(FieldValidationError, match="frozen"):
        c.sub.scale = 3.0


def test_task_runs_with_subtask_and_returns_struct():
    t = TopTask(config=TopConfig(n_iter=1, sub={"scale": 3.0}))
    r = t.run(2.0)
    assert isinstance(r, Struct) and r.out == 7.0
    assert t.sub.full_name == "top.sub"
    assert t.config.frozen
    with pytest.raises(TypeError, match="TopConfig"):
        TopTask(config=SubConfig())
    with pytest.raises(FieldValidationError):
        TopTask(config=TopConfig(n_iter=-1))


def test_save_load_round_trip(tmp_path):
    c = TopConfig(n_iter=7, label="x", sub={"scale": 0.5})
    c.save(tmp_path / "c.json")
    assert TopConfig.load(tmp_path / "c.json") == c
    (tmp_path / "c.toml").write_text('n_iter = 9\nmethod = "kernel"\n[sub]\nscale = 4.0\n')
    d = TopConfig.load(tmp_path / "c.toml")
    assert (d.n_iter, d.method, d.sub.scale) == (9, "kernel", 4.0)


def test_load_reports_unreadable_files(tmp_path):
    """A config file in the wrong format names the file and the format."""
    (tmp_path / "c.py").write_text("method = 'kernel'\n")
    with pytest.raises(ValueError, match=r"c\.py: not valid JSON \(name the file \*\.toml"):
        TopConfig.load(tmp_path / "c.py")
    (tmp_path / "c.toml").write_text("n_iter = = 3\n")
    with pytest.raises(ValueError, match=r"c\.toml: not valid TOML"):
        TopConfig.load(tmp_path / "c.toml")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="expected a table.*got list"):
        TopConfig.load(tmp_path / "list.json")
    (tmp_path / "bin.json").write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ValueError, match="bin.json: not valid JSON"):
        TopConfig.load(tmp_path / "bin.json")


def test_struct():
    s = Struct(a=1, b=2)
    assert s.get_dict() == {"a": 1, "b": 2}
