"""CCDs through BPS with Parsl on one machine: ``bps submit`` timed end to end (issue 46 item 4).

Makes a fresh SQLite Butler repository with the package's seed config in a
temporary directory (or ``--workdir``), writes ``--n`` CCD-sized post-ISR
images (``--size`` square, float32, in electrons: camera_scale.py's field,
a sky of 1200 e and 400 Gaussian stars of 1e4 to 1.5e6 e, each image its
own seed) and puts them into the run ``bf/inputs`` as ``post_isr_image``
of instrument ``BFCam``, exposure 1, detectors 0 to N-1
(:func:`lsst_bfdrift.pipeline.put_exposures`, i.e. ``bfdrift
butler-put``). It writes the submit YAML of docs/pipelines.rst (the
bundled pipeline, ``lsst.ctrl.bps.parsl.sites.Local`` with ``--cores``
cores) and runs ``bps submit`` in a subprocess with
``CTRL_MPEXEC_DIR`` and ``DAF_BUTLER_DIR`` set to this Python's prefix,
``NUMBA_NUM_THREADS=1`` and ``OMP_NUM_THREADS=1``; the Task runs with its
defaults (drift with the geometry maps). Each quantum is its own
``pipetask run-qbb`` process.

Timed: ``bps submit`` from start to exit (quantum graph, the init job,
the quanta, the final job that registers the outputs). From what BPS and
the Parsl plugin leave: the stages BPS times itself (its ``Completed ...:
Took ... seconds`` lines) and, per job, from its log files in the submit
directory, its wall time (the files' creation, just before the plugin
starts the command, to their last change), its start-up (to the first
``--long-log`` line: Python's start and the imports) and the Task's own
time (``Execution of task ... took ... seconds``, Butler read and write
included). CPU seconds (user + system) of every process of the run are
sampled from ``/proc`` every 0.2 s (:class:`CpuSampler`), by kind of job.
CCDs per core-second = N / (total wall s x cores); CCDs per CPU-second =
N / total CPU s, the figure that holds when the cores are not shared. For
comparison, camera_scale_results.json's serial rates (one process, FITS
files, no Butler) are quoted when that file exists.

``--final-cpus N`` adds ``finalJob: requestCpus: N`` to the submit YAML:
the final job's ``butler aggregate-graph -j N`` (BPS's default 16).

Then it checks that the repository holds ``bf_corrected_image`` and
``bf_geometry_maps`` for every data ID in the output collection, and that
their files exist, and fails otherwise. The working directory is deleted at
the end unless ``--keep``. Needs ``lsst-ctrl-bps-parsl`` (see
docs/pipelines.rst for the versions that work). Run from the repository
root::

    OMP_NUM_THREADS=1 nice -n 10 python benchmarks/performance/bps_scale.py \\
        [--n 6] [--size 4096] [--cores 2] [--final-cpus N] [--workdir DIR] [--keep]

Prints the figures and writes ``benchmarks/performance/bps_scale_results.txt`` / ``.json``.
"""

import os

os.environ["NUMBA_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"

import argparse  # noqa: E402
import glob  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from datetime import datetime  # noqa: E402

import numpy as np  # noqa: E402
from astropy.io import fits  # noqa: E402

import bench_task  # noqa: E402  (this folder's bench_task.py: its star field)

__all__ = ["CpuSampler", "check_bps", "write_submit_yaml", "parse_bps_stages", "parse_job_logs",
           "main"]

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import command_line, write_results  # noqa: E402
OUT = os.path.join(HERE, "bps_scale_results")
CAMERA_SCALE_JSON = os.path.join(HERE, "camera_scale_results.json")
INSTRUMENT = "BFCam"
INPUT_RUN = "bf/inputs"
OUTPUT = "bf/bps"
OUTPUT_TYPES = ("bf_corrected_image", "bf_geometry_maps")
PIP = 'pip install lsst-ctrl-bps-parsl "parsl==2025.12.1"'

SUBMIT_YAML = """\
pipelineYaml: "{pipe}"
wmsServiceClass: lsst.ctrl.bps.parsl.ParslService
computeSite: local
site:
  local:
    class: lsst.ctrl.bps.parsl.sites.Local
    cores: {cores}
payload:
  payloadName: bfcam
  butlerConfig: "{repo}"
  inCollection: {inputs}
  dataQuery: "instrument = '{instrument}'"
  output: {output}
"""

#: A ``--long-log`` line's time stamp (``INFO 2026-12-07T12:40:01.123+00:00 ...``).
_STAMP = re.compile(r"^[A-Z]+ (\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d+)?(?:[+-]\d\d:\d\d|Z)?) ")
_TASK_TOOK = re.compile(r"Execution of task '[^']+' on quantum .* took ([0-9.]+) seconds")


def check_bps():
    """Fail with the pip command when ``bps`` or the Parsl plugin is missing."""
    missing = []
    for name in ("lsst.ctrl.bps", "lsst.ctrl.bps.parsl", "parsl", "psutil"):
        try:
            found = importlib.util.find_spec(name) is not None
        except ModuleNotFoundError:  # a parent package is missing
            found = False
        if not found:
            missing.append(name)
    if missing or shutil.which("bps") is None:
        what = ", ".join(missing) if missing else "the `bps` command on PATH"
        raise SystemExit(f"bps_scale.py: {what} not found in this environment "
                         f"({sys.prefix}); install BPS and its Parsl plugin with\n    {PIP}\n"
                         "next to the package's [lsst] extra (docs/pipelines.rst, 'BPS with "
                         "Parsl', says which versions work).")


def write_submit_yaml(path, *, pipe, repo, cores, final_cpus=None):
    """Write docs/pipelines.rst's submit YAML with the pipeline, repository and cores filled in.

    ``final_cpus``, when given, adds ``finalJob: requestCpus:`` (the final
    job's ``butler aggregate-graph -j``; BPS's default is 16).
    """
    text = SUBMIT_YAML.format(pipe=pipe, repo=repo, cores=cores, inputs=INPUT_RUN,
                              instrument=INSTRUMENT, output=OUTPUT)
    if final_cpus is not None:
        text += f"finalJob:\n  requestCpus: {final_cpus}\n"
    with open(path, "w") as fh:
        fh.write(text)


def parse_bps_stages(text):
    """BPS's own timings: ``{"Completed creating quantum graph": 2.3, ...}`` from its output."""
    out = {}
    for line in text.splitlines():
        if "Took" not in line:
            continue
        m = re.search(r"(Completed [^:]+?)\s*:\s*Took ([0-9.]+) seconds", line)
        if m:
            key = m.group(1)
            out[key] = out.get(key, 0.0) + float(m.group(2))
    return out


def _stamps(path):
    """Time stamps (datetime) of the ``--long-log`` lines of one log file."""
    out = []
    with open(path, errors="replace") as fh:
        for line in fh:
            m = _STAMP.match(line)
            if m:
                out.append(datetime.fromisoformat(m.group(1).replace("Z", "+00:00")))
    return out


def _birth(path):
    """A file's creation time (POSIX seconds) from ``stat -c %W``, or None where unknown."""
    try:
        out = subprocess.run(["stat", "-c", "%.9W", path], capture_output=True, text=True,
                             check=True).stdout.strip()
        value = float(out)
    except (OSError, subprocess.CalledProcessError, ValueError):
        return None
    return value if value > 0 else None


def parse_job_logs(submit_dir):
    """Per-job times from the logs the Parsl plugin writes under ``submit_dir/logs``.

    The plugin creates a job's ``.stdout`` and ``.stderr`` just before it
    starts the job's command and the job writes them until it exits, so a
    job runs from the files' creation (``stat %W``) to their last change;
    its ``--long-log`` lines give the first line's time (after Python's
    start and the imports) and the Task's own time.

    Returns
    -------
    dict
        Job name -> ``{"kind", "start", "end", "wall_seconds",
        "startup_seconds", "task_seconds"}`` (``start``/``end`` POSIX
        seconds; ``startup_seconds`` from start to the first log line;
        ``task_seconds`` None for a job that ran no Task; ``start`` the
        first log line, ``startup_seconds`` None, where the file system
        does not record creation times).
    """
    jobs = {}
    for path in sorted(glob.glob(os.path.join(submit_dir, "logs", "**", "*.std*"),
                                 recursive=True)):
        name = os.path.basename(path).rsplit(".", 1)[0]
        job = jobs.setdefault(name, {"stamps": [], "task_seconds": None, "born": [],
                                     "changed": []})
        job["stamps"] += _stamps(path)
        job["born"].append(_birth(path))
        job["changed"].append(os.stat(path).st_mtime)
        with open(path, errors="replace") as fh:
            took = [float(m.group(1)) for m in map(_TASK_TOOK.search, fh) if m]
        if took:
            job["task_seconds"] = sum(took)
    out = {}
    for name, job in jobs.items():
        if not job["stamps"]:
            continue
        first = min(job["stamps"]).timestamp()
        born = None if None in job["born"] else min(job["born"])
        t0 = first if born is None else born
        t1 = max(max(job["stamps"]).timestamp(), max(job["changed"]))
        kind = ("quantum" if job["task_seconds"] is not None else
                "init" if "init" in name.lower() else
                "final" if "final" in name.lower() else "other")
        out[name] = {"kind": kind, "start": t0, "end": t1, "wall_seconds": t1 - t0,
                     "startup_seconds": None if born is None else first - born,
                     "task_seconds": job["task_seconds"]}
    return out


class CpuSampler:
    """CPU seconds of every process of a run, sampled from a thread.

    Parsl's local provider starts its worker pool in the background, so its
    processes leave the process tree of ``bps submit`` and
    ``RUSAGE_CHILDREN`` misses them. Every ``interval`` seconds this reads
    the CPU time (user + system) of each process whose command line names
    ``marker`` (the working directory: the worker pool, each job's
    ``pipetask``/``butler``), of ``root`` (the ``bps`` process) and of all
    their descendants; each process counts with its last reading, so up to
    ``interval`` of a process's CPU time can be missed.
    """

    def __init__(self, marker, root, *, interval=0.2):
        import threading

        import psutil  # a dependency of parsl

        self._psutil = psutil
        self.marker, self.root, self.interval = marker, root, interval
        self.seen = {}  # (pid, create_time) -> [cpu seconds, kind]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def _kind(cmdline):
        text = " ".join(cmdline)
        if "run-qbb" in text:
            m = re.search(r"--qgraph-node-id\s+(\S+)", text)
            return "quantum:" + (m.group(1) if m else "?")
        return ("init" if "pre-exec-init-qbb" in text
                else "final" if "aggregate-graph" in text else
                "qgraph" if " qgraph " in text else
                "parsl workers" if "process_worker_pool" in text else None)

    def _sample(self):
        roots = []
        try:
            roots.append((self._psutil.Process(self.root), "bps"))
        except self._psutil.Error:
            pass
        for proc in self._psutil.process_iter(["cmdline"]):
            cmd = proc.info["cmdline"] or []
            if proc.pid != self.root and any(self.marker in c for c in cmd):
                roots.append((proc, self._kind(cmd) or "other"))
        for proc, root_kind in roots:
            try:
                family = [proc] + proc.children(recursive=True)
            except self._psutil.Error:
                continue
            for member in family:
                try:
                    with member.oneshot():
                        key = (member.pid, member.create_time())
                        t = member.cpu_times()
                        kind = self._kind(member.cmdline()) or root_kind
                except self._psutil.Error:
                    continue
                entry = self.seen.setdefault(key, [0.0, kind])
                entry[0] = max(entry[0], t.user + t.system)
                if entry[1] in ("bps", "other"):  # a process's own command says more
                    entry[1] = kind

    def _run(self):
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.interval)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    def totals(self):
        """CPU seconds by kind of process, ``total`` for all of them."""
        out = {}
        for cpu, kind in self.seen.values():
            kind = kind.split(":")[0]
            out[kind] = out.get(kind, 0.0) + cpu
        out["total"] = sum(cpu for cpu, _ in self.seen.values())
        return out

    def quanta(self):
        """CPU seconds of each quantum's processes (``pipetask run-qbb`` and its shell)."""
        out = {}
        for cpu, kind in self.seen.values():
            if kind.startswith("quantum:"):
                out[kind] = out.get(kind, 0.0) + cpu
        return sorted(out.values())


def write_field(path, img):
    hdr = fits.Header()
    hdr["BUNIT"] = "electron"
    fits.PrimaryHDU(img, header=hdr).writeto(path, overwrite=True)


def check_outputs(repo, n):
    """Every data ID has both outputs in the output collection, and their files exist."""
    from lsst.daf.butler import Butler

    butler = Butler.from_config(repo)
    runs = [c for c in butler.registry.queryCollections(f"{OUTPUT}/*")]
    if not runs:
        raise SystemExit(f"bps_scale.py: no output run under {OUTPUT}/ in {repo}: "
                         "bps submit wrote nothing")
    found = {}
    for dtype in OUTPUT_TYPES:
        refs = list(butler.registry.queryDatasets(dtype, collections=runs,
                                                  instrument=INSTRUMENT))
        dets = sorted(r.dataId["detector"] for r in refs)
        missing = [r for r in refs if not butler.getURI(r).exists()]
        if dets != list(range(n)) or missing:
            raise SystemExit(f"bps_scale.py: {dtype}: {len(refs)} datasets for detectors {dets} "
                             f"(expected 0..{n - 1}), {len(missing)} without a file, in runs "
                             f"{runs}")
        found[dtype] = len(refs)
    return runs, found


def numba_cache_files():
    """Files of numba's on-disk cache index (``*.nbi``) under the imported package."""
    import lsst_bfdrift

    root = os.path.dirname(os.path.abspath(lsst_bfdrift.__file__))
    return len(glob.glob(os.path.join(root, "**", "*.nbi"), recursive=True))


def camera_scale_rate():
    """camera_scale_results.json's serial and dask CCDs per core-second, or None."""
    try:
        with open(CAMERA_SCALE_JSON) as fh:
            d = json.load(fh)
        return {"command": d["command"], "size": d["size"], "n_images": d["n_images"],
                "serial": d["routes"]["serial"]["images_per_core_second"],
                "dask": d["routes"]["dask"]["images_per_core_second"],
                "serial_cpu": d["routes"]["serial"]["images_per_cpu_second"],
                "load_average": [d["load_average_before"], d["load_average_after"]]}
    except (OSError, KeyError, ValueError):
        return None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=6, help="CCDs (quanta)")
    ap.add_argument("--size", type=int, default=4096, help="CCD side in pixels")
    ap.add_argument("--cores", type=int, default=2, help="cores of Parsl's Local site")
    ap.add_argument("--final-cpus", type=int, default=None,
                    help="finalJob requestCpus (aggregate-graph -j; default BPS's, 16)")
    ap.add_argument("--workdir", default=None,
                    help="where the repository and submit directory go (default a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the working directory")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds for bps submit")
    ap.add_argument("--out", default=OUT,
                    help="results prefix: writes OUT.txt and OUT.json (default %(default)s)")
    args = ap.parse_args()
    if args.n < 1 or args.size < 64 or args.cores < 1 or (args.final_cpus or 1) < 1:
        ap.error("--n >= 1, --size >= 64, --cores >= 1 and --final-cpus >= 1")
    check_bps()
    from lsst.daf.butler import Butler, Config

    import lsst_bfdrift.pipeline as bfpipe

    load_before = os.getloadavg()
    if args.workdir:
        os.makedirs(args.workdir, exist_ok=True)
        work = tempfile.mkdtemp(prefix="bps_scale_", dir=args.workdir)
    else:
        work = tempfile.mkdtemp(prefix="bps_scale_")
    try:
        repo = os.path.join(work, "repo")
        Butler.makeRepo(repo, config=Config(bfpipe.seed_config_path()))
        t0 = time.perf_counter()
        files = []
        for k in range(args.n):
            path = os.path.join(work, f"ccd{k:03d}.fits")
            write_field(path, bench_task.star_field(args.size, 400, seed=100 + k)
                        .astype(np.float32))
            files.append(path)
        bfpipe.put_exposures(repo, files, run=INPUT_RUN, instrument=INSTRUMENT,
                             data_ids=[{"exposure": 1, "detector": k} for k in range(args.n)])
        for path in files:  # in the repository now
            os.remove(path)
        t_prep = time.perf_counter() - t0
        submit = os.path.join(work, "submit.yaml")
        write_submit_yaml(submit, pipe=bfpipe.pipeline_path(), repo=repo, cores=args.cores,
                          final_cpus=args.final_cpus)
        # PWD: the submit directory's default (${PWD}/submit/{outputRun}) in the work dir
        env = dict(os.environ, CTRL_MPEXEC_DIR=sys.prefix, DAF_BUTLER_DIR=sys.prefix,
                   NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", PWD=work)
        nbi_before = numba_cache_files()
        bps = os.path.join(os.path.dirname(sys.executable), "bps")
        if not os.path.exists(bps):
            bps = shutil.which("bps")
        print(f"bps submit: {args.n} CCDs of {args.size} px, {args.cores} cores, in {work}",
              flush=True)
        start = time.time()
        t0, c0 = time.perf_counter(), time.process_time()
        with subprocess.Popen([bps, "submit", submit], cwd=work, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT) as proc:
            with CpuSampler(work, proc.pid) as cpu:
                try:
                    output, _ = proc.communicate(timeout=args.timeout)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    raise
        total, own_cpu = time.perf_counter() - t0, time.process_time() - c0
        load_after = os.getloadavg()
        with open(os.path.join(work, "bps_submit.log"), "w") as fh:
            fh.write(output)
        if proc.returncode != 0:
            raise SystemExit(f"bps_scale.py: bps submit failed (exit {proc.returncode}) after "
                             f"{total:.1f} s; its output's end:\n{output[-4000:]}"
                             f"\n(working directory {work} kept)")
        runs, found = check_outputs(repo, args.n)
        stages = parse_bps_stages(output)
        m = re.search(r"^Submit dir: (\S+)", output, re.M)
        jobs = parse_job_logs(m.group(1)) if m else {}
        nbi_after = numba_cache_files()
    except BaseException:
        args.keep = True
        print(f"working directory kept: {work}", file=sys.stderr)
        raise
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)

    quanta = sorted((j for j in jobs.values() if j["kind"] == "quantum"),
                    key=lambda j: j["start"])
    rate = args.n / (total * args.cores)
    lines = [
        f"{args.n} CCDs of {args.size} x {args.size} float32 (sky 1200 e, 400 stars; "
        "camera_scale.py's field) in a SQLite Butler repository,",
        "bundled pipeline, default Task (drift + geometry maps), through `bps submit` with "
        f"lsst.ctrl.bps.parsl.sites.Local ({args.cores} cores);",
        "each quantum its own `pipetask run-qbb` process; NUMBA_NUM_THREADS=1, OMP_NUM_THREADS=1.",
        f"Machine: {os.cpu_count()} cores ({platform.machine()}, Python "
        f"{platform.python_version()}), shared with other jobs; 1-min load average "
        f"{load_before[0]:.2f} at start, {load_after[0]:.2f} at end.",
        f"One run (not a median); numba's disk cache held {nbi_before} index files before, "
        f"{nbi_after} after.",
        f"Images written and put into the repository before the timing ({t_prep:.1f} s).",
        "",
        f"bps submit, end to end:              {total:7.1f} s",
    ]
    for key, sec in stages.items():
        lines.append(f"  {key + ':':<52}{sec:7.1f} s  (BPS's own timing)")
    phase = None
    if quanta:
        phase = max(j["end"] for j in quanta) - min(j["start"] for j in quanta)
        wall = np.array([j["wall_seconds"] for j in quanta])
        task = np.array([j["task_seconds"] for j in quanta])
        lines.append(f"  quanta, first start to last end ({len(quanta)} quanta):  {phase:7.1f} s")
        for kind in ("init", "final"):
            for j in (j for j in jobs.values() if j["kind"] == kind):
                lines.append(f"  {kind} job:{'':<{43 - len(kind)}}{j['wall_seconds']:7.1f} s")
        lines += ["", "quantum  start(s after submit)  wall(s)  start-up(s)  in Task(s)"]
        for k, j in enumerate(quanta):
            up = "-" if j["startup_seconds"] is None else f"{j['startup_seconds']:.1f}"
            lines.append(f"{k:>7d} {j['start'] - start:>22.1f} {j['wall_seconds']:>8.1f} "
                         f"{up:>12} {j['task_seconds']:>11.1f}")
        lines.append(f"median  {'':>22} {np.median(wall):>8.1f} "
                     f"{np.median([j['startup_seconds'] or np.nan for j in quanta]):>12.1f} "
                     f"{np.median(task):>11.1f}")
        lines.append("wall: the job's log files' creation to their last change; start-up: to "
                     "the first log line (Python, imports);")
        lines.append("in Task: pipetask's 'Execution of task' time (Butler read and write "
                     "included).")
    else:
        lines.append("  (no per-job logs found in the submit directory: total only)")
    cpus = cpu.totals()
    qcpu = np.array(cpu.quanta())
    lines += ["", "CPU seconds (user + system, sampled every 0.2 s from /proc; by process): " +
              ", ".join(f"{k} {v:.1f}" for k, v in sorted(cpus.items()) if k != "total") +
              f"; total {cpus['total']:.1f}"]
    if qcpu.size:
        lines.append(f"  per quantum: median {np.median(qcpu):.1f} (min {qcpu.min():.1f}, max "
                     f"{qcpu.max():.1f}); this script's sampling thread {own_cpu:.1f}")
    cpu_rate = args.n / cpus["total"] if cpus["total"] > 0 else float("nan")
    lines += [
        f"CCDs per CPU-second (N / total CPU s, the figure when the cores are not shared): "
        f"{cpu_rate:.4f}",
    ]
    lines += [
        f"CCDs per core-second (N / (total s x {args.cores} cores)): {rate:.4f}",
    ]
    cam = camera_scale_rate()
    if cam is not None:
        lines += [
            f"camera_scale_results.json ({cam['n_images']} CCDs of {cam['size']} px, files, no "
            f"Butler, load {cam['load_average'][0]:.1f}-{cam['load_average'][1]:.1f}): serial "
            f"{cam['serial']:.4f} CCDs per core-second, {cam['serial_cpu']:.4f} per CPU-second;",
            f"  BPS here / serial there: {rate / cam['serial']:.2f} per core-second, "
            f"{cpu_rate / cam['serial_cpu']:.2f} per CPU-second",
        ]
    lines.append(f"Outputs checked in {', '.join(runs)}: " + ", ".join(
        f"{v} {k}" for k, v in found.items()) + " (one per detector, files present).")
    print(f"# command: {command_line(__file__)}\n" + "\n".join(lines))
    write_results(args.out, lines, {
        "n_ccds": args.n, "size": args.size, "dtype": "float32", "n_stars": 400,
        "cores": args.cores, "site": "lsst.ctrl.bps.parsl.sites.Local",
        "env": {"NUMBA_NUM_THREADS": 1, "OMP_NUM_THREADS": 1}, "cpu_count": os.cpu_count(),
        "load_average_start": load_before[0], "load_average_end": load_after[0],
        "prepare_seconds": t_prep, "total_seconds": total, "bps_stages_seconds": stages,
        "numba_cache_index_files_before": nbi_before, "numba_cache_index_files_after": nbi_after,
        "quanta_phase_seconds": phase,
        "jobs": {name: {**j, "start": j["start"] - start, "end": j["end"] - start}
                 for name, j in sorted(jobs.items(), key=lambda kv: kv[1]["start"])},
        "ccds_per_core_second": rate, "cpu_seconds": cpus, "quantum_cpu_seconds": qcpu,
        "sampler_cpu_seconds": own_cpu, "ccds_per_cpu_second": cpu_rate, "camera_scale": cam,
        "bps_over_camera_scale_serial": None if cam is None else rate / cam["serial"],
        "bps_over_camera_scale_serial_cpu": None if cam is None else cpu_rate / cam["serial_cpu"],
        "output_runs": runs, "outputs": found,
    }, script=__file__, indent=2)


if __name__ == "__main__":
    main()
