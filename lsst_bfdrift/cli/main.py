"""Command line interface ``bfdrift``.

Subcommands
-----------
``bfdrift template build --out FILE [--config FILE]``
    Compute a template from the electrostatic model (progress bar on stderr).
``bfdrift template summary [FILE] [--json]``
    Key numbers: A00, A01, A10, A11 (px^2, pixel at (di, dj) = (serial,
    parallel) offset), ratio_01_10 = dlnA01/dlnA10, area_sum_error (sum of
    all areas minus N^2), window_leak (the fraction of the aggressor's area
    change outside the window), aggressor charge.
``bfdrift template plot [FILE] --out PNG``
    Distorted boundaries (exaggerated) and the area map.
``bfdrift template import-galsim NAME --out FILE``
    Convert a GalSim sensor file (e.g. lsst_itl_50_8) to a template file.
``bfdrift ptc FILES...|DIR [--max-lag L] [--json]``
    Photon transfer analysis (Astier et al. 2019): either one two-column text
    file (mean ADU, variance ADU^2; exponential C00 fit: gain, a00) or FITS
    flats paired by EXPTIME as ``calibrate`` reads them (covariances by FFT,
    full model: gain and a_ij; the pairs used and dropped are listed).
``bfdrift flat-sim [--template FILE] [--n-images N] [--steps K] ... [--json]``
    Flat-field simulation with moving boundaries: per-step covariances by the
    paper's all-pairs estimator and LSST's per-pair estimator.
``bfdrift star-sim [--psf gaussian|moffat|kolmogorov] [--fwhm F] [--flux N] ... [--json]``
    Star simulation with GalSim photons and moving boundaries: per-step
    central counts, size, ellipticity and orientation with and without BF.
``bfdrift correct IN.fits OUT.fits [--config FILE] [--method M] [--json]``
    BrighterFatterDriftTask on a FITS image; several inputs with
    ``--out-dir`` (in turn, or on a dask cluster with ``--scheduler local`` or
    ``--scheduler ADDRESS``; progress bar; a failed file is reported and the
    others go on).
``bfdrift validate-stars [--n-stars N] [--psf moffat|kolmogorov] [--json]``
    Sky-like stars drawn by galsim.SiliconSensor (paired BF-free twins):
    size and ellipticity slopes against flux for uncorrected, coulton18,
    astier23 and drift, with errors. Defaults: the sensor's template imported
    with ``--match transfers``, about 1000 GalSim boundary updates per
    exposure (``--updates 1000 --min-nrecalc 100``; converged, see
    ``benchmarks/correction/probe_validation_cadence_results.txt``).
``bfdrift reproduce [--json] [--out DIR] [--quick]``
    The paper's numbers next to the calibrated model's (A00..A11, ratio,
    radial slopes, neighbour recovery, fall-off), the V_BSS ratio scan, and
    figures in DIR.
``bfdrift validate-sky IMAGE.fits [--json] [--plot PNG] [--gain G] [--route R]``
    Star catalog of a sky image (photutils, adaptive moments) and robust
    size- and ellipticity-flux slopes at fixed position, before and after
    the catalog-level and/or pixel-level BF correction, with a verdict
    (``residual_bf_detected``) and optional figures.
``bfdrift diagnose INPUT [--json] [--report DIR] [--basis FILE] [--no-template-change]``
    Where the electrostatic model is wrong and which effect explains it:
    INPUT is an a_ij table, a PTC text file or a directory of flat pairs;
    chi2/dof, rms and largest residual lags before and after each added
    effect, and what an added effect changes in the calibrated template and
    in star corrections (see ``docs/calibration.rst``).
``bfdrift spots SPOT_IMAGE... [--json] [--plot PNG] [--template FILE | --galsim-sensor NAME]``
    Spot-projector series: the spots found once on the sum of the images,
    measured in every image with one fixed Gaussian weight, and the slopes
    of sigma_x, sigma_y, ln T, e1 and e2 against flux with errors from the
    image-to-image and spot-to-spot scatter; with a template, the slopes it
    predicts (drift forward model) against the measured ones.
``bfdrift spot-plan CALIBRATION_JSON SPOT_IMAGE... [--goal-e1 PCT...] [--sigma S...] [--json]``
    How many spots (and spot images) state the corrected e1 and size slopes
    to goal precisions, from the stated precision of a ``calibrate --spots``
    fit, for the fitted series' design and for other spot sizes.
``bfdrift spot-sim OUTDIR [--sensor NAME] [--grid NX NY] [--sigma S] [--twin] [--json]``
    Spot-grid series drawn by galsim.SiliconSensor, one FITS file per
    exposure time (EXPTIME, BUNIT), optionally with BF-free twins.
``bfdrift butler-put REPO FILES... --run RUN --instrument NAME [--data-id ID ...]``
    FITS exposures put into a run collection of a Butler repository (made
    with the package's seed config) as the pipeline's input, with their data
    IDs, for ``pipetask run -i RUN``.
``bfdrift maps [IMAGE] [--template FILE] [--out FILE] [--plot PNG] [--json]``
    Final pixel geometry (area, centroid shift, ellipticity maps) of an image
    in electrons; with no IMAGE, the bundled sample star. This is the quick
    start's main job.

Build config files are pex_config override files of
:class:`~lsst_bfdrift.templates.build_config.TemplateBuildConfig`, or JSON/TOML
with up to two tables: ``sensor`` (keys of
:class:`~lsst_bfdrift.physics.sensor.SensorParameters`) and ``template`` (keys of
:class:`~lsst_bfdrift.templates.template.TemplateSettings`). Unknown keys are errors.

Each subcommand's options and code are in one module: ``template`` in
:mod:`~lsst_bfdrift.cli.template_commands`; ``correct`` and ``maps`` in
:mod:`~lsst_bfdrift.cli.image_commands`; ``flat-sim``, ``star-sim`` and
``spot-sim`` in :mod:`~lsst_bfdrift.cli.simulation_commands`; ``spots`` and ``spot-plan`` in
:mod:`~lsst_bfdrift.cli.spot_commands`; ``calibrate``, ``ptc`` and
``diagnose`` in :mod:`~lsst_bfdrift.cli.calibration_commands`;
``validate-stars``, ``validate-sky`` and ``reproduce`` in
:mod:`~lsst_bfdrift.cli.validation_commands`; ``butler-put`` in
:mod:`~lsst_bfdrift.cli.butler_commands`. An option's default is that of
the config field or function it feeds, read from there.
"""

import argparse
import re
import sys

from lsst_bfdrift.cli._common import remove_stale_outputs, sigterm_raises
from lsst_bfdrift.cli.butler_commands import add_butler_put_parser
from lsst_bfdrift.cli.calibration_commands import (add_calibrate_parser, add_diagnose_parser,
                                                   add_ptc_parser)
from lsst_bfdrift.cli.image_commands import (add_correct_parser, add_maps_parser,
                                             sample_image_path)
from lsst_bfdrift.cli.simulation_commands import (add_flat_sim_parser, add_spot_sim_parser,
                                                  add_star_sim_parser)
from lsst_bfdrift.cli.spot_commands import add_spot_plan_parser, add_spots_parser
from lsst_bfdrift.cli.template_commands import add_template_parser, read_config
from lsst_bfdrift.cli.validation_commands import (add_reproduce_parser, add_validate_sky_parser,
                                                  add_validate_stars_parser)
from lsst_bfdrift.images.exposure import read_image
from lsst_bfdrift.simulation.stars import make_psf
from lsst_bfdrift.utils.errors import (BfdriftError, ComputationError, FieldValidationError,
                                       FitError, InputError)
from lsst_bfdrift.utils import version

__all__ = ["main", "build_parser", "exit_code", "EXIT_OK", "EXIT_OTHER", "EXIT_INPUT",
           "EXIT_EXISTS", "EXIT_FIT", "DefaultsHelpFormatter", "show_defaults", "COMMON_HELP",
           "read_config", "sample_image_path", "make_psf", "read_image"]


def build_parser():
    """The argparse parser of ``bfdrift``: one subparser per command, each made
    by the ``add_*_parser`` function of its module.

    Returns
    -------
    parser : argparse.ArgumentParser
    """
    p = argparse.ArgumentParser(prog="bfdrift", description="Electrostatic brighter-fatter "
                                "model (Rasmussen 2015): templates and pixel-geometry maps.")
    p.add_argument("--version", action="version", version=f"bfdrift {version.__version__}",
                   help="print the package version and exit")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (add_template_parser, add_calibrate_parser, add_ptc_parser, add_flat_sim_parser,
                add_star_sim_parser, add_correct_parser, add_validate_stars_parser,
                add_reproduce_parser, add_validate_sky_parser, add_diagnose_parser,
                add_maps_parser, add_spots_parser, add_spot_plan_parser, add_spot_sim_parser,
                add_butler_put_parser):
        add(sub)
    show_defaults(p)
    return p


#: Help of the flags common to many commands, when a command gives none.
COMMON_HELP = {"--json": "print the result as JSON on stdout", "--seed": "random seed",
               "--quiet": "no progress bar",
               "--overwrite": "replace existing output files (never an input)"}

#: What argparse appends to a help to show the default.
_DEFAULT_SUFFIX = " (default: %(default)s)"
#: A help that already speaks of the default ("default: the config's", "default on").
_STATES_DEFAULT = re.compile(r"\bdefault\b", re.IGNORECASE)


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help with each option's default, once.

    ``" (default: X)"`` is appended only when the help does not speak of the
    default already (``--free``: "default: chosen by the data"; a
    ``BooleanOptionalAction``, which appends it itself) and when the default
    means something: an option that is None unless given shows none.
    """

    def _get_help_string(self, action):
        text = action.help or ""
        stem = text[:-len(_DEFAULT_SUFFIX)] if text.endswith(_DEFAULT_SUFFIX) else text
        if "%(default)" in stem or _STATES_DEFAULT.search(stem):
            return stem
        if action.default is None or action.default is argparse.SUPPRESS:
            return stem
        if not action.option_strings and action.nargs not in (argparse.OPTIONAL,
                                                              argparse.ZERO_OR_MORE):
            return stem  # a required positional: no default
        return stem + _DEFAULT_SUFFIX


def show_defaults(parser):
    """Every (sub)command's --help shows each option's default and a line for
    each option (the flags common to many commands get their line here).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The parser, changed in place with its subparsers: their formatter
        becomes :class:`DefaultsHelpFormatter`, and an option without help
        gets that of :data:`COMMON_HELP`.
    """
    parser.formatter_class = DefaultsHelpFormatter
    for action in parser._actions:
        if not action.help and action.option_strings:
            action.help = COMMON_HELP.get(action.option_strings[-1])
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                show_defaults(child)


#: Exit status of ``bfdrift`` for each kind of error (documented in ``docs/cli.rst``):
#: 0 success; 1 a file-system error (permission, disk full, ...) or files that
#: failed in ``correct``; 2 usage, a bad argument or a bad input; 3 an output
#: that exists (without ``--overwrite``) or is one of the inputs; 4 a fit or
#: computation that failed.
EXIT_OK, EXIT_OTHER, EXIT_INPUT, EXIT_EXISTS, EXIT_FIT = 0, 1, 2, 3, 4


def exit_code(exc):
    """Exit status of ``bfdrift`` for the exception ``exc`` (see :data:`EXIT_OK`).

    Parameters
    ----------
    exc : BfdriftError or OSError
        The error that ended the command.

    Returns
    -------
    code : int
        2 for :class:`~lsst_bfdrift.utils.errors.InputError` (and an input
        path that does not exist or is of the wrong kind), 3 for
        :class:`~lsst_bfdrift.utils.errors.OutputExistsError`, 4 for
        :class:`~lsst_bfdrift.utils.errors.FitError` and
        :class:`~lsst_bfdrift.utils.errors.ComputationError`, 1 otherwise.
    """
    if isinstance(exc, FileExistsError):
        return EXIT_EXISTS
    if isinstance(exc, (FitError, ComputationError)):
        return EXIT_FIT
    if isinstance(exc, (InputError, FieldValidationError, FileNotFoundError, IsADirectoryError,
                        NotADirectoryError)):
        return EXIT_INPUT
    return EXIT_OTHER


def main(argv=None):
    """Entry point; returns the exit status (errors: one message on stderr).

    Only the package's errors (:class:`~lsst_bfdrift.utils.errors.BfdriftError`)
    and ``OSError`` are caught, each mapped to one status by :func:`exit_code`;
    anything else is a bug and keeps its traceback.

    Before the command runs, partial files left by killed runs (``.tmp-*``
    files whose process is gone) are removed from the directories it writes
    into, and listed on stderr. SIGTERM ends the command through an exception
    (exit status 143), so that its partial output is removed like on
    Ctrl-C.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    with sigterm_raises():
        try:
            remove_stale_outputs(args)
            return args.func(args)
        except (BfdriftError, FieldValidationError, OSError) as exc:
            print(f"bfdrift: error: {exc}", file=sys.stderr)
            return exit_code(exc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
