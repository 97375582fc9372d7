"""``bfdrift flat-sim``, ``bfdrift star-sim`` and ``bfdrift spot-sim``: simulations
with moving boundaries, and spot-projector series drawn by GalSim (options and
commands).

The options' defaults are those of the functions they feed
(:func:`~lsst_bfdrift.simulation.flats.simulate_flats`,
:func:`~lsst_bfdrift.simulation.stars.simulate_star`,
:func:`~lsst_bfdrift.simulation.spots.simulate_spot_series`), except where a
comment says why not.
"""

import os

from lsst_bfdrift.cli._common import (add_common_options, check_output_dir, check_outputs,
                                      library_default, load_template, print_json, save_plot,
                                      template_input)
from lsst_bfdrift.simulation.flats import simulate_flats, with_responsivity
from lsst_bfdrift.simulation.spots import SPOT_PROFILES, simulate_spot_series, write_spot_series
from lsst_bfdrift.simulation.stars import make_psf, simulate_star
from lsst_bfdrift.utils.io import atomic_output

__all__ = ["add_flat_sim_parser", "add_star_sim_parser", "add_spot_sim_parser", "cmd_flat_sim",
           "cmd_star_sim", "cmd_spot_sim", "CLI_SEED"]

#: Seed of the simulations when ``--seed`` is not given: a run is repeatable
#: by default (the library's ``seed=None`` draws a fresh one each time); the
#: package's usual seed (that of ``validate-stars`` and ``calibrate --stars``).
CLI_SEED = 20151


def cmd_flat_sim(args):
    """``bfdrift flat-sim``: flats with moving boundaries, covariances per step.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_outputs(args, [template_input(args.template)],
                  {"--out": args.out, "--plot": args.plot})
    tpl = load_template(args.template)
    if args.responsivity is not None:
        # same displacements, attributed to the charge giving dlnA00/Q = responsivity
        tpl = with_responsivity(tpl, args.responsivity)
    tab = simulate_flats(tpl, n_images=args.n_images, shape=(args.size, args.size),
                         step=args.step, n_steps=args.steps, max_lag=args.max_lag,
                         seed=args.seed, progress=not args.quiet)
    if args.out:
        with atomic_output(args.out) as tmp:
            tab.write(tmp, format="ascii.ecsv", overwrite=True)
    if args.plot:
        # matplotlib: simulation.plots imports it; only when --plot is given
        from lsst_bfdrift.simulation.plots import plot_flat_simulation
        save_plot(plot_flat_simulation(tab, tpl), args.plot)
    steps = [{"mu": float(r["mu"]),
              **{f"C{i}{j}_paper": float(r["paper"][i, j] * r["mu"]) for i in range(2)
                 for j in range(2)},
              **{f"C{i}{j}_pairs": float(r["pairs"][i, j]) for i in range(2) for j in range(2)},
              **{f"C{i}{j}_pairs_err": float(r["pairs_err"][i, j]) for i in range(2)
                 for j in range(2)}} for r in tab]
    out = {"template_charge": tpl.charge, "n_images": args.n_images,
           "shape": [args.size, args.size], "step": args.step, "steps": steps,
           "units": "covariances in e^2, mean in e"}
    if args.json:
        print_json(out)
    else:
        last = steps[-1]
        print(f"final mean {last['mu']:.1f} e: C00 {last['C00_paper']:.1f}, C01 "
              f"{last['C01_paper']:.2f}, C10 {last['C10_paper']:.2f} e^2 (all pairs)")
    return 0


def cmd_star_sim(args):
    """``bfdrift star-sim``: one star shot photon by photon with moving boundaries.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_outputs(args, [template_input(args.template)],
                  {"--out": args.out, "--plot": args.plot})
    tpl = load_template(args.template)
    psf = make_psf(args.psf, args.fwhm, e=args.e, beta=args.beta)
    hist, final = simulate_star(tpl, psf, args.flux, stamp_size=args.stamp,
                                update_every=args.update_every, pixel_scale=args.pixel_scale,
                                center=(args.dx, args.dy), seed=args.seed,
                                progress=not args.quiet)
    if args.out:
        with atomic_output(args.out) as tmp:
            hist.write(tmp, format="ascii.ecsv", overwrite=True)
    if args.plot:
        # matplotlib: simulation.plots imports it; only when --plot is given
        from lsst_bfdrift.simulation.plots import plot_star_history
        run = (f"star-sim: {args.psf} PSF, FWHM {args.fwhm:g}\", {args.flux:.3g} e, "
               f"template {os.path.basename(args.template or 'bundled default')} "
               f"({tpl.charge:.3g} e aggressor)")
        save_plot(plot_star_history(hist, title=run), args.plot)
    last = hist[-1]
    out = {"psf": args.psf, "fwhm_arcsec": args.fwhm, "flux": args.flux,
           "template_charge": tpl.charge, "lost": final["lost"],
           "T_growth": float(last["T"] / last["T_nominal"] - 1),
           "central_counts": float(last["central"]),
           "central_counts_square_pixels": float(final["nominal_image"][args.stamp // 2,
                                                                         args.stamp // 2]),
           "min_area": float(final["maps"].area.min()),
           "steps": [{k: float(r[k]) for k in hist.colnames} for r in hist]}
    if args.json:
        print_json(out)
    else:
        print(f"T grew by {100 * out['T_growth']:.3f} % relative to square pixels; "
              f"central pixel {out['central_counts']:.0f} e "
              f"({out['central_counts_square_pixels']:.0f} with square pixels)")
    return 0


def cmd_spot_sim(args):
    """``bfdrift spot-sim``: a spot-grid series drawn by galsim.SiliconSensor, as FITS files.

    Parameters
    ----------
    args : argparse.Namespace
        The parsed options.

    Returns
    -------
    code : int
        The exit status.
    """
    check_output_dir(args, args.out_dir, "OUTDIR")
    sim = simulate_spot_series(sensor=args.sensor, grid=tuple(args.grid), pitch=args.pitch,
                               sigma=args.sigma, profile=args.profile, n_images=args.n_images,
                               flux_min=args.flux_min, peak_max=args.peak_max,
                               flux_scatter=args.flux_scatter, rate=args.rate,
                               read_noise=args.read_noise, bias=args.bias,
                               background=args.background, full_well=args.full_well,
                               twin=args.twin, updates=args.updates, seed=args.seed,
                               progress=not args.quiet)
    paths = write_spot_series(sim, args.out_dir, gain=args.gain, overwrite=args.overwrite)
    times = sim["exptimes"].value
    levels = sim["levels"].value
    out = {"out_dir": os.path.abspath(args.out_dir), "images": paths["images"],
           "twins": paths["twins"], "truth": paths["truth"], "exptimes": times.tolist(),
           "levels": levels.tolist(), "settings": sim["settings"],
           "units": "EXPTIME in s; levels: mean spot flux (e); images in "
                    + ("electrons" if args.gain is None else f"ADU (GAIN {args.gain:g} e/ADU)")}
    if args.json:
        print_json(out)
    else:
        twins = f" and {len(paths['twins'])} BF-free twins (*_nobf.fits, truth only)" \
            if paths["twins"] else ""
        print(f"wrote {len(paths['images'])} spot images{twins} to {args.out_dir}: "
              f"{len(sim['spots'])} spots of sigma {args.sigma:g} px ({args.profile}), "
              f"{args.sensor}, EXPTIME {times.min():.3g}-{times.max():.3g} s, mean spot flux "
              f"{levels.min():.3g}-{levels.max():.3g} e")
    return 0


def add_flat_sim_parser(subparsers):
    """Add ``flat-sim`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    def default(name):
        return library_default(simulate_flats, name)

    fs = subparsers.add_parser("flat-sim", help="flat-field simulation with moving boundaries")
    fs.add_argument("--template", help="template FITS file (default: bundled)")
    fs.add_argument("--responsivity", type=float,
                    help="rescale the template to this dlnA00 per electron; write it "
                    "as --responsivity=-1e-5 (a leading minus needs the = form)")
    fs.add_argument("--n-images", type=int, default=default("n_images"),
                    help="periodic images simulated")
    # square images: the side of simulate_flats' default shape
    fs.add_argument("--size", type=int, default=default("shape")[0],
                    help="side of each periodic image")
    fs.add_argument("--step", type=float, default=default("step"),
                    help="electrons per pixel per step")
    fs.add_argument("--steps", type=int, default=default("n_steps"),
                    help="exposure steps per image")
    fs.add_argument("--max-lag", type=int, default=default("max_lag"),
                    help="largest covariance lag (px)")
    # not simulate_flats' seed=None: a run is repeatable unless --seed changes it
    fs.add_argument("--seed", type=int, default=CLI_SEED, help="random seed")
    fs.add_argument("--out", help="write the per-step table (ECSV)")
    fs.add_argument("--plot", help="write a PNG of covariances against mean")
    add_common_options(fs, "overwrite", "json", "quiet")
    fs.set_defaults(func=cmd_flat_sim)
    return fs


def add_star_sim_parser(subparsers):
    """Add ``star-sim`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser.

    The PSF options (``--psf``, ``--fwhm``, ``--flux``) have no library
    default; ``--e`` and ``--beta`` differ from
    :func:`~lsst_bfdrift.simulation.stars.make_psf`'s round PSF on purpose
    (see the comments).

    """
    def default(name):
        return library_default(simulate_star, name)

    ss = subparsers.add_parser("star-sim", help="star simulation with moving boundaries")
    ss.add_argument("--template", help="template FITS file (default: bundled)")
    ss.add_argument("--psf", default="gaussian", choices=("gaussian", "moffat", "kolmogorov"),
                    help="PSF profile")
    ss.add_argument("--fwhm", type=float, default=0.6, help="arcsec")
    # not make_psf's round PSF (e=0, beta=0): the demonstration star is the slightly
    # elliptical one of docs/simulations.rst ("Running it")
    ss.add_argument("--e", type=float, default=0.05, help="PSF ellipticity")
    ss.add_argument("--beta", type=float, default=30.0, help="PSF position angle (deg)")
    ss.add_argument("--flux", type=float, default=2e6, help="conversions (e)")
    ss.add_argument("--stamp", type=int, default=default("stamp_size"),
                    help="stamp side (px)")
    ss.add_argument("--update-every", type=int, default=default("update_every"),
                    help="electrons between boundary updates")
    ss.add_argument("--pixel-scale", type=float, default=default("pixel_scale"),
                    help="arcsec per px")
    ss.add_argument("--dx", type=float, default=default("center")[0],
                    help="centre offset (px)")
    ss.add_argument("--dy", type=float, default=default("center")[1],
                    help="centre offset (px)")
    # not simulate_star's seed=None: a run is repeatable unless --seed changes it
    ss.add_argument("--seed", type=int, default=CLI_SEED, help="random seed")
    ss.add_argument("--out", help="write the per-step table (ECSV)")
    ss.add_argument("--plot", help="write a PNG like the paper's Fig. 7")
    add_common_options(ss, "overwrite", "json", "quiet")
    ss.set_defaults(func=cmd_star_sim)
    return ss


def add_spot_sim_parser(subparsers):
    """Add ``spot-sim`` to ``subparsers`` (the ``bfdrift`` subcommands); return its parser."""
    def default(name):
        return library_default(simulate_spot_series, name)

    sp = subparsers.add_parser("spot-sim", help="spot-grid series drawn by galsim.SiliconSensor "
                               "(FITS files with EXPTIME, optional BF-free twins)")
    sp.add_argument("out_dir", metavar="OUTDIR", help="directory of the FITS files")
    sp.add_argument("--sensor", default=default("sensor"),
                    help="GalSim sensor (lsst_itl_50_8, lsst_e2v_50_8, lsst_itl_50_32, ...)")
    sp.add_argument("--grid", type=int, nargs=2, default=list(default("grid")),
                    metavar=("NX", "NY"), help="spots along x and y")
    sp.add_argument("--pitch", type=float, default=default("pitch"), help="spot spacing (px)")
    sp.add_argument("--sigma", type=float, default=default("sigma"), help="spot sigma (px)")
    sp.add_argument("--profile", default=default("profile"), choices=SPOT_PROFILES,
                    help="spot profile (a Moffat has the Gaussian's FWHM)")
    sp.add_argument("--n-images", type=int, default=default("n_images"),
                    help="exposures in the series")
    sp.add_argument("--flux-min", type=float, default=default("flux_min"),
                    help="mean spot flux of the shortest exposure (e)")
    sp.add_argument("--peak-max", type=float, default=default("peak_max"),
                    help="peak pixel of the longest exposure without BF (e)")
    sp.add_argument("--flux-scatter", type=float, default=default("flux_scatter"),
                    help="relative rms of the spots' flux factors")
    sp.add_argument("--rate", type=float, default=default("rate"),
                    help="mean spot flux per second (e/s): EXPTIME = flux / rate")
    sp.add_argument("--read-noise", type=float, default=default("read_noise"),
                    help="read noise (e rms)")
    sp.add_argument("--bias", type=float, default=default("bias"),
                    help="bias pedestal left in the images (e; header BIASLVL)")
    sp.add_argument("--background", type=float, default=default("background"),
                    help="uniform background (e per px)")
    sp.add_argument("--full-well", type=float, default=default("full_well"),
                    help="clip pixels at this level plus the bias (e); header SATURATE")
    sp.add_argument("--gain", type=float,
                    help="write ADU with this GAIN (e/ADU) instead of electrons")
    sp.add_argument("--twin", action="store_true",
                    help="also write BF-free twins (*_nobf.fits: same photons and noise; "
                         "benchmark truth only)")
    sp.add_argument("--updates", type=float, default=default("updates"),
                    help="GalSim boundary updates per spot and exposure")
    sp.add_argument("--seed", type=int, default=default("seed"))
    add_common_options(sp, "overwrite", "json", "quiet")
    sp.set_defaults(func=cmd_spot_sim)
    return sp
