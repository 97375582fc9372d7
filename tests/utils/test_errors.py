"""Tests of the exception hierarchy (lsst_bfdrift.utils.errors)."""

import pytest

import lsst_bfdrift
import lsst_bfdrift.utils
from lsst_bfdrift.utils import errors


def test_every_error_is_a_bfdrift_error_and_its_builtin():
    e = errors
    pairs = [(e.InputError, ValueError), (e.InputTypeError, TypeError),
             (e.InputKeyError, KeyError), (e.InputAttributeError, AttributeError),
             (e.InputFileError, ValueError), (e.InputNotFoundError, FileNotFoundError),
             (e.TemplateFileError, ValueError),
             (e.OutputExistsError, FileExistsError), (e.FitError, ValueError),
             (e.ComputationError, RuntimeError)]
    for cls, builtin in pairs:
        assert issubclass(cls, e.BfdriftError) and issubclass(cls, builtin), cls
        assert getattr(lsst_bfdrift.utils, cls.__name__) is cls  # from the subpackage
    assert lsst_bfdrift.BfdriftError is e.BfdriftError  # the one catch-all at the top
    # config errors are lsst.pex.config's own (a ValueError, exit status 2)
    import lsst.pex.config as pexConfig
    assert e.FieldValidationError is pexConfig.FieldValidationError
    assert issubclass(e.FieldValidationError, ValueError)
    from lsst_bfdrift.cli.main import EXIT_INPUT, exit_code
    assert exit_code(e.FieldValidationError.__new__(e.FieldValidationError)) == EXIT_INPUT


def test_existing_errors_are_re_parented_not_copied():
    from lsst_bfdrift.calibration.fitting import FitError
    from lsst_bfdrift.calibration.tuning import CalibrationError
    from lsst_bfdrift.templates.template import TemplateFileError
    from lsst_bfdrift.utils.config import FieldValidationError
    assert FitError is errors.FitError and issubclass(CalibrationError, errors.BfdriftError)
    assert TemplateFileError is errors.TemplateFileError
    assert issubclass(TemplateFileError, errors.InputFileError)
    assert FieldValidationError is errors.FieldValidationError


def test_input_file_error_names_the_file():
    err = errors.InputFileError("truncated", "/data/x.fits")
    assert err.path == "/data/x.fits" and str(err) == "/data/x.fits: truncated"
    assert str(errors.InputFileError("/data/x.fits is bad", "/data/x.fits")) == \
        "/data/x.fits is bad"
    with pytest.raises(FileNotFoundError, match="y.fits"):
        raise errors.InputNotFoundError("no such file", "y.fits")


def test_key_error_message_is_not_quoted():
    assert str(errors.InputKeyError("unknown column 'a'")) == "unknown column 'a'"


def test_package_raises_its_own_errors():
    """A ValueError the package raises on purpose is an InputError."""
    from lsst_bfdrift.physics.sensor import SensorParameters
    with pytest.raises(errors.InputKeyError, match="bogus"):
        SensorParameters.from_dict({"bogus": 1})
    with pytest.raises(errors.FieldValidationError, match="gain"):  # pex_config's
        lsst_bfdrift.BrighterFatterDriftConfig(gain=-1.0).validate()
