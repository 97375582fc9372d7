"""Effect-free flat sets made by GalSim, for the diagnosis's false-alarm rate (issue 15).

Each set is drawn by :func:`lsst_bfdrift.simulation.flats.simulate_flat_pairs`
with ``engine='galsim'``: every flat fills in steps, each step adds Poisson
electrons with the pixel areas that ``galsim.SiliconSensor.calculate_pixel_areas``
gives for the charge collected so far (GalSim's own BF; no effect of the
package's library is present). Sets differ in sensor, size, level ladder,
pairs per level and seed, drawn from a seeded generator, so that nothing is
tuned to one configuration.

    python benchmarks/diagnosis/galsim_flat_sets.py --n-sets 50 --out /work/flatcache
    python benchmarks/diagnosis/galsim_flat_sets.py --injections --out /work/flatcache

``--injections`` draws the power sets of the effects that act while a flat
fills (a static response pattern, diffusion, a charge cloud, well filling) at two or three
amplitudes (the first
two near what sensors show, the third well above, to find the threshold;
:data:`FILL_INJECTIONS`) on two sizes (160 and 240 px), named
``inj_<effect>_<k>_<size>.npz``, each with its effect-free twin (the same
configuration and seed without the effect), ``twin_<effect>_<k>_<size>.npz``;
``--repeats`` draws more sets per cell (``..._r<r>.npz``, other configurations,
seeds and sensors).
The effects that act on the read-out of the collected charge (CTI on either
axis, an echo, gain non-linearity;
:data:`~lsst_bfdrift.simulation.flats.READOUT_EFFECTS`) need no drawing:
``benchmarks/diagnosis/diagnose_power.py`` applies them to the effect-free sets, which
are then their exact twins.

Writes one ``set_NNN.npz`` per set (flats as float32 electrons, the levels,
EXPTIME per flat, the configuration) and skips sets that exist, so it can be
stopped and resumed. Prints the time per set.
"""

import argparse
import json
import os
import time

import numpy as np

from lsst_bfdrift.simulation.flats import simulate_flat_pairs

SENSORS = ("lsst_itl_50_8", "lsst_e2v_50_8")

#: Injected effects and amplitudes (the package's parameters, simulation.flats.INJECTABLE):
#: CTI eps (fraction of a pixel's charge trailing into the next, per axis), echo (kappa,
#: lag px), gain non-linearity (nu per ADU), static pattern (variance, correlation length
#: px), diffusion (rms px), charge cloud (variances px^2), well filling (beta per e:
#: a_ij grows by beta Q, 24 %, 80 % and 240 % at 80 ke). The first two are near what
#: sensors show (well filling: the first); the others are far above, to locate the
#: detection threshold at these data sizes.
INJECTIONS = {"cti_serial": [(3e-4,), (1e-3,), (1e-2,)],
              "cti_parallel": [(3e-4,), (1e-3,), (1e-2,)],
              "echo": [(3e-4, 3), (1e-3, 3), (1e-2, 3)],
              "gain_nonlinearity": [(2e-7,), (6e-7,), (3e-6,)],
              "static_area": [(1e-5, 3.0), (4e-5, 3.0), (4e-4, 3.0)],
              "diffusion": [(0.1,), (0.25,), (0.5,)],
              "charge_cloud": [(0.05, 0.05), (0.15, 0.15)],
              "well_filling": [(3e-6,), (1e-5,), (3e-5,)]}
#: The injections that change how a flat fills: drawn with their twins.
FILL_INJECTIONS = ("static_area", "diffusion", "charge_cloud", "well_filling")
SIZES = (160, 200, 240)


def set_config(k, *, seed=2026):
    """Configuration of set ``k`` (deterministic in ``k`` and ``seed``)."""
    rng = np.random.default_rng([seed, k])
    n_levels = int(rng.integers(8, 13))
    top = float(rng.uniform(6e4, 9e4))
    levels = np.geomspace(float(rng.uniform(2e3, 6e3)), top, n_levels)
    return {"index": k, "sensor": SENSORS[k % len(SENSORS)],
            "size": int(SIZES[int(rng.integers(len(SIZES)))]),
            "pairs_per_level": int(rng.integers(2, 5)),
            "levels": [float(v) for v in levels], "n_steps": 20,
            "seed": int(rng.integers(1 << 30))}


def draw_set(cfg):
    """Flats (n_pairs, 2, ny, nx) float32 in e, levels per pair, EXPTIME per pair."""
    levels = np.repeat(cfg["levels"], cfg["pairs_per_level"])
    inject = {k: tuple(v) for k, v in cfg.get("inject", {}).items()}
    pairs = simulate_flat_pairs(cfg["sensor"], levels, engine="galsim",
                                shape=(cfg["size"],) * 2, n_steps=cfg["n_steps"],
                                seed=cfg["seed"], inject=inject or None)
    flats = np.array([[p[0], p[1]] for p in pairs], dtype=np.float32)
    return flats, levels, levels * 1e-4  # EXPTIME (s): 1e4 e/s, no shutter error


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n-sets", type=int, default=50)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--out", default="/work/flatcache")
    ap.add_argument("--injections", action="store_true", help="draw the power sets")
    ap.add_argument("--only", nargs="+", help="with --injections: these effects only")
    ap.add_argument("--size", type=int, help="with --injections: this size only")
    ap.add_argument("--amplitude", type=int, help="with --injections: this amplitude (index) only")
    ap.add_argument("--repeats", type=int, default=1,
                    help="with --injections: sets per effect, amplitude and size (repeat r > 0 "
                         "is named ..._r<r>.npz and has its own configuration and seed)")
    args = ap.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    jobs = [(os.path.join(args.out, f"set_{k:03d}.npz"), set_config(k))
            for k in range(args.first, args.first + args.n_sets)]
    if args.injections:
        jobs = []
        for n, (name, amps) in enumerate(INJECTIONS.items()):
            if name not in FILL_INJECTIONS or (args.only and name not in args.only):
                continue
            for a, amp in enumerate(amps):
                if args.amplitude is not None and a != args.amplitude:
                    continue
                for size in (160, 240) if args.size is None else (args.size,):
                    for r in range(args.repeats):
                        cfg = set_config(1000 + 10 * n + 2 * a + (size == 240) + 1000 * r)
                        cfg.update(size=size, pairs_per_level=3,
                                   sensor=SENSORS[(n + a + r) % 2])
                        tag = f"{name}_{a}_{size}" + (f"_r{r}" if r else "")
                        jobs.append((os.path.join(args.out, f"twin_{tag}.npz"), dict(cfg)))
                        cfg.update(inject={name: list(amp)})
                        jobs.append((os.path.join(args.out, f"inj_{tag}.npz"), cfg))
    for path, cfg in jobs:
        if os.path.exists(path):
            continue
        t0 = time.time()
        flats, levels, exptime = draw_set(cfg)
        tmp = path + ".tmp.npz"
        np.savez_compressed(tmp, flats=flats, levels=levels, exptime=exptime,
                            config=json.dumps(cfg))
        os.replace(tmp, path)
        print(f"{os.path.basename(path)}: {cfg.get('inject', '')} {cfg['sensor']} "
              f"{cfg['size']}^2, {len(cfg['levels'])} levels x {cfg['pairs_per_level']} "
              f"pairs, top {cfg['levels'][-1]:.0f} e: {time.time() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
