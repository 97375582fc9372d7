"""Power of the diagnosis on GalSim flats with one injected effect (issue 15).

Two kinds of injection, both on flats drawn with GalSim's own pixel areas
(``benchmarks/diagnosis/galsim_flat_sets.py``):

* **read-out effects** (CTI on either axis, an echo at serial lag 3, a gain
  non-linearity; :data:`~lsst_bfdrift.simulation.flats.READOUT_EFFECTS`)
  act on the collected charge, so they are applied with
  :func:`~lsst_bfdrift.simulation.flats.apply_readout_effects` to the
  effect-free sets ``set_*.npz`` themselves: every amplitude on every set of
  160 and 240 px (``--per-size`` of each, both sensors), and the effect-free
  set is the exact twin. This gives detection *rates*.
* **fill effects** (a static response pattern, diffusion, a charge cloud,
  well filling)
  change how a flat fills: ``inj_*.npz`` sets drawn with them, each against its twin
  ``twin_*.npz`` (same configuration and seed, no effect; its noise is not
  the same, so the bias below has both sets' errors).

For each injected set: the diagnosis names the effect (for an effect the
library has) or calls the residual unexplained at the effect's lag (the
echo, which the library lacks: an effect nobody declared); another effect
added counts as a false attribution; and the base a00 and a01 of the final
fit move from the twin's by ``d/sd`` (the difference over the injected
fit's error, or over both errors for drawn twins). A charge cloud and the
engine's diffusion change the a-matrix the flats carry; "vs truth" compares
the move with that change, computed from GalSim's noise-free areas
(:func:`~lsst_bfdrift.simulation.flats.engine_acoeffs`), so that the fit is
judged against what the flats hold.

    python benchmarks/diagnosis/galsim_flat_sets.py --n-sets 50
    python benchmarks/diagnosis/galsim_flat_sets.py --injections
    python benchmarks/diagnosis/diagnose_power.py [--cache /work/flatcache] [--per-size 8]

Writes ``benchmarks/diagnosis/diagnose_power_results.txt`` and ``.json``.
"""

import argparse
import glob
import io
import json
import os
import platform
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.calibration.acoeff_model import load_default_basis  # noqa: E402
from lsst_bfdrift.diagnosis.effects_fit import base_acoeffs  # noqa: E402
from lsst_bfdrift.diagnosis.effects_fit import diagnose, observations_from_pairs, scaled_basis
from lsst_bfdrift.simulation.effects import EFFECT_NAMES  # noqa: E402
from lsst_bfdrift.simulation.flats import (READOUT_EFFECTS, apply_readout_effects,  # noqa: E402
                                           engine_acoeffs)

from galsim_flat_sets import INJECTIONS  # noqa: E402

OUT = os.path.join(HERE, "diagnose_power_results")
#: The echo's lag (serial): where an undeclared echo must be named.
ECHO_LAG = "C3,0"


def _load(path):
    d = np.load(path)
    return (json.loads(str(d["config"])), np.asarray(d["flats"], float),
            np.asarray(d["exptime"], float))


def _diagnose(flats, exptime, basis):
    pairs = [(f[0], f[1]) for f in flats]
    res = diagnose(observations_from_pairs(pairs, max_lag=3, exptimes=exptime), basis)
    a, s = base_acoeffs(res.steps[-1], scaled_basis(basis, res.base_scales), 1)
    return res, {key: (float(a[i, j]), float(s[i, j]))
                 for key, (i, j) in (("a00", (0, 0)), ("a01", (0, 1)))}


def _row(name, amp, cfg, res, a, twin_a, *, drawn_twin, twin_res):
    in_library = name in EFFECT_NAMES
    if name in res.not_identifiable:  # the diagnosis says the input cannot show it
        found = None
    elif in_library:
        found = name in res.effects_added
    else:  # an effect nobody declared: an unexplained residual at its lag
        found = bool(res.unexplained and res.worst_lag == ECHO_LAG)
    others = [e for e in res.effects_added if e != name]
    # the change of the a-matrix these flats carry (GalSim's noise-free areas with the
    # fill effect, times the discrete filling's 1 - 1/n_steps): zero for the read-out
    # effects, static patterns and well filling (a_ij at zero charge)
    truth = np.zeros((2, 2))
    if drawn_twin and name in ("charge_cloud", "diffusion"):
        truth = (engine_acoeffs(cfg["sensor"], {name: tuple(amp)}, max_lag=1)
                 - engine_acoeffs(cfg["sensor"], None, max_lag=1)) * (1 - 1 / cfg["n_steps"])
    bias, off = {}, {}
    for k, ij in (("a00", (0, 0)), ("a01", (0, 1))):
        (v, s), (v0, s0) = a[k], twin_a[k]
        sd = np.hypot(s, s0) if drawn_twin else s
        bias[k] = float((v - v0) / sd)
        off[k] = float((v - v0 - truth[ij]) / sd)
    # not added: the base a00, a01 with the effect free (Diagnosis.not_excluded) against
    # the twin's with it free
    free = {}
    ne = {d["effect"]: d for d in res.not_excluded}
    ne0 = {d["effect"]: d for d in twin_res.not_excluded}
    if name in ne and name in ne0:
        for k in ("a00", "a01"):
            (v, s), (v0, s0) = ne[name][k], ne0[name][k]
            free[k] = float((v - v0) / (np.hypot(s, s0) if drawn_twin else s))
    return {"d_a00_free_sd": free.get("a00"), "d_a01_free_sd": free.get("a01"),
            "a00_shift_if_free_sd": ne[name]["a00_shift_sd"] if name in ne else None,
            "effect": name, "amplitude": list(amp), "size": cfg["size"],
            "sensor": cfg["sensor"], "pairs": len(cfg["levels"]) * cfg["pairs_per_level"],
            "set": cfg.get("index"), "in_library": in_library,
            "found": None if found is None else bool(found),
            "not_identifiable": res.not_identifiable.get(name),
            "added": res.effects_added, "other_effects": others,
            "unexplained": bool(res.unexplained), "worst_lag": res.worst_lag,
            "d_a00_sd": bias["a00"], "d_a01_sd": bias["a01"],
            "d_a00_truth_sd": off["a00"], "d_a01_truth_sd": off["a01"], "drawn_twin": drawn_twin}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default="/work/flatcache")
    ap.add_argument("--per-size", type=int, default=8,
                    help="effect-free sets of each size (160, 240) that carry the read-out "
                         "injections")
    args = ap.parse_args(argv)
    basis = load_default_basis()
    out = io.StringIO()
    t_start = time.time()

    def say(s=""):
        print(s, flush=True)
        out.write(s + "\n")

    clean = {160: [], 240: []}
    for p in sorted(glob.glob(os.path.join(args.cache, "set_*.npz"))):
        cfg = json.loads(str(np.load(p)["config"]))
        if cfg["size"] in clean and len(clean[cfg["size"]]) < args.per_size:
            clean[cfg["size"]].append(p)
    say(f"Diagnosis power on GalSim flats ({platform.machine()}, {os.cpu_count()} cores): "
        f"read-out effects on {len(clean[160])} + {len(clean[240])} effect-free sets of "
        "160 and 240 px; fill effects on drawn sets with their twins")
    rows = []
    for size, paths in clean.items():
        for p in paths:
            cfg, flats, t = _load(p)
            res0, a0 = _diagnose(flats, t, basis)
            for name in READOUT_EFFECTS:
                for amp in INJECTIONS[name]:
                    inj = np.array([[apply_readout_effects(f, {name: tuple(amp)}) for f in pr]
                                    for pr in flats])
                    res, a = _diagnose(inj, t, basis)
                    rows.append(_row(name, amp, cfg, res, a, a0, drawn_twin=False,
                                     twin_res=res0))
    for p in sorted(glob.glob(os.path.join(args.cache, "inj_*.npz"))):
        twin = p.replace("inj_", "twin_")
        if not os.path.exists(twin):
            continue
        cfg, flats, t = _load(p)
        (name, amp), = cfg["inject"].items()
        res, a = _diagnose(flats, t, basis)
        res0, a0 = _diagnose(*_load(twin)[1:], basis)
        rows.append(_row(name, amp, cfg, res, a, a0, drawn_twin=True, twin_res=res0))
    say()
    say("effect              amplitude  size  sets  found  other  moved: a00     a01"
        "         vs truth: a00   a01   (|d|/sd median, max)")
    table = []
    for name in INJECTIONS:
        for amp in INJECTIONS[name]:
            for size in (160, 240):
                sel = [r for r in rows if r["effect"] == name and r["amplitude"] == list(amp)
                       and r["size"] == size]
                if not sel:
                    continue
                d00 = np.abs([r["d_a00_sd"] for r in sel])
                d01 = np.abs([r["d_a01_sd"] for r in sel])
                t00 = np.abs([r["d_a00_truth_sd"] for r in sel])
                t01 = np.abs([r["d_a01_truth_sd"] for r in sel])
                nid = all(r["found"] is None for r in sel)
                t = {"effect": name, "amplitude": list(amp), "size": size, "sets": len(sel),
                     "found": None if nid else sum(bool(r["found"]) for r in sel),
                     "other": sum(bool(r["other_effects"]) for r in sel),
                     "d_a00_median": float(np.median(d00)), "d_a00_max": float(d00.max()),
                     "d_a01_median": float(np.median(d01)), "d_a01_max": float(d01.max()),
                     "truth_a00_median": float(np.median(t00)), "truth_a00_max": float(t00.max()),
                     "truth_a01_median": float(np.median(t01)),
                     "truth_a01_max": float(t01.max())}
                table.append(t)
                found = "  n/i" if nid else f"{t['found']:5d}"
                say(f"{name:18s} {amp[0]:9.1e}  {size:4d}  {len(sel):4d}  {found}  "
                    f"{t['other']:5d}  {t['d_a00_median']:4.2f}, {t['d_a00_max']:4.2f}  "
                    f"{t['d_a01_median']:4.2f}, {t['d_a01_max']:4.2f}      "
                    f"{t['truth_a00_median']:4.2f}, {t['truth_a00_max']:4.2f}  "
                    f"{t['truth_a01_median']:4.2f}, {t['truth_a01_max']:4.2f}")
    say()
    say("not added, with the effect free (Diagnosis.not_excluded): the base a00, a01 "
        "minus the twin's with it free, |d|/sd median, max")
    for name in INJECTIONS:
        for amp in INJECTIONS[name]:
            sel = [r for r in rows if r["effect"] == name and r["amplitude"] == list(amp)
                   and r["d_a00_free_sd"] is not None]
            if not sel:
                continue
            f00 = np.abs([r["d_a00_free_sd"] for r in sel])
            f01 = np.abs([r["d_a01_free_sd"] for r in sel])
            sh = np.abs([r["a00_shift_if_free_sd"] for r in sel])
            say(f"  {name:18s} {amp[0]:9.1e}  {len(sel):3d} sets  a00 {np.median(f00):4.2f}, "
                f"{f00.max():4.2f}  a01 {np.median(f01):4.2f}, {f01.max():4.2f}  "
                f"(freeing it moves a00 by {np.median(sh):.1f}, up to {sh.max():.1f} sigma of "
                "the final fit)")
    say()
    say(f"another effect added (a false attribution) in "
        f"{sum(bool(r['other_effects']) for r in rows)} of {len(rows)} injected sets")
    nid = sorted({r["effect"] for r in rows if r["found"] is None})
    for name in nid:
        why = next(r["not_identifiable"] for r in rows if r["effect"] == name)
        say(f"n/i: the diagnosis reports {name} as not identifiable from flat pairs ({why}); "
            "silence is the right answer")
    say("found: the effect named (library effects), or the residual called unexplained with "
        f"its worst lag at {ECHO_LAG} (the echo, which the library lacks); other effect: "
        "another effect added; moved: the final fit's a00, a01 minus the twin's, over the "
        "injected fit's error (read-out effects: the twin is the same flats) or both errors "
        "(drawn twins); vs truth: the same minus the change of the a-matrix the flats carry "
        "(engine_acoeffs: GalSim's noise-free areas with a charge cloud or diffusion; zero "
        f"for the other effects). {len(rows)} diagnoses in {time.time() - t_start:.0f} s.")
    write_results(OUT, out.getvalue().removesuffix("\n").split("\n"),
                  {"table": table, "sets": rows}, script=__file__)


if __name__ == "__main__":
    main()
