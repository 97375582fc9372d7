"""The defaults of ``bfdrift``'s options come from the library, and --help shows
each once (the architecture issue, CLI share).

An option that feeds a function's keyword or a config field has that
keyword's default, read from the function (never retyped): the tables below
list each such option with its source, and a test fails when a default
differs from its source's or no longer follows it. Where the command
deliberately differs from the library, the table of deliberate differences
says so, and every option with a default must be in one of the tables.
"""

import argparse
import inspect
import re

import pytest

from lsst_bfdrift.calibration.routes import calibrate_route
from lsst_bfdrift.calibration.spot_fit import calibrate_with_spots
from lsst_bfdrift.calibration.spot_plan import SpotDesign
from lsst_bfdrift.calibration.star_fit import calibrate_with_stars
from lsst_bfdrift.calibration.tuning import calibrate
from lsst_bfdrift.catalogs.spot_series import SpotSeries
from lsst_bfdrift.catalogs.spot_slopes import predict_spot_slopes
from lsst_bfdrift.cli.main import build_parser, main
from lsst_bfdrift.correction.batch import correct_files
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig
from lsst_bfdrift.diagnosis.effects_fit import load_input
from lsst_bfdrift.geometry.superpose import moment_maps
from lsst_bfdrift.calibration.band_transfer import calibrated_band_templates
from lsst_bfdrift.ptc.inputs import read_calibration_input
from lsst_bfdrift.simulation.flats import simulate_flats
from lsst_bfdrift.simulation.spots import simulate_spot_series
from lsst_bfdrift.simulation.stars import make_psf, simulate_star
from lsst_bfdrift.templates.galsim_export import export_galsim_sensor
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.validation.sky import validate_sky
from lsst_bfdrift.validation.stars import draw_star_pairs, validate_stars

__all__ = []

#: Required arguments of each command (the options under test are not given).
ARGV = {"validate-sky": ["validate-sky", "img.fits"],
        "calibrate": ["calibrate", "a.txt", "--out", "o.fits"],
        "correct": ["correct", "in.fits", "out.fits"],
        "diagnose": ["diagnose", "a.txt"], "ptc": ["ptc", "a.txt"],
        "maps": ["maps"], "flat-sim": ["flat-sim"], "star-sim": ["star-sim"],
        "validate-stars": ["validate-stars"], "reproduce": ["reproduce"],
        "template build": ["template", "build", "--out", "t.fits"],
        "template summary": ["template", "summary"],
        "template plot": ["template", "plot", "--out", "t.png"],
        "template export-galsim": ["template", "export-galsim", "prefix"],
        "template import-galsim": ["template", "import-galsim", "x", "--out", "t.fits"],
        "spots": ["spots", "a.fits"], "spot-sim": ["spot-sim", "outdir"],
        "spot-plan": ["spot-plan", "c.json", "a.fits"]}


def _same(v):
    return v


def _square(v):
    return (v, v)


#: Options whose default is read from the function they feed:
#: (command, option dest(s), function, keyword, what the command passes for
#: the option's value, another default the option must follow).
SOURCES = [
    ("validate-sky", "gain", validate_sky, "gain", _same, 2.0),
    ("validate-sky", "saturation", validate_sky, "saturation", _same, 1e5),
    ("validate-sky", "route", validate_sky, "route", _same, "pixel"),
    ("validate-sky", "method", validate_sky, "method", _same, "astier23"),
    ("validate-sky", "z_crit", validate_sky, "z_crit", _same, 4.5),
    ("validate-sky", "min_snr", validate_sky, "min_snr", _same, 50.0),
    ("validate-sky", "poly_order", validate_sky, "poly_order", _same, 3),
    ("validate-sky", "n_boot", validate_sky, "n_boot", _same, 99),
    ("calibrate", "max_lag", read_calibration_input, "max_lag", _same, 5),
    ("calibrate", "model", calibrate_route, "model", _same, "astier23"),
    ("calibrate", "free", calibrate, "free", _same, ["xi0"]),
    ("calibrate", "max_chi2_dof", calibrate, "max_chi2_dof", _same, 5.0),
    ("calibrate", "max_evaluations", calibrate, "max_evaluations", _same, 12),
    ("calibrate", "band_nodes", calibrated_band_templates, "nodes", _same, 5),
    ("calibrate", "holdout", calibrate_with_stars, "holdout", _same, "cross"),
    ("calibrate", "gain", calibrate_with_stars, "gain", _same, 1.5),
    ("calibrate", "fit_slopes", calibrate_with_stars, "fitted_slopes", tuple, ("size", "e1")),
    ("calibrate", "size_goal", calibrate_with_stars, "size_goal", _same, 5.0),
    ("calibrate", "spot_split", calibrate_with_spots, "split_by", _same, "images"),
    ("calibrate", "spot_fit_slopes", calibrate_with_spots, "spot_slopes", tuple, ("size", "e1")),
    ("calibrate", "min_spots", calibrate_with_spots, "min_spots", _same, 6),
    ("calibrate", "spot_saturation", calibrate_with_spots, "saturation", _same, 9e4),
    ("correct", "scheduler", correct_files, "scheduler", _same, "local"),
    ("correct", "n_workers", correct_files, "n_workers", _same, 4),
    ("diagnose", "max_lag", load_input, "max_lag", _same, 2),
    ("maps", "samples", moment_maps, "samples", _same, 8),
    ("flat-sim", "n_images", simulate_flats, "n_images", _same, 64),
    ("flat-sim", "size", simulate_flats, "shape", _square, (20, 20)),
    ("flat-sim", "step", simulate_flats, "step", _same, 500.0),
    ("flat-sim", "steps", simulate_flats, "n_steps", _same, 100),
    ("flat-sim", "max_lag", simulate_flats, "max_lag", _same, 2),
    ("star-sim", "stamp", simulate_star, "stamp_size", _same, 41),
    ("star-sim", "update_every", simulate_star, "update_every", _same, 500),
    ("star-sim", "pixel_scale", simulate_star, "pixel_scale", _same, 0.3),
    ("star-sim", ("dx", "dy"), simulate_star, "center", tuple, (0.5, 0.0)),
    ("validate-stars", "psf", draw_star_pairs, "psf", _same, "kolmogorov"),
    ("validate-stars", "sensor", draw_star_pairs, "sensor", _same, "lsst_e2v_50_8"),
    ("validate-stars", "updates", draw_star_pairs, "updates", _same, 300),
    ("validate-stars", "min_nrecalc", draw_star_pairs, "min_nrecalc", _same, 50),
    ("validate-stars", "sky", draw_star_pairs, "sky", _same, 800.0),
    ("validate-stars", "seed", draw_star_pairs, "seed", _same, 7),
    ("template export-galsim", "vertices", export_galsim_sensor, "num_vertices", _same, 12),
    ("spots", "min_snr", SpotSeries, "min_snr", _same, 40.0),
    ("spots", "min_spots", SpotSeries, "min_spots", _same, 9),
    ("spots", "model", predict_spot_slopes, "model", _same, "stamp"),
    ("spot-sim", "sensor", simulate_spot_series, "sensor", _same, "lsst_e2v_50_8"),
    ("spot-sim", "grid", simulate_spot_series, "grid", tuple, (7, 7)),
    ("spot-sim", "pitch", simulate_spot_series, "pitch", _same, 50.0),
    ("spot-sim", "sigma", simulate_spot_series, "sigma", _same, 2.0),
    ("spot-sim", "profile", simulate_spot_series, "profile", _same, "moffat"),
    ("spot-sim", "n_images", simulate_spot_series, "n_images", _same, 12),
    ("spot-sim", "flux_min", simulate_spot_series, "flux_min", _same, 2e4),
    ("spot-sim", "peak_max", simulate_spot_series, "peak_max", _same, 1.2e5),
    ("spot-sim", "flux_scatter", simulate_spot_series, "flux_scatter", _same, 0.1),
    ("spot-sim", "rate", simulate_spot_series, "rate", _same, 1e4),
    ("spot-sim", "read_noise", simulate_spot_series, "read_noise", _same, 7.0),
    ("spot-sim", "bias", simulate_spot_series, "bias", _same, 1000.0),
    ("spot-sim", "background", simulate_spot_series, "background", _same, 5.0),
    ("spot-sim", "updates", simulate_spot_series, "updates", _same, 1000.0),
    ("spot-sim", "seed", simulate_spot_series, "seed", _same, 7),
    ("spot-plan", "read_noise", SpotDesign, "read_noise", _same, 7.0),
    ("spot-plan", "background", SpotDesign, "background", _same, 5.0),
]


def _not(v):
    return not v


def _numerics(v):
    """--model-numerics NAME as calibrate's model_settings (None: the default settings)."""
    from lsst_bfdrift.calibration.fit_model import MODEL_NUMERICS, MODEL_SETTINGS

    return None if MODEL_NUMERICS[v] is MODEL_SETTINGS else MODEL_NUMERICS[v]


#: Options that feed a keyword with the same default but are not read from it:
#: flags (absent = the keyword's default), an option read from another source,
#: a default that would import matplotlib at startup (plot_template's).
ALSO_FEEDS = [
    ("calibrate", "no_refine", calibrate, "refine", _not),
    ("calibrate", "no_parameter_modes", calibrate, "modes", _not),
    ("calibrate", "allow_poor_fit", calibrate, "allow_poor_fit", _same),
    ("calibrate", "model_numerics", calibrate, "model_settings", _numerics),
    ("calibrate", "model_directions_only", calibrate_with_stars, "flats_uncertainty", _not),
    ("calibrate", "spot_correction_bias", calibrate_with_spots, "correction_bias", _same),
    ("correct", "processes", correct_files, "processes", _same),
    ("validate-stars", "sky", validate_stars, "sky", _same),
    ("validate-stars", "sensor", import_galsim_sensor, "name", _same),
    ("template plot", "exaggerate", "lsst_bfdrift.templates.plots:plot_template", "exaggerate",
     _same),
    ("template plot", "half_width", "lsst_bfdrift.templates.plots:plot_template", "half_width",
     _same),
    # read from it (library_default); a bound classmethod takes no __signature__ to patch
    ("spot-plan", "peak_max", SpotDesign.saturating, "peak_max", _same),
]

#: Deliberate differences from the library (the reason is a comment at the
#: option): (command, dest, the command's default, function, keyword).
DELIBERATE = [
    ("flat-sim", "seed", 20151, simulate_flats, "seed"),  # repeatable runs
    ("star-sim", "seed", 20151, simulate_star, "seed"),  # repeatable runs
    ("star-sim", "e", 0.05, make_psf, "e"),  # the demonstration star of the docs
    ("star-sim", "beta", 30.0, make_psf, "beta"),
    ("ptc", "max_lag", 3, read_calibration_input, "max_lag"),  # a00..a11, not calibrate's 8
    ("validate-stars", "match", "transfers", import_galsim_sensor, "match"),  # benchmarks
    ("spots", "match", "transfers", import_galsim_sensor, "match"),  # as validate-stars
]

#: Options with a default and no library keyword behind it: the command's own.
OWN = {("star-sim", "psf"), ("star-sim", "fwhm"), ("star-sim", "flux"),
       ("validate-stars", "n_stars"), ("diagnose", "template_change"),
       ("spot-plan", "goal_e1"), ("spot-plan", "goal_size")}  # spot_plan.PLAN_GOALS


def _resolve(func):
    if isinstance(func, str):  # "module:name", imported when the test runs
        module, name = func.split(":")
        func = getattr(__import__(module, fromlist=[name]), name)
    return func


def _default(func, name):
    return inspect.signature(_resolve(func)).parameters[name].default


def _cli_value(command, dest):
    args = build_parser().parse_args(ARGV[command])
    if isinstance(dest, tuple):
        return tuple(getattr(args, d) for d in dest)
    return getattr(args, dest)


def _row_id(row):
    dest = row[1] if isinstance(row[1], str) else "+".join(row[1])
    return f"{row[0]}--{dest}"


@pytest.mark.parametrize("command, dest, func, name, passed, other", SOURCES,
                         ids=[_row_id(r) for r in SOURCES])
def test_option_default_is_its_source(monkeypatch, command, dest, func, name, passed, other):
    """Each option's default, as the command passes it on, is the keyword's
    default; and it follows the keyword when that changes (it is read, not
    retyped)."""
    default = _default(func, name)
    assert passed(_cli_value(command, dest)) == default
    sig = inspect.signature(func)
    changed = sig.replace(parameters=[p.replace(default=other) if p.name == name else p
                                      for p in sig.parameters.values()])
    monkeypatch.setattr(func, "__signature__", changed, raising=False)
    assert passed(_cli_value(command, dest)) == other != default


@pytest.mark.parametrize("command, dest, func, name, passed", ALSO_FEEDS,
                         ids=[_row_id(r) for r in ALSO_FEEDS])
def test_option_default_equals_the_keyword_it_feeds(command, dest, func, name, passed):
    assert passed(_cli_value(command, dest)) == _default(func, name)


@pytest.mark.parametrize("command, dest, value, func, name", DELIBERATE,
                         ids=[_row_id(r) for r in DELIBERATE])
def test_deliberate_differences(command, dest, value, func, name):
    """The command's own default, documented in docs/cli.rst, and different
    from the library's (otherwise the option belongs in SOURCES)."""
    cli = _cli_value(command, dest)
    assert cli == value and type(cli) is type(value)
    assert cli != _default(func, name)


def test_correct_leaves_the_config_fields_and_quotes_them(capsys):
    """`correct`'s Task options are None: the config's field stays; --help
    quotes the config's defaults, read from BrighterFatterDriftConfig."""
    args = build_parser().parse_args(ARGV["correct"])
    for dest in ("method", "gain", "template", "saturation", "geometry", "blocking_planes",
                 "config"):
        assert getattr(args, dest) is None, dest
    assert args.strict is False  # on_input_warning stays the config's
    cfg = BrighterFatterDriftConfig()
    assert cfg.on_input_warning != "raise"
    with pytest.raises(SystemExit):
        main(["correct", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "{" + ",".join(BrighterFatterDriftConfig.method.allowed) + "}" in out
    assert f"(default: the config's, {cfg.method})" in out
    assert f"compute_geometry, {cfg.compute_geometry}," in out
    assert f"(default: the config's, {','.join(cfg.blocking_mask_planes)})" in out


def test_every_option_with_a_default_has_a_source():
    """An option with a default (not None, not an off flag) is in SOURCES,
    ALSO_FEEDS, DELIBERATE or OWN: a new option's default is checked too."""
    known = {(c, d) for c, dest, *_ in SOURCES + ALSO_FEEDS
             for d in ((dest,) if isinstance(dest, str) else dest)}
    known |= {(c, d) for c, d, *_ in DELIBERATE} | OWN
    missing = []
    for path, parser in _subparsers(build_parser()):
        for action in parser._actions:
            if not action.option_strings or action.dest in ("help", "version") \
                    or any(action.default is x for x in (None, False, argparse.SUPPRESS)):
                continue
            if (" ".join(path), action.dest) not in known:
                missing.append(f"{' '.join(path)} {action.option_strings[-1]}"
                               f" (default {action.default!r})")
    assert missing == [], "options whose default has no source in the tables:\n" + \
        "\n".join(missing)


def _subparsers(parser, path=()):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                yield from _subparsers(child, path + (name,))


#: The " (default: X)" that the formatter appends, at the end of a help.
_APPENDED = re.compile(r" \(default: [^()]*\)$")


def doubled_defaults(parser):
    """Options of ``parser`` whose help states the default twice, or shows a
    meaningless ``(default: None)``."""
    formatter = parser._get_formatter()
    bad = []
    for action in parser._actions:
        if not action.help or action.help is argparse.SUPPRESS:
            continue
        text = formatter._expand_help(action)
        m = _APPENDED.search(text)
        if "(default: None)" in text or \
                (m and re.search(r"\bdefault\b", text[:m.start()], re.IGNORECASE)):
            bad.append(f"{'/'.join(action.option_strings) or action.dest}: {text}")
    return bad


def test_help_shows_each_default_once(capsys):
    """No option's help says its default twice ("(default: chosen by the data
    ...) (default: None)" of `calibrate --free`) or shows "(default: None)"."""
    bad = [f"{' '.join(path)}: {b}" for path, parser in _subparsers(build_parser())
           for b in doubled_defaults(parser)]
    assert bad == [], "\n".join(bad)
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "charge_cloud, charge_variance_parallel) --max-lag MAX_LAG" in out \
        and "(default: None)" not in out
    assert out.count("(default: 8)") == 1


def test_the_check_sees_a_doubled_default():
    """The check has power: argparse's own ArgumentDefaultsHelpFormatter gives
    the doubled text of `calibrate --free` and `diagnose --template-change`."""
    parsers = dict(_subparsers(build_parser()))
    for path, option in ((("calibrate",), "--free"), (("diagnose",), "--template-change"),
                         (("maps",), "--gain")):
        parser = parsers[path]
        parser.formatter_class = argparse.ArgumentDefaultsHelpFormatter
        assert any(b.startswith(option) for b in doubled_defaults(parser)), path
