"""Where the diagnosis' false alarms on large flat sets come from: the base model.

Flat sets made with the linear engine (FFT areas,
:func:`~lsst_bfdrift.simulation.flats.simulate_flat_pairs`) in the
configurations of the 240 px sets of ``benchmarks/diagnosis/galsim_flat_sets.py``
(levels, pairs, seeds; 20 fill steps), diagnosed with three base models:

* ``default``: the shipped basis (electrostatic a_ij linearised about the
  fit to the measured ITL table, 4 parameters);
* ``+ global scale``: plus one scale of every a_ij;
* ``+ a00, a01, a10 scales``: plus one scale for each of these lags.

Data: (1) GalSim's own a-matrix of the set's sensor (ITL or e2v), no
effect: every effect added is a false alarm; (2) the default basis' own
a-matrix (which the base model represents exactly), 20 and 160 fill steps:
separates a mismatch of the base model from the discrete filling; (3)
GalSim's a-matrix with effects injected at large amplitudes into the first
three configurations: the power each base model keeps. The linear engine is
the package's own forward model with another simulator's a-matrix, so
these runs locate the cause; the false-alarm rate itself is measured on
GalSim's pixel areas (``benchmarks/diagnosis/diagnose_false_alarms.py``)::

    python benchmarks/diagnosis/diagnose_base_model.py

Writes ``benchmarks/diagnosis/diagnose_base_model_results.txt`` and ``.json``.
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

from galsim_flat_sets import set_config  # noqa: E402
from lsst_bfdrift.calibration.acoeff_model import load_default_basis  # noqa: E402
from lsst_bfdrift.diagnosis.effects_fit import diagnose, observations_from_pairs  # noqa: E402
from lsst_bfdrift.simulation.flats import simulate_flat_pairs  # noqa: E402
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs  # noqa: E402

INJECTIONS = (("cti_parallel", (1e-2,)), ("cti_serial", (1e-2,)),
              ("gain_nonlinearity", (6e-7,)), ("gain_nonlinearity", (2e-7,)),
              ("echo", (1e-2, 3)))


def run(a, cfg, bases, *, steps=20, inject=None):
    levels = np.repeat(cfg["levels"], cfg["pairs_per_level"])
    pairs = simulate_flat_pairs(a, levels, engine="linear", shape=(cfg["size"],) * 2,
                                n_steps=steps, seed=cfg["seed"], inject=inject)
    obs = observations_from_pairs(pairs, max_lag=3, exptimes=levels * 1e-4)
    out = {}
    for name, basis in bases.items():
        res = diagnose(obs, basis, base_scales=())  # the bases as given
        cand = res.candidates[0][:-1] if res.candidates else []
        best = min(cand, key=lambda c: c["delta_bic"]) if cand else None
        out[name] = {"added": res.effects_added, "unexplained": res.unexplained,
                     "chi2_dof": res.steps[0]["chi2_dof"],
                     "best": None if best is None else [best["name"], best["delta_bic"]]}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(HERE, "diagnose_base_model_results"))
    args = ap.parse_args(argv)
    t0 = time.time()
    base = load_default_basis()
    L = base.max_lag
    bases = {"default": base,
             "+ global scale": base.with_scales([[(i, j) for i in range(L + 1)
                                                  for j in range(L + 1)]]),
             "+ a00, a01, a10 scales": base.with_scales([[(0, 0)], [(0, 1)], [(1, 0)]])}
    configs = [set_config(k) for k in range(50) if set_config(k)["size"] == 240]
    galsim_a = {s: galsim_acoeffs(s, 5) for s in {c["sensor"] for c in configs}}
    own_a = base.a([base.x0[n] for n in base.names])
    lines, rec = [], {"clean": [], "basis_own": [], "injections": []}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    say(f"Diagnosis base models on linear-engine flat sets in the configurations of the "
        f"{len(configs)} sets of 240 px ({platform.machine()}, {os.cpu_count()} cores)")

    def summary(rows, label):
        for name in bases:
            alarms = sum(bool(r[name]["added"] or r[name]["unexplained"]) for r in rows)
            best = [r[name]["best"][1] for r in rows if r[name]["best"]]
            say(f"  {label:34s} {name:24s} false alarms {alarms:2d}/{len(rows)}; best dBIC "
                f"{min(best):+7.1f} to {max(best):+6.1f} (median {np.median(best):+5.1f})")

    for cfg in configs:
        r = run(galsim_a[cfg["sensor"]], cfg, bases)
        rec["clean"].append(dict(set=cfg["index"], sensor=cfg["sensor"], **r))
    summary(rec["clean"], "GalSim a-matrix, no effect")
    for steps in (20, 160):
        rows = [run(own_a, cfg, {"default": base}, steps=steps) for cfg in configs]
        rec["basis_own"].append({"steps": steps, "rows": rows})
        alarms = sum(bool(r["default"]["added"] or r["default"]["unexplained"]) for r in rows)
        best = [r["default"]["best"][1] for r in rows if r["default"]["best"]]
        say(f"  basis' own a-matrix, {steps:3d} fill steps   default                  false alarms "
            f"{alarms:2d}/{len(rows)}; best dBIC {min(best):+7.1f} to {max(best):+6.1f}")
    say("  power (GalSim a-matrix, effect injected; first three configurations): named / sets")
    for name, amp in INJECTIONS:
        rows = [run(galsim_a[c["sensor"]], c, bases, inject={name: amp}) for c in configs[:3]]
        rec["injections"].append({"effect": name, "amplitude": list(amp), "rows": rows})
        say(f"    {name:18s} {str(amp):12s} " + "   ".join(
            f"{b}: {sum(name in r[b]['added'] for r in rows)}/{len(rows)}" for b in bases))
    say(f"({time.time() - t0:.0f} s)")
    write_results(args.out, lines, rec, script=__file__, json_default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
