"""``bfdrift template``: build, summarise, draw and convert templates (options and
commands).

``template build``, ``template summary``, ``template plot``,
``template export-galsim`` and ``template import-galsim``; the parser of each is
made by :func:`add_template_parser`.
"""

import os

from lsst_bfdrift.cli._common import (add_common_options, check_outputs, emit, library_default,
                                      load_template, print_json, save_and_report, save_plot,
                                      template_input)
from lsst_bfdrift.physics.depth import BANDS
from lsst_bfdrift.templates.bands import (DEPTH_RESPONSES, build_band_templates,
                                          load_templates)
from lsst_bfdrift.templates.build_config import read_build_config
from lsst_bfdrift.templates.galsim_export import export_galsim_sensor
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.templates.template import TemplateSettings, build_template
from lsst_bfdrift.utils.errors import InputError

#: What ``template build --help`` says of the defaults and of the bundled template.
BUILD_DESCRIPTION = (
    "Compute a template from the electrostatic model. With no --config (and no option) it "
    "builds the bundled default template's sensor, SensorParameters(), with its settings, "
    "TemplateSettings(): 21 x 21 pixels around a 1e4 e aggressor, 32 samples per edge, "
    "1e-5 px bisection tolerance (11-13 s on 2 free cores, up to 1.5 minutes on a loaded "
    "machine). The bundled template "
    "is that build with one more step: its pixel areas moved to the measured a_ij of the "
    "LSST ITL sensor it was calibrated to, where the model misses them significantly "
    "(lsst_bfdrift.calibration.tuning.refine_template, lags up to 8; edge samples moved by "
    "at most 5e-5 px). That step changes A01 (1.001529 -> 1.001689) and so ratio_01_10 "
    "(2.39 -> 2.64); A00, A10 and the window leak (2.7 % of the aggressor's area change "
    "falls outside the 21 x 21 window, window_leak in the summary) stay the same. "
    "bfdrift calibrate makes such a refined template from your sensor's data.")

__all__ = ["BUILD_DESCRIPTION", "band_sources", "read_config", "add_template_parser",
           "cmd_template_build",
           "cmd_template_summary", "cmd_template_plot", "cmd_template_export",
           "cmd_template_import"]


def read_config(path):
    """Read a build configuration (:func:`~lsst_bfdrift.templates.build_config.read_build_config`).

    Parameters
    ----------
    path : str or None
        A pex_config override file of ``TemplateBuildConfig``, or JSON/TOML
        with ``sensor`` and ``template`` tables; None: the package defaults.

    Returns
    -------
    params : SensorParameters
    settings : TemplateSettings
    """
    return read_build_config(path)


def cmd_template_build(args):
    """``bfdrift template build``: compute a template from the model, write ``--out``.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    params, settings = read_config(args.config)
    overrides = {k: v for k, v in (("size", args.size), ("aggressor_charge", args.charge),
                                   ("edge_samples", args.samples), ("tol", args.tol),
                                   ("workers", args.workers)) if v is not None}
    if overrides:
        settings = type(settings).from_dict({**settings.to_dict(), **overrides})
    sources = band_sources(args.band, args.wavelength)
    check_outputs(args, [args.config], {"--out": args.out})
    if not sources:
        for opt, val in (("--sed", args.sed), ("--depth-response", args.depth_response),
                         ("--nodes", args.nodes), ("--temperature", args.temperature)):
            if val is not None:
                raise InputError(f"{opt} applies to per-band templates: give --band or "
                                 "--wavelength as well")
        return save_and_report(build_template(params, settings, progress=not args.quiet), args)
    kw = {"depth_response": args.depth_response or "drift"}
    if args.nodes is not None:
        kw["nodes"] = args.nodes
    mb = build_band_templates(params, sources, sed=args.sed, settings=settings,
                              temperature=args.temperature, progress=not args.quiet, **kw)
    mb.save(args.out, overwrite=True)
    if args.json:
        print_json({"out": os.path.abspath(args.out), "bands": list(mb.bands),
                    "summary": mb.summary()})
    else:
        print(f"wrote {args.out} (bands {', '.join(mb.bands)})")
    return 0


def band_sources(bands, wavelengths):
    """The bands and wavelengths of ``--band`` / ``--wavelength``, in order, once each.

    Parameters
    ----------
    bands : list of str or None
        ``--band`` values: band names ('u' .. 'y') or ``'all'`` (the six).
    wavelengths : list of float or None
        ``--wavelength`` values (nm).

    Returns
    -------
    list
        Band names and wavelengths for
        :func:`~lsst_bfdrift.templates.bands.build_band_templates`; empty
        without either option.
    """
    out = []
    for b in bands or ():
        for item in (BANDS if b.strip().lower() == "all" else (b,)):
            if item not in out:
                out.append(item)
    out += [float(w) for w in wavelengths or ()]
    return out


def cmd_template_summary(args):
    """``bfdrift template summary``: the key numbers of a template.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    if args.file is None:
        return emit(load_template(None).summary(), args.json)
    mb = load_templates(args.file)
    if mb.single is not None:
        return emit(mb.single.summary(), args.json)
    return emit(mb.summary(), args.json)


def cmd_template_plot(args):
    """``bfdrift template plot``: boundaries and area map as a PNG.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    # matplotlib: templates.plots imports it; only this command draws
    from lsst_bfdrift.templates.plots import plot_template
    check_outputs(args, [template_input(args.file)], {"--out": args.out})
    tpl = load_template(args.file)
    save_plot(plot_template(tpl, exaggerate=args.exaggerate, half_width=args.half_width),
              args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_template_export(args):
    """``bfdrift template export-galsim``: GalSim sensor files (.cfg, .dat).

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    tpl = load_template(args.file)
    cfg, dat = export_galsim_sensor(tpl, args.prefix, num_vertices=args.vertices,
                                    overwrite=args.overwrite)
    return emit({"cfg": os.path.abspath(cfg), "dat": os.path.abspath(dat),
                 "pixels": f"{tpl.size} x {tpl.size}",
                 "num_vertices": tpl.edge_samples if args.vertices is None else args.vertices,
                 "charge": tpl.charge}, args.json)


def cmd_template_import(args):
    """``bfdrift template import-galsim``: a GalSim sensor file as a template.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_outputs(args, [], {"--out": args.out})
    return save_and_report(import_galsim_sensor(args.name), args)


def add_template_parser(subparsers):
    """Add ``template`` and its actions to the subcommands of ``bfdrift``.

    Options that are None by default leave the value to the build
    configuration (``build``) or to the function they feed
    (:func:`~lsst_bfdrift.templates.plots.plot_template`,
    :func:`~lsst_bfdrift.templates.galsim_export.export_galsim_sensor`).

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``add_subparsers()`` of the top-level parser.

    Returns
    -------
    parser : argparse.ArgumentParser
        The parser of ``template``.
    """
    tp = subparsers.add_parser("template", help="build, inspect and convert templates")
    tsub = tp.add_subparsers(dest="action", required=True)
    b = tsub.add_parser("build", help="compute a template from the model",
                        description=BUILD_DESCRIPTION)
    b.add_argument("--out", required=True, help="output FITS file")
    b.add_argument("--config", help="TemplateBuildConfig: a pex_config override file "
                   "(config.sensor.v_bss = -60.0), or JSON/TOML with 'sensor' and 'template' "
                   "tables")
    dflt = TemplateSettings()
    b.add_argument("--size", type=int, help="neighbourhood side N (odd); default: the "
                   f"config's, else {dflt.size}")
    b.add_argument("--charge", type=float, help="aggressor charge (e); default: the config's, "
                   f"else {dflt.aggressor_charge:g}")
    b.add_argument("--samples", type=int, help="samples per edge; default: the config's, else "
                   f"{dflt.edge_samples} (8 leave ~15 %% of A10's change)")
    b.add_argument("--tol", type=float, help="bisection tolerance (px); default: the config's, "
                   f"else {dflt.tol:g} (1e-4 loses ~20 %% of the area change outside the "
                   "window)")
    b.add_argument("--workers", type=int, help="threads")
    b.add_argument("--band", action="append", metavar="B",
                   help="per-band template: drift lines start at the conversion depths of "
                   f"the band's photons ({', '.join(BANDS)} or 'all'; repeatable); all "
                   "bands and wavelengths go to one multi-band --out file")
    b.add_argument("--wavelength", action="append", type=float, metavar="NM",
                   help="per-wavelength template (nm, within GalSim's silicon absorption "
                   "table 255-1450; repeatable)")
    b.add_argument("--sed", help="with --band: spectrum of the light, 'flat' (photons per "
                   "nm; default), a temperature such as '5800K', or a GalSim SED name "
                   "(e.g. CWW_E_ext)")
    b.add_argument("--depth-response", choices=sorted(DEPTH_RESPONSES),
                   help="with --band: 'drift' (drift lines start at the conversion height; "
                   "default) or 'galsim' (the entrance-window template times GalSim's mean "
                   "tanh(z / 12 um))")
    b.add_argument("--nodes", type=int, help="with --band: conversion heights of the shared "
                   "grid (default 8: 7 builds for all bands)")
    b.add_argument("--temperature", type=float, metavar="K",
                   help="with --band: temperature of the silicon (K) for the absorption "
                   "lengths (default: 300 K, GalSim's table; an LSST sensor runs at about "
                   "173 K, where z and y photons convert deeper)")
    add_common_options(b, "overwrite", "quiet", "json")
    b.set_defaults(func=cmd_template_build)
    s = tsub.add_parser("summary", help="key numbers of a template")
    s.add_argument("file", nargs="?", help="template FITS file (default: bundled)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_template_summary)
    pl = tsub.add_parser("plot", help="draw boundaries and area map")
    pl.add_argument("file", nargs="?", help="template FITS file (default: bundled)")
    pl.add_argument("--out", required=True, help="output PNG")
    pl.add_argument("--exaggerate", type=float, help="displacement factor")
    pl.add_argument("--half-width", type=int, help="pixels shown each side")
    pl.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    pl.set_defaults(func=cmd_template_plot)
    ex = tsub.add_parser("export-galsim", help="write GalSim sensor files (.cfg, .dat) that "
                         "galsim.SiliconSensor(name=PREFIX) reads")
    ex.add_argument("file", nargs="?", help="template FITS file (default: bundled)")
    ex.add_argument("prefix", help="output path without extension")
    ex.add_argument("--vertices", type=int,
                    default=library_default(export_galsim_sensor, "num_vertices"),
                    help="vertices per edge (default: the template's edge samples)")
    add_common_options(ex, "overwrite", "json")
    ex.set_defaults(func=cmd_template_export)
    g = tsub.add_parser("import-galsim", help="convert a GalSim sensor file")
    g.add_argument("name", help="sensor name (e.g. lsst_itl_50_8) or path prefix")
    g.add_argument("--out", required=True, help="output template FITS file")
    add_common_options(g, "overwrite", "json")
    g.set_defaults(func=cmd_template_import)
    return tp
