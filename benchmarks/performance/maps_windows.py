"""The linear maps' windowed route (issue 46 item 1): where the sky's noise allows it, and its time.

Part 1, on the 400-star 4096 x 4096 field of ``bench_task.py`` (sky 1200 e,
Poisson): each map's signal S (largest abs(map - nominal) of the
first-order maps), the first-order response of ``q - qbar`` (the maps minus
their uniform value, pixels beyond the template's reach of the border) and
the share of pixels where it exceeds ``rtol S``: the windowed route
returns the uniform value only where its bound is below that, so where the
response itself exceeds it, no bound can avoid the windows. Also the
route that ``first_order_route`` expects and the one taken, with the
windows' share, per ``rtol``.

Part 2: the Task (drift, default options) with the maps at
``geometry_tolerance`` 1e-3 (the default: full route) and 3e-2 (windowed
route where taken), the default without the route's pre-check (the code
before the windowed route), drift without maps and astier23, on the
400-star field and the 4000-star field; in each of ``--repeat`` rounds
every Task runs once, in a new (seeded) random order; medians and the
fastest call, ratios to astier23 in the same run::

    python benchmarks/performance/maps_windows.py [--repeat 5]

Writes ``benchmarks/performance/maps_windows_results.txt`` and ``.json``.
"""

import argparse
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from bench_task import star_field  # noqa: E402
from lsst_bfdrift import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402
from lsst_bfdrift.correction import steps  # noqa: E402
from lsst_bfdrift.geometry.bounds import reference_level  # noqa: E402
from lsst_bfdrift.geometry.first_order import LINEAR_MAPS, linear_kernels  # noqa: E402
from lsst_bfdrift.geometry.linear import first_order_route, linear_moment_maps  # noqa: E402
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402

RTOLS = (1e-3, 1e-2, 3e-2, 1e-1)
NOMINAL = dict(area=1.0, dx=0.0, dy=0.0, e1=0.0, e2=0.0)


def sky_response(img, template):
    """Per map: signal, median response of q - qbar, share of pixels above rtol S."""
    lk = linear_kernels(template, samples=8)
    r = lk.reach
    lin = linear_moment_maps(template, img, samples=8, workers=2, fallback=False,
                             route="full")
    qbar = reference_level(img)
    out = {}
    for k, name in enumerate(LINEAR_MAPS):
        m = getattr(lin, name)
        s = float(np.abs(m - NOMINAL[name]).max())
        dev = np.abs(m[r:-r, r:-r] - (NOMINAL[name] + qbar * lk.kernels[k].sum()))
        out[name] = dict(signal=s, median=float(np.median(dev)),
                         above={str(t): float(np.mean(dev > t * s)) for t in RTOLS})
    routes = {}
    for t in RTOLS:
        info = {}
        linear_moment_maps(template, img, samples=8, workers=2, rtol=t, info=info,
                           dtype=np.float32, map_dtype=np.float32)
        routes[str(t)] = dict(expected=first_order_route(template, img, rtol=t, samples=8),
                              taken=info["route"],
                              first_order_fraction=info["first_order_fraction"])
    return out, routes


class _NoPrecheck:
    """The default Task with the route's pre-check replaced by 'full' (the
    code path before the windowed route)."""

    def __init__(self, task):
        self.task = task

    def run(self, img):
        orig = steps.first_order_route
        steps.first_order_route = lambda *a, **k: "full"
        try:
            return self.task.run(img)
        finally:
            steps.first_order_route = orig


def timings(img, repeat):
    def task(method="drift", **kw):
        return BrighterFatterDriftTask(config=BrighterFatterDriftConfig(method=method,
                                                                        workers=2, **kw))

    tasks = {"astier23": task("astier23", compute_geometry=False),
             "drift": task(compute_geometry=False),
             "default": task(),
             "default, no pre-check": _NoPrecheck(task()),
             "maps at 3e-2": task(geometry_tolerance=3e-2)}
    for t in tasks.values():
        t.run(img[:64, :64])
        t.run(img)
    out = {k: [] for k in tasks}
    order = list(tasks.items())
    rng = np.random.default_rng(0)
    for _ in range(repeat):
        # a new order each round (seeded): a call's time depends on the call
        # before it on a loaded machine; a fixed order biases the medians
        for i in rng.permutation(len(order)):
            name, t = order[i]
            t0 = time.perf_counter()
            t.run(img)
            out[name].append(time.perf_counter() - t0)
    res = {k: dict(median=float(np.median(v)), min=min(v), max=max(v)) for k, v in out.items()}
    # the route each Task with maps took (one more call, not timed)
    orig = steps.linear_moment_maps
    for name in ("default", "maps at 3e-2"):
        info = {}

        def spy(*a, **k):
            k["info"] = info
            return orig(*a, **k)

        steps.linear_moment_maps = spy
        try:
            tasks[name].run(img)
        finally:
            steps.linear_moment_maps = orig
        res[name].update(route=info["route"], first_order_fraction=info["first_order_fraction"])
    return res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(HERE, "maps_windows_results"))
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    t = load_default_template()
    fields = {"400 stars": star_field(4096, 400), "4000 stars": star_field(4096, 4000, seed=2)}
    resp, routes = sky_response(fields["400 stars"], t)
    lines = [f"4096 x 4096, {os.cpu_count()} cores ({platform.machine()}, "
             f"{platform.python_version()}); 1-min load average {load:.2f} before"]
    lines.append("Part 1, 400 stars (sky 1200 e, Poisson): first-order response of q - qbar, "
                 "share of pixels above rtol x signal")
    for name, r in resp.items():
        lines.append(f"  {name:4s} signal {r['signal']:.3e}  median response {r['median']:.2e} "
                     f"= {r['median'] / (1e-3 * r['signal']):.2f} x (1e-3 signal);  above: "
                     + "  ".join(f"rtol {k} {v:6.2%}" for k, v in r["above"].items()))
    for k, v in routes.items():
        lines.append(f"  rtol {k}: expected route {v['expected']}, taken {v['taken']}, "
                     f"first-order convolutions over {v['first_order_fraction']:.1%} of the image")
    res = {"sky_response": resp, "routes": routes}
    lines.append(f"Part 2: Task calls in a random order per round, median (min-max) of "
                 f"{args.repeat}; ratios of medians and of the fastest calls")
    for fname, img in fields.items():
        tm = timings(img, args.repeat)
        res[fname] = tm
        base = tm["astier23"]["median"]
        lines.append(f"  {fname}:")
        for name, v in tm.items():
            route = (f"; {v['route']} route, first order over {v['first_order_fraction']:.1%}"
                     if "route" in v else "")
            lines.append(f"    {name:22s} {v['median']:6.3f} s ({v['min']:.3f}-{v['max']:.3f}) "
                         f"= {v['median'] / base:5.2f}x astier23, fastest "
                         f"{v['min'] / tm['astier23']['min']:5.2f}x{route}")
    lines.append(f"  1-min load average after: {os.getloadavg()[0]:.2f}")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(args.out, lines, {"load_average_before": load,
                                    "load_average_after": os.getloadavg()[0], **res},
                  script=__file__, indent=2)


if __name__ == "__main__":
    main()
