"""Benchmarks: template build, 4k x 4k superposition, flat and star simulations.

Run from the repository root::

    python benchmarks/performance/bench_engine.py [--size 4096]
        [--out benchmarks/performance/bench_engine_results]
                                        [--sections template,superpose,flat,star]

Prints the figures and writes ``<out>.json`` and ``<out>.txt`` (quoted by
``docs/benchmarks.rst``). Timings are wall-clock seconds on this machine;
the machine's core count is recorded with them. With ``--sections`` only
the named sections are run and their lines replace those of the existing
files. The star section also records CPU seconds (``time.process_time``),
which depend much less on other jobs than wall-clock time.
"""

import argparse
import json
import os
import platform
import resource
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import command_line  # noqa: E402

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.utils.io import write_json, write_text  # noqa: E402
from lsst_bfdrift.geometry.superpose import moment_maps  # noqa: E402
from lsst_bfdrift.templates.template import TemplateSettings, build_template, load_default_template  # noqa: E402,E501


def _timed(fn, *a, **k):
    t0 = time.perf_counter()
    out = fn(*a, **k)
    return out, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=4096, help="side of the charge image")
    ap.add_argument("--out", default=os.path.join(HERE, "bench_engine_results"))
    ap.add_argument("--sections", default="template,superpose,flat,star",
                    help="comma-separated subset of template,superpose,flat,star")
    args = ap.parse_args()
    sections = set(args.sections.split(","))
    unknown = sections - {"template", "superpose", "flat", "star"}
    if unknown:
        ap.error(f"unknown sections {sorted(unknown)}")
    rows = {"machine": {"cores": os.cpu_count(), "python": platform.python_version(),
                        "numpy": np.__version__, "platform": platform.platform()}}
    lines = [f"machine: {os.cpu_count()} cores, Python {platform.python_version()}, "
             f"numpy {np.__version__}"]

    if "template" in sections:
        _template_section(rows, lines)
    if "superpose" in sections:
        _superpose_section(rows, lines, args.size)
    if "flat" in sections:
        _flat_section(rows, lines)
    if "star" in sections:
        _star_section(rows, lines)
    _write(args.out, rows, lines, sections)


def _template_section(rows, lines):
    # 1. template build (21 x 21, 8 samples, tol 1e-4 px: the defaults until issue 43),
    #    serial vs 2 processes
    times = {}
    for workers in (1, 2):
        tpl, dt = _timed(build_template, settings=TemplateSettings(edge_samples=8, tol=1e-4,
                                                                   workers=workers))
        times[workers] = dt
        a00 = tpl.summary()["A00"]
    rows["template_build"] = {"seconds_workers1": times[1], "seconds_workers2": times[2],
                              "speedup": times[1] / times[2], "target_seconds": 30.0,
                              "A00": a00}
    lines.append(f"template build 21x21x8, tol 1e-4: {times[1]:.1f} s (1 process), "
                 f"{times[2]:.1f} s (2 processes), ratio {times[1] / times[2]:.2f}x; "
                 f"target <= 30 s")


def _superpose_section(rows, lines, n):
    # 2. superposition of a size x size charge image into moment maps
    rng = np.random.default_rng(7)
    charge = rng.poisson(2e4, (n, n)).astype(np.float64)
    tpl = load_default_template()
    # the Task's default first (8 resampled edge samples, float32 FFTs), then the
    # full 32-sample template in double precision
    _, dtt = _timed(moment_maps, tpl, charge, workers=2, samples=8, dtype=np.float32)
    _, dt1 = _timed(moment_maps, tpl, charge, workers=1)
    maps, dt2 = _timed(moment_maps, tpl, charge, workers=2)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    rows["superpose"] = {"size": n, "seconds_fft_workers1": dt1, "seconds_fft_workers2": dt2,
                         "seconds_task_default": dtt,
                         "pixels_per_second": n * n / dt2, "peak_rss_mb": peak,
                         "image_mb": charge.nbytes / 2**20,
                         "area_sum_minus_npix": float(maps.area.sum() - n * n)}
    lines.append(f"superposition {n}x{n} -> area/centroid/ellipticity maps: Task default "
                 f"(8 resampled samples, float32) {dtt:.1f} s (2 FFT threads); full "
                 f"{tpl.edge_samples}-sample template, float64: {dt1:.1f} s "
                 f"(1 FFT thread), {dt2:.1f} s (2), {n * n / dt2 / 1e6:.2f} Mpix/s, peak RSS "
                 f"{peak:.0f} MB (image {charge.nbytes / 2**20:.0f} MB)")


def _flat_section(rows, lines):
    # 3. paper-scale flat simulation: 1024 images of 16 x 16, 250 steps of 1000 e
    from lsst_bfdrift.simulation.flats import simulate_flats
    tpl = load_default_template()
    tab, dt = _timed(simulate_flats, tpl, n_images=1024, shape=(16, 16), step=1000.0,
                     n_steps=250, seed=1)
    rows["flat_sim"] = {"seconds": dt, "target_seconds": 300.0, "final_mu": float(tab["mu"][-1])}
    lines.append(f"flat simulation 1024 x (16x16) x 250 steps of 1000 e: {dt:.1f} s "
                 f"(target <= 300 s)")


def _star_section(rows, lines):
    # 4. star simulation conversions per second against galsim.SiliconSensor, same
    #    photon count, boundaries updated every 1000 conversions in both (nrecalc),
    #    GalSim with its default OpenMP threads and with 1 thread (ours is serial)
    import galsim

    from lsst_bfdrift.simulation.stars import simulate_star
    itl = import_galsim_sensor("lsst_itl_50_8")
    nphot, every = 500000, 1000
    psf = galsim.Gaussian(fwhm=0.7)
    simulate_star(itl, psf, 2 * every, stamp_size=31, update_every=every, seed=1)  # compile

    def _galsim(threads):
        default = galsim.utilities.get_omp_threads()
        galsim.utilities.set_omp_threads(threads or default)
        sensor = galsim.SiliconSensor("lsst_itl_50_8", rng=galsim.BaseDeviate(3),
                                      nrecalc=every, diffusion_factor=0.0)
        img = galsim.ImageD(31, 31, scale=0.2)
        c0 = time.process_time()
        _, dt = _timed(psf.withFlux(nphot).drawImage, img, method="phot", sensor=sensor,
                       rng=galsim.BaseDeviate(4), n_photons=nphot)
        cpu = time.process_time() - c0
        galsim.utilities.set_omp_threads(default)
        return dt, cpu, threads or default

    dt_gs, cpu_gs, gs_threads = _galsim(None)
    c0 = time.process_time()
    _, dt_ours = _timed(simulate_star, itl, psf, nphot, stamp_size=31, update_every=every,
                        seed=3)
    cpu_ours = time.process_time() - c0
    dt_gs1, cpu_gs1, _ = _galsim(1)
    load = os.getloadavg()[0]
    rows["star_sim"] = {"photons": nphot, "update_every": every,
                        "ours_per_second": nphot / dt_ours, "galsim_per_second": nphot / dt_gs,
                        "galsim_threads": gs_threads,
                        "galsim_1thread_per_second": nphot / dt_gs1,
                        "ratio": dt_gs / dt_ours, "ratio_1thread": dt_gs1 / dt_ours,
                        "ours_cpu_seconds": cpu_ours, "galsim_cpu_seconds": cpu_gs,
                        "galsim_1thread_cpu_seconds": cpu_gs1,
                        "ratio_1thread_cpu": cpu_gs1 / cpu_ours,
                        "target_ratio": 1.0, "load_average_1min": load}
    lines.append(f"star simulation, {nphot} conversions, update every {every} (nrecalc "
                 f"{every}): {nphot / dt_ours / 1e3:.0f} k/s (lsst_bfdrift, serial) vs "
                 f"{nphot / dt_gs / 1e3:.0f} k/s (galsim.SiliconSensor, {gs_threads} OpenMP "
                 f"threads, diffusion off), ratio {dt_gs / dt_ours:.2f}x; vs "
                 f"{nphot / dt_gs1 / 1e3:.0f} k/s (GalSim 1 thread), ratio "
                 f"{dt_gs1 / dt_ours:.2f}x; CPU seconds {cpu_ours:.3f} (ours) vs "
                 f"{cpu_gs1:.3f} (GalSim 1 thread), ratio {cpu_gs1 / cpu_ours:.2f}x, "
                 f"{cpu_gs:.3f} (GalSim {gs_threads} threads); target >= 1.0x; load average "
                 f"{load:.1f}")


_PREFIXES = {"template": "template build", "superpose": "superposition",
             "flat": "flat simulation", "star": "star simulation"}


def _write(out, rows, lines, sections):
    """Write the results, keeping the other sections' lines and rows (and the
    commands that wrote them, before this run's)."""
    commands = [command_line(__file__)]
    if sections != set(_PREFIXES) and os.path.exists(out + ".json"):
        with open(out + ".json") as fh:
            old_rows = json.load(fh)
        old_rows.update(rows)
        rows = old_rows
        with open(out + ".txt") as fh:
            old = fh.read().splitlines()
        commands = [ln[len("# command: "):] for ln in old
                    if ln.startswith("# command: ")] + commands
        new = {k: ln for k, p in _PREFIXES.items() for ln in lines if ln.startswith(p)}
        kept = [lines[0]]
        for k, p in _PREFIXES.items():
            if k in new:
                kept.append(new[k])
            else:
                kept += [ln for ln in old if ln.startswith(p)]
        lines = kept
    text = "\n".join(lines) + "\n"
    print(text, end="")
    rows = {"command": " && ".join(commands), **{k: v for k, v in rows.items() if k != "command"}}
    write_json(out + ".json", rows, indent=2)
    write_text(out + ".txt", "".join(f"# command: {c}\n" for c in commands) + text)


if __name__ == "__main__":
    main()
