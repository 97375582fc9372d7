"""Wall time of ``bfdrift calibrate`` on flats: 7 pairs of 256 x 256 px (issue 46, <= 60 s).

The flats: 7 pairs drawn with GalSim's own pixel areas (``lsst_itl_50_8``,
:func:`~lsst_bfdrift.simulation.flats.simulate_flat_pairs`, engine
``galsim``, 20 fill steps, gain 1.5 e/ADU, 1e4 to 8e4 e), written as FITS
with ``EXPTIME`` (:func:`~lsst_bfdrift.simulation.flats.write_flat_pairs`)
into ``--flats-dir`` (reused when present). Timed, ``--repeat`` times,
alternated, medians:

* the covariance measurement of the route
  (:func:`~lsst_bfdrift.ptc.inputs.read_calibration_input`, lags to 8: FITS
  reading, checks, FFT covariances), and of the FFT estimator alone
  (:func:`~lsst_bfdrift.ptc.covariances.pair_covariances`) on these pairs
  and on one 2048 x 2048 Poisson pair, in s per megapixel of flat;
* the full covariance model fit
  (:func:`~lsst_bfdrift.ptc.full_model.fit_covariance_model`, b_ij fixed then
  free) with the exact Jacobian, and once with the former finite-difference
  Jacobian (``jac='2-point'``), with the differences of gain and a_ij;
* the whole command, ``bfdrift calibrate FLATS --out T.fits`` in a fresh
  process, its progress lines counted (numba's cache is assumed warm: the
  first run of a new checkout also compiles the drift kernels, about 30 s
  on a loaded machine).

Prints the machine and the load average and writes
``benchmarks/performance/calibrate_flats_speed_results.txt`` / ``.json``::

    python benchmarks/performance/calibrate_flats_speed.py [--repeat 3]
"""

import argparse
import glob
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402
ROOT = os.path.dirname(os.path.dirname(HERE))

from lsst_bfdrift.ptc.covariances import pair_covariances, read_flat_pair  # noqa: E402
from lsst_bfdrift.ptc.full_model import fit_covariance_model  # noqa: E402
from lsst_bfdrift.ptc.inputs import read_calibration_input  # noqa: E402
from lsst_bfdrift.simulation.flats import simulate_flat_pairs, write_flat_pairs  # noqa: E402

#: Mean signals (e) of the 7 pairs.
LEVELS = np.linspace(1e4, 8e4, 7)
SHAPE = (256, 256)
MAX_LAG = 8


def flat_files(directory):
    """The 14 FITS flats, drawn once (about a minute) and reused."""
    files = sorted(glob.glob(os.path.join(directory, "flat_*.fits")))
    if len(files) == 2 * LEVELS.size:
        return files
    os.makedirs(directory, exist_ok=True)
    print(f"drawing {LEVELS.size} GalSim flat pairs of {SHAPE[0]} x {SHAPE[1]} px ...", flush=True)
    pairs = simulate_flat_pairs("lsst_itl_50_8", LEVELS, engine="galsim", shape=SHAPE,
                                n_steps=20, gain=1.5, seed=46)
    return write_flat_pairs(pairs, LEVELS, directory, gain=1.5, overwrite=True)


def load():
    return os.getloadavg()[0]


def timed(fn, cpu=None):
    """(wall seconds, result) of ``fn()``; its CPU seconds appended to ``cpu``."""
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    if cpu is not None:
        cpu.append(time.process_time() - c)
    return time.perf_counter() - t, out


def run_cli(files, out):
    """``bfdrift calibrate`` in a fresh process: (seconds, progress lines, the
    electrostatic calibration's own seconds from its ``--json`` summary, CPU
    seconds of the process)."""
    cmd = [sys.executable, "-c", "import sys; from lsst_bfdrift.cli.main import main; "
           "sys.exit(main(sys.argv[1:]))", "calibrate", *files, "--out", out, "--overwrite",
           "--json"]
    t = time.perf_counter()
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=ROOT))
    dt = time.perf_counter() - t
    ru2 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru2.ru_utime - ru.ru_utime) + (ru2.ru_stime - ru.ru_stime)
    if p.returncode:
        raise RuntimeError(f"bfdrift calibrate failed ({p.returncode}): {p.stderr[-2000:]}")
    lines = [x for x in p.stderr.replace("\r", "\n").splitlines() if x.strip()]
    return dt, len(lines), json.loads(p.stdout)["seconds"]["total"], cpu


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--flats-dir", default=os.path.join(tempfile.gettempdir(),
                                                       "calibrate_flats_speed_flats"))
    ap.add_argument("--skip-finite-differences", action="store_true",
                    help="leave out the former finite-difference fit (2-3 min)")
    ap.add_argument("--out", default=os.path.join(HERE, "calibrate_flats_speed_results"))
    args = ap.parse_args(argv)
    machine = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
               f"Python {platform.python_version()}")
    files = flat_files(args.flats_dir)
    pairs = [read_flat_pair(files[2 * k], files[2 * k + 1]) for k in range(LEVELS.size)]
    mpx_route = sum(a.size + b.size for a, b in pairs) / 1e6
    rng = np.random.default_rng(46)
    big = [rng.poisson(5e4, (2048, 2048)).astype(float) for _ in range(2)]
    mpx_big = 2 * big[0].size / 1e6
    data = read_calibration_input(files, max_lag=MAX_LAG)  # warm: imports, caches
    mu, cov, npix = np.asarray(data.mu, float), np.asarray(data.cov, float), data.npix
    runs = {k: [] for k in ("read", "fft_256", "fft_2048", "fit_exact", "cli")}
    cpu_fit = []
    cpu = {k: [] for k in ("read", "fft_256", "fft_2048")}
    loads = [load()]
    fit_exact = None
    tpl = os.path.join(tempfile.gettempdir(), "calibrate_flats_speed_template.fits")
    for r in range(args.repeat):
        runs["read"].append(timed(lambda: read_calibration_input(files, max_lag=MAX_LAG),
                                  cpu["read"])[0])
        runs["fft_256"].append(timed(lambda: [pair_covariances(a, b, max_lag=MAX_LAG)
                                              for a, b in pairs], cpu["fft_256"])[0])
        runs["fft_2048"].append(timed(lambda: pair_covariances(*big, max_lag=MAX_LAG),
                                      cpu["fft_2048"])[0])
        dt, fit_exact = timed(lambda: fit_covariance_model(mu, cov, npix=npix), cpu_fit)
        runs["fit_exact"].append(dt)
        runs["cli"].append(run_cli(files, tpl))
        loads.append(load())
        print(f"run {r + 1}: read {runs['read'][-1]:.2f} s, fit {dt:.1f} s, calibrate "
              f"{runs['cli'][-1][0]:.1f} s (load {loads[-1]:.1f})", flush=True)
    n_exact = [0]
    fit_covariance_model(mu, cov, npix=npix,
                         progress=lambda: n_exact.__setitem__(0, n_exact[0] + 1))
    fd = None
    if not args.skip_finite_differences:
        n_fd, cpu_fd = [0], []
        t_fd, fd = timed(lambda: fit_covariance_model(
            mu, cov, npix=npix, jac="2-point",
            progress=lambda: n_fd.__setitem__(0, n_fd[0] + 1)), cpu_fd)
        loads.append(load())
    med = {k: statistics.median(v) for k, v in runs.items() if k != "cli"}
    mcpu = {k: statistics.median(v) for k, v in cpu.items()}
    cli_s = statistics.median(x[0] for x in runs["cli"])
    cli_lines = statistics.median(x[1] for x in runs["cli"])
    cli_model = statistics.median(x[2] for x in runs["cli"])
    cli_cpu = statistics.median(x[3] for x in runs["cli"])
    a = fit_exact["a"]
    lines = [f"bfdrift calibrate on {LEVELS.size} pairs of {SHAPE[0]} x {SHAPE[1]} px GalSim ITL "
             f"flats (lags to {MAX_LAG}), {machine}; {args.repeat} runs, medians (target <= 60 s)",
             f"  whole command (fresh process)        {cli_s:6.1f} s, {cli_lines:.0f} progress "
             "lines on stderr",
             f"    CPU time of the command            {cli_cpu:6.1f} s (both cores; wall time on "
             "an idle 2-core machine lies between half of it and all of it)",
             f"    of which the electrostatic model   {cli_model:6.1f} s wall (calibrate(): the "
             "a-matrix route's own cost, after the flats' covariances and their fit)",
             f"  covariance measurement, route        {med['read']:6.2f} s = "
             f"{med['read'] / mpx_route:.3f} s/Mpx, CPU {mcpu['read'] / mpx_route:.3f} s/Mpx "
             f"({mpx_route:.2f} Mpx of flats: FITS reading, checks, FFT)",
             f"  FFT covariances alone, 256^2 pairs   {med['fft_256']:6.2f} s = "
             f"{med['fft_256'] / mpx_route:.3f} s/Mpx, CPU "
             f"{mcpu['fft_256'] / mpx_route:.3f} s/Mpx",
             f"  FFT covariances alone, 2048^2 pair   {med['fft_2048']:6.2f} s = "
             f"{med['fft_2048'] / mpx_big:.3f} s/Mpx, CPU {mcpu['fft_2048'] / mpx_big:.3f} s/Mpx",
             f"  covariance model fit, exact Jacobian {med['fit_exact']:6.1f} s, "
             f"{statistics.median(cpu_fit):.1f} s CPU ({n_exact[0]} model and Jacobian "
             "evaluations; b_ij "
             f"{'fitted' if fit_exact['b_fitted'] else 'fixed to 0'})"]
    out = {"machine": machine, "repeat": args.repeat, "levels_e": LEVELS.tolist(),
           "shape": SHAPE, "max_lag": MAX_LAG, "median_seconds": med,
           "cli_median_seconds": cli_s, "cli_progress_lines": cli_lines,
           "cli_electrostatic_median_seconds": cli_model, "cli_cpu_median_seconds": cli_cpu,
           "s_per_mpx": {"route": med["read"] / mpx_route, "fft_256": med["fft_256"] / mpx_route,
                         "fft_2048": med["fft_2048"] / mpx_big},
           "cpu_s_per_mpx": {"route": mcpu["read"] / mpx_route,
                             "fft_256": mcpu["fft_256"] / mpx_route,
                             "fft_2048": mcpu["fft_2048"] / mpx_big},
           "evaluations_exact": n_exact[0], "runs": runs, "cpu_fit_exact": cpu_fit,
           "exact": {"gain": fit_exact["gain"], "a": a.tolist(), "chi2": fit_exact["chi2"],
                     "b_test": fit_exact["b_test"]}}
    if fd is not None:
        rel = np.abs(fit_exact["a"] - fd["a"]) / np.abs(fd["a"])
        sig = np.abs(fit_exact["a"] - fd["a"]) / fd["a_err"]
        lines.append(f"  former finite-difference fit         {t_fd:6.1f} s, {cpu_fd[0]:.1f} s "
                     f"CPU ({n_fd[0]} model evaluations): {t_fd / med['fit_exact']:.0f}x the "
                     "exact one's wall time")
        lines.append(f"  exact minus former: gain {abs(fit_exact['gain'] / fd['gain'] - 1):.1e}, "
                     f"a00 {rel[0, 0]:.1e}, a01 {rel[0, 1]:.1e}, a10 {rel[1, 0]:.1e} relative; "
                     f"all a_ij within {sig.max():.1e} of their errors; chi2 "
                     f"{fit_exact['chi2']:.4f} against {fd['chi2']:.4f}")
        out["finite_differences"] = {"seconds": t_fd, "cpu_seconds": cpu_fd[0],
                                     "evaluations": n_fd[0],
                                     "gain": fd["gain"], "a": fd["a"].tolist(),
                                     "chi2": fd["chi2"], "b_test": fd["b_test"],
                                     "max_rel_a00_a01_a10": float(max(rel[0, 0], rel[0, 1],
                                                                      rel[1, 0])),
                                     "max_diff_over_error": float(sig.max())}
    lines.append(f"  load average (1 min) during the runs: {min(loads):.1f}-{max(loads):.1f} "
                 "(2 = both cores busy)")
    out["load_average"] = loads
    text = "\n".join(lines)
    print(text)
    write_results(args.out, lines, out, script=__file__, json_default=float, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
