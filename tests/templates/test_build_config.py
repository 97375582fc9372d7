"""Tests of lsst_bfdrift.templates.build_config (the build config on pex_config).

Consistency checks of the config layer against the dataclasses it mirrors and
the JSON files it replaces (no physics is computed here).
"""

import dataclasses
import json

import pytest

from lsst_bfdrift.physics.sensor import SensorParameters
from lsst_bfdrift.templates.build_config import (SensorConfig, TemplateBuildConfig,
                                                 TemplateSettingsConfig, read_build_config)
from lsst_bfdrift.templates.template import TemplateSettings
from lsst_bfdrift.utils.config import FieldValidationError, save_config
from lsst_bfdrift.utils.errors import InputFileError
from lsst_bfdrift.utils.io import data_path


@pytest.mark.parametrize("config_cls, target", [(SensorConfig, SensorParameters),
                                                (TemplateSettingsConfig, TemplateSettings)])
def test_fields_mirror_the_dataclass(config_cls, target):
    """One field per dataclass field, same default, a real doc from the numpydoc section."""
    names = [f.name for f in dataclasses.fields(target)]
    assert list(config_cls._fields) == names
    built = config_cls().build()
    assert built == target()
    for name in names:
        doc = config_cls._fields[name].doc
        assert doc and doc != name and len(doc) > 8, name


def test_round_trip_through_an_override_file(tmp_path):
    params = SensorParameters(v_bss=-55.0, column_overrides=[(3, 2.0), (7, -1.0)],
                              truncations=[(2, 5.0, 1, 0.5)], bloom_stop=4.0)
    settings = TemplateSettings(edge_samples=12, size=15)
    cfg = TemplateBuildConfig()
    cfg.sensor = SensorConfig.from_object(params)
    cfg.template = TemplateSettingsConfig.from_object(settings)
    path = tmp_path / "build.py"
    save_config(cfg, path)
    got = read_build_config(path)
    assert got == (params, settings)


def test_hand_written_override_file(tmp_path):
    path = tmp_path / "mine.py"
    path.write_text("config.sensor.v_bss = -60.0\n"
                    "config.sensor.row_shifts = [5, 0.2]\n"
                    "config.template.edge_samples = 16\n")
    params, settings = read_build_config(path)
    assert params == SensorParameters(v_bss=-60.0, row_shifts=[(5, 0.2)])
    assert settings == TemplateSettings(edge_samples=16)


def test_physical_checks_name_the_field(tmp_path):
    cfg = TemplateBuildConfig()
    cfg.sensor.thickness = -5.0
    with pytest.raises(FieldValidationError, match="sensor.thickness.*must be positive"):
        cfg.validate()
    cfg = TemplateBuildConfig()
    cfg.sensor.column_overrides = [1.0, 2.0, 3.0]
    with pytest.raises(FieldValidationError, match="column_overrides needs groups of 2"):
        cfg.validate()
    (tmp_path / "bad.py").write_text("config.template.size = 20\n")
    with pytest.raises(FieldValidationError, match="odd"):
        read_build_config(tmp_path / "bad.py")
    (tmp_path / "typo.py").write_text("config.sensor.vbss = 1.0\n")
    with pytest.raises(InputFileError, match="typo.py: not a valid TemplateBuildConfig"):
        read_build_config(tmp_path / "typo.py")


def test_bundled_json_reads_as_before(tmp_path):
    """The bundled JSON build config and its pex_config translation give the same objects."""
    path = data_path("default_template_config.json")
    params, settings = read_build_config(path)
    with open(path) as fh:
        data = json.load(fh)
    assert params == SensorParameters.from_dict(data["sensor"])
    assert settings == TemplateSettings.from_dict(data["template"])
    cfg = TemplateBuildConfig()
    cfg.sensor = SensorConfig.from_object(params)
    cfg.template = TemplateSettingsConfig.from_object(settings)
    save_config(cfg, tmp_path / "default.py")
    assert read_build_config(tmp_path / "default.py") == (params, settings)
