"""A camera's worth of CCDs: images per core-second, serially and through dask (issue 46 item 4).

``N`` CCD-sized post-ISR images (``--size`` square, float32, in electrons: a
sky of 1200 e and 400 Gaussian stars of 1e4 to 1.5e6 e, each image its own
seed) are written as FITS files and corrected with the package's default
Task (drift with the geometry maps) by
:func:`lsst_bfdrift.correction.batch.correct_files`, the code behind
``bfdrift correct``: FITS read, correction, maps and FITS write, per file.

(a) ``serial``: ``scheduler=None``, every file in turn in this process (one core).
(b) ``dask``: a ``distributed.LocalCluster`` of 2 worker processes x 1 thread
    started once by this script, given to ``correct_files`` by its scheduler
    address, exactly as a remote cluster would be (two cores).

``NUMBA_NUM_THREADS=1``, ``OMP_NUM_THREADS=1`` (set before any import, the
worker processes inherit them) and the Task's ``workers=1`` (FFT threads): one
core per image. Each worker is warmed first (one small file: numba kernels,
template), then one untimed round of (a) and (b) at full size; then
``--repeat`` rounds, each running (a) and (b) on the same ``N`` files,
alternated. Images per core-second = N / (wall seconds x cores used); on a
machine shared with other jobs that undercounts, so images per CPU-second
(CPU time of this process, which runs the dask scheduler, and of the dask
worker processes) is given too. The visit estimate scales the dask rates
(the route that scales out) to 189 science CCDs and a prompt-processing
budget of ``--budget`` seconds: cores = 189 / (rate x budget), with no I/O
or scheduling beyond what this run contains. Run from the repository root::

    nice -n 10 python benchmarks/performance/camera_scale.py [--size 4096] [--n 10] [--repeat 3]

Prints the table and writes ``benchmarks/performance/camera_scale_results.txt`` / ``.json``.
"""

import os

os.environ["NUMBA_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from astropy.io import fits  # noqa: E402

import bench_task  # noqa: E402  (this folder's bench_task.py: its star field)
from lsst_bfdrift.correction.batch import correct_files  # noqa: E402

__all__ = ["star_field", "main"]

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import command_line, write_results  # noqa: E402
OUT = os.path.join(HERE, "camera_scale")
#: Science CCDs in one LSSTCam visit.
VISIT_CCDS = 189


def star_field(n, n_stars=400, *, seed=1):
    """bench_task.py's sky (1200 e, ``n_stars`` Gaussian stars of 1e4 to 1.5e6 e), float32."""
    return bench_task.star_field(n, n_stars, seed=seed).astype(np.float32)


def write_field(path, img):
    hdr = fits.Header()
    hdr["BUNIT"] = "electron"
    fits.PrimaryHDU(img, header=hdr).writeto(path, overwrite=True)


def _cpu(client):
    """CPU seconds of this process and, with a client, of every dask worker process."""
    total = time.process_time()
    if client is not None:
        total += sum(client.run(time.process_time).values())
    return total


def run_round(pairs, config, scheduler, client=None):
    """Wall and CPU seconds (this process and the workers) of one ``correct_files`` call."""
    c0, t0 = _cpu(client), time.perf_counter()
    res = correct_files(pairs, config, scheduler=scheduler, overwrite=True)
    dt, cpu = time.perf_counter() - t0, _cpu(client) - c0
    bad = [r["error"] for r in res if r["error"]]
    if bad:
        raise RuntimeError(f"{len(bad)} file(s) failed: {bad[0]}")
    return dt, cpu


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=4096)
    ap.add_argument("--n", type=int, default=10, help="images per round")
    ap.add_argument("--repeat", type=int, default=3, help="rounds (serial and dask alternated)")
    ap.add_argument("--workers", type=int, default=2, help="dask worker processes (1 thread each)")
    ap.add_argument("--budget", type=float, default=60.0, help="seconds per visit")
    ap.add_argument("--out", default=OUT)
    args = ap.parse_args()
    from distributed import Client, LocalCluster

    config = {"workers": 1}  # FFT threads; everything else the Task's defaults
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="camera_scale_") as tmp:
        pairs = []
        for k in range(args.n):
            src = os.path.join(tmp, f"ccd{k:03d}.fits")
            write_field(src, star_field(args.size, seed=100 + k))
            pairs.append((src, os.path.join(tmp, f"ccd{k:03d}_bf.fits")))
        warm = [(os.path.join(tmp, f"warm{k}.fits"), os.path.join(tmp, f"warm{k}_bf.fits"))
                for k in range(2 * args.workers)]
        for src, _ in warm:
            write_field(src, star_field(256, 4, seed=7))
        cluster = LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0")
        client = Client(cluster)
        try:
            address = cluster.scheduler_address
            run_round(warm[:1], config, None)
            run_round(warm, config, address)
            # one untimed round at full size: the shape's kernels, FFT plans, disk caches
            t_warm = {"serial": run_round(pairs, config, None)[0],
                      "dask": run_round(pairs, config, address, client)[0]}
            times = {"serial": [], "dask": []}
            cpus = {"serial": [], "dask": []}
            loads = []
            for _ in range(args.repeat):
                for name, sched, cl in (("serial", None, None), ("dask", address, client)):
                    dt, cpu = run_round(pairs, config, sched, cl)
                    times[name].append(dt)
                    cpus[name].append(cpu)
                loads.append(os.getloadavg()[0])
        finally:
            client.close()
            cluster.close()
    load_after = os.getloadavg()
    cores = {"serial": 1, "dask": args.workers}
    rows = {}
    for name in ("serial", "dask"):
        med = float(np.median(times[name]))
        rate = args.n / (med * cores[name])
        cpu = float(np.median(cpus[name]))
        rows[name] = {"cores": cores[name], "seconds": times[name], "median_seconds": med,
                      "seconds_per_image": med / args.n, "images_per_second": args.n / med,
                      "images_per_core_second": rate, "cpu_seconds": cpus[name],
                      "median_cpu_seconds": cpu, "images_per_cpu_second": args.n / cpu,
                      "first_round_seconds": t_warm[name]}
    rate = rows["dask"]["images_per_core_second"]
    need = VISIT_CCDS / (rate * args.budget)
    one_core_visit = VISIT_CCDS / rate
    cpu_rate = rows["dask"]["images_per_cpu_second"]
    need_cpu = VISIT_CCDS / (cpu_rate * args.budget)
    lines = [
        f"{args.n} images of {args.size} x {args.size} float32 (sky 1200 e, 400 stars), "
        "default Task (drift + geometry maps),",
        "FITS read + correct + maps + FITS write per image (correct_files); NUMBA_NUM_THREADS=1, "
        "OMP_NUM_THREADS=1, Task workers=1.",
        f"Machine: {os.cpu_count()} cores ({platform.machine()}, "
        f"Python {platform.python_version()}), shared with other jobs; 1-min load average",
        f"{load_before[0]:.2f} before, {load_after[0]:.2f} after, "
        f"{', '.join(f'{x:.2f}' for x in loads)} after each round (2: this job alone).",
        f"Medians of {args.repeat} rounds, serial and dask alternated, after one untimed round "
        "at full size;",
        "img/core-s = images / (wall s x cores used); img/CPU-s = images / CPU s of this process "
        "and the dask workers.",
        "",
        f"{'route':<36} {'cores':>5} {'s/round':>8} {'s/image':>8} {'img/core-s':>11} "
        f"{'img/CPU-s':>10}",
    ]
    labels = {"serial": "serial, one process",
              "dask": f"dask LocalCluster {args.workers} proc x 1 thread"}
    for name, r in rows.items():
        lines.append(f"{labels[name]:<36} {r['cores']:>5d} {r['median_seconds']:>8.2f} "
                     f"{r['seconds_per_image']:>8.2f} {r['images_per_core_second']:>11.4f} "
                     f"{r['images_per_cpu_second']:>10.4f}")
    eff = rows["dask"]["images_per_core_second"] / rows["serial"]["images_per_core_second"]
    lines += [
        "",
        f"dask per-core efficiency against serial (wall): {eff:.2f}",
        f"A visit ({VISIT_CCDS} CCDs) at the dask wall rate (this shared machine): "
        f"{one_core_visit:.0f} core-seconds;",
        f"  within {args.budget:.0f} s it needs {need:.1f} cores, i.e. {math.ceil(need)} cores "
        f"({math.ceil(need / 2)} machines like this one).",
        f"At the dask CPU rate (cores to itself): {VISIT_CCDS / cpu_rate:.0f} CPU-seconds; within "
        f"{args.budget:.0f} s {need_cpu:.1f} cores, i.e. {math.ceil(need_cpu)} cores.",
        "Scaling out: the same correct_files call with the scheduler's address, or "
        "`bfdrift correct --scheduler tcp://HOST:8786`.",
    ]
    print(f"# command: {command_line(__file__)}\n" + "\n".join(lines))
    write_results(args.out + "_results", lines, {
        "size": args.size, "n_images": args.n, "repeat": args.repeat,
        "dtype": "float32", "n_stars": 400, "dask_workers": args.workers, "threads_per_worker": 1,
        "env": {"NUMBA_NUM_THREADS": 1, "OMP_NUM_THREADS": 1}, "cpu_count": os.cpu_count(),
        "load_average_before": load_before[0], "load_average_after": load_after[0],
        "load_average_rounds": loads, "routes": rows, "dask_efficiency": eff,
        "visit_ccds": VISIT_CCDS, "budget_seconds": args.budget,
        "visit_core_seconds": one_core_visit, "visit_cores": need,
        "visit_cpu_seconds": VISIT_CCDS / cpu_rate, "visit_cores_cpu_rate": need_cpu,
    }, script=__file__, indent=2)


if __name__ == "__main__":
    main()
