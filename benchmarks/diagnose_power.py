"""Power of the diagnosis on GalSim flats with one injected effect (issue 15).

Reads the ``inj_*.npz`` sets of ``benchmarks/galsim_flat_sets.py --injections``
(GalSim's own pixel areas, one library effect injected at two amplitudes, on
160 and 240 px flats) and the effect-free ``set_*.npz`` sets. For each
injected set: does the diagnosis name the injected effect, which effects it
adds, and how far the base fit's a00 and a01 moved from the effect-free fits
of the same sensor (the median of those, in units of the set's own error).

    python benchmarks/galsim_flat_sets.py --injections
    python benchmarks/diagnose_power.py [--cache /work/flatcache]

Writes ``benchmarks/diagnose_power_results.txt`` and ``.json``.
"""

import argparse
import glob
import io
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, ".."))

from lsst_bfdrift.calibration.acoeff_fit import load_default_basis  # noqa: E402
from lsst_bfdrift.calibration.diagnosis import (diagnose, observations_from_pairs,  # noqa: E402
                                               scaled_basis)
from lsst_bfdrift.utils.io import atomic_output  # noqa: E402

OUT = os.path.join(HERE, "diagnose_power_results")


def _fit(path, basis):
    d = np.load(path)
    cfg = json.loads(str(d["config"]))
    pairs = [(f[0].astype(float), f[1].astype(float)) for f in d["flats"]]
    res = diagnose(observations_from_pairs(pairs, max_lag=3, exptimes=d["exptime"]), basis)
    used = scaled_basis(basis, res.base_scales)
    a = used.a(np.array([res.steps[-1]["base_params"][n] for n in used.names]), 1)
    return cfg, res, a


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/work/flatcache")
    args = ap.parse_args(argv)
    basis = load_default_basis()
    out = io.StringIO()

    def say(s=""):
        print(s, flush=True)
        out.write(s + "\n")

    ref = {}
    for p in sorted(glob.glob(os.path.join(args.cache, "set_*.npz"))):
        cfg, _, a = _fit(p, basis)
        ref.setdefault(cfg["sensor"], []).append(a)
    ref = {k: (np.median(v, axis=0), np.std(v, axis=0, ddof=1) if len(v) > 1 else None)
           for k, v in ref.items()}
    rows = []
    say("injected effect         amp  size sensor         named  added                "
        "d a00/sd  d a01/sd")
    for p in sorted(glob.glob(os.path.join(args.cache, "inj_*.npz"))):
        cfg, res, a = _fit(p, basis)
        (name, amp), = cfg["inject"].items()
        r0, sd = ref.get(cfg["sensor"], (None, None))
        da00 = da01 = None
        if r0 is not None and sd is not None:
            da00 = float((a[0, 0] - r0[0, 0]) / sd[0, 0])
            da01 = float((a[0, 1] - r0[0, 1]) / sd[0, 1])
        named = name in res.effects_added
        rows.append({"effect": name, "amplitude": amp, "size": cfg["size"],
                     "sensor": cfg["sensor"], "named": named, "added": res.effects_added,
                     "unexplained": res.unexplained, "d_a00_sd": da00, "d_a01_sd": da01,
                     "verdict": res.verdict})
        say(f"{name:20s} {amp[0]:8.1e} {cfg['size']:4d} {cfg['sensor']:14s} "
            f"{'yes' if named else 'no ':5s}  {','.join(res.effects_added) or '-':20s} "
            + (f"{da00:+8.2f}  {da01:+8.2f}" if da00 is not None else "     n/a       n/a"))
    n = len(rows)
    if n:
        say()
        say(f"named: {sum(r['named'] for r in rows)} of {n}; another effect added: "
            f"{sum(bool(set(r['added']) - {r['effect']}) for r in rows)}")
    with atomic_output(OUT + ".txt") as tmp, open(tmp, "w") as fh:
        fh.write(out.getvalue())
    with atomic_output(OUT + ".json") as tmp, open(tmp, "w") as fh:
        json.dump({"sets": rows, "reference_sensors": sorted(ref)}, fh, indent=1)


if __name__ == "__main__":
    main()
