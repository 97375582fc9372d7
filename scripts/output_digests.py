"""SHA-256 digests of the package's main outputs, for refactors that must not change them.

Run before and after a change and compare the JSON files::

    python scripts/output_digests.py --out before.json
    # ... refactor ...
    python scripts/output_digests.py --out after.json --compare before.json

Covered: the Task (drift, astier23, coulton18 on a seeded star field with a
NaN, with and without geometry maps), an exact template build (small
settings and the default settings), ``moment_maps``, the PTC measurement and
its two fits on seeded flat pairs, the eotest PTC reader, the a_ij table
reader and the two flat generators. Each digest covers the exact bytes of
every array and float of the result, so a digest match is a bit-identical
result.
"""

import argparse
import dataclasses
import hashlib
import importlib
import json
import pathlib
import sys

import numpy as np

SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data" / "measured"


def _import(*names):
    """The first module of ``names`` that imports (old and new layouts)."""
    for name in names:
        try:
            return importlib.import_module(name)
        except ImportError:
            continue
    raise ImportError(names)


def _feed(h, obj):
    if obj is None or isinstance(obj, (str, bool)):
        h.update(repr(obj).encode())
    elif isinstance(obj, (int, float, np.floating, np.integer)):
        h.update(np.float64(obj).tobytes())
    elif isinstance(obj, np.ndarray):
        h.update(str(obj.dtype).encode() + str(obj.shape).encode())
        h.update(np.ascontiguousarray(obj).tobytes())
    elif isinstance(obj, dict):
        for k in sorted(obj, key=str):
            h.update(str(k).encode())
            _feed(h, obj[k])
    elif isinstance(obj, (list, tuple)):
        for v in obj:
            _feed(h, v)
    elif dataclasses.is_dataclass(obj):
        _feed(h, {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)})
    elif hasattr(obj, "colnames"):  # astropy Table
        _feed(h, {c: np.asarray(obj[c]) for c in obj.colnames})
    elif hasattr(obj, "getDict") or hasattr(obj, "get_dict"):  # Struct
        _feed(h, {k: v for k, v in _struct_dict(obj).items() if not hasattr(v, "header")})
    elif hasattr(obj, "data") and hasattr(obj, "unit"):  # CCDData
        _feed(h, np.asarray(obj.data))
    elif hasattr(obj, "__dict__"):
        _feed(h, {k: v for k, v in vars(obj).items() if not k.startswith("_")})
    else:
        h.update(repr(obj).encode())


def _struct_dict(obj):
    return obj.getDict() if hasattr(obj, "getDict") else obj.get_dict()


def digest(obj):
    h = hashlib.sha256()
    _feed(h, obj)
    return h.hexdigest()[:16]


def _template_digest(t):
    return digest([t.corner_d, t.vedge_d, t.hedge_d, t.fractions, t.charge, t.vedge_t,
                   t.hedge_t])


def star_field(n=512, seed=11):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:n, :n]
    img = rng.poisson(800.0, (n, n)).astype(float)
    for _ in range(25):
        x0, y0 = rng.uniform(20, n - 20, 2)
        flux = 10 ** rng.uniform(4, 6.2)
        s = rng.uniform(1.2, 2.0)
        img += flux / (2 * np.pi * s * s) * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * s * s))
    img[100, 200] = np.nan
    return img


def flat_pairs(levels, shape=(200, 180), seed=5):
    rng = np.random.default_rng(seed)
    return [(rng.poisson(m, shape) / 1.4, rng.poisson(m, shape) / 1.4) for m in levels]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--compare")
    ap.add_argument("--skip-default-build", action="store_true",
                    help="skip the 20 s build with the default settings")
    args = ap.parse_args(argv)

    pkg = importlib.import_module("lsst_bfdrift")
    tmod = _import("lsst_bfdrift.templates.template", "lsst_bfdrift.template")
    smod = _import("lsst_bfdrift.physics.sensor", "lsst_bfdrift.sensor")
    sup = _import("lsst_bfdrift.geometry.superpose", "lsst_bfdrift.superpose")
    ptc = _import("lsst_bfdrift.ptc.covariances", "lsst_bfdrift.ptc")
    aco = _import("lsst_bfdrift.calibration.acoeff_model", "lsst_bfdrift.acoeff_fit")
    sims = _import("lsst_bfdrift.simulation.flats", "lsst_bfdrift.simulations")
    inj = _import("lsst_bfdrift.simulation.injection", "lsst_bfdrift.simulation.flats",
                  "lsst_bfdrift.injection")

    out = {}
    tpl = tmod.load_default_template()
    img = star_field()
    for method in ("drift", "astier23", "coulton18"):
        for geom in (False, True):
            cfg = pkg.BrighterFatterDriftConfig(method=method, compute_geometry=geom)
            res = pkg.BrighterFatterDriftTask(config=cfg, template=tpl).run(img)
            key = f"task_{method}{'_geometry' if geom else ''}"
            out[key] = digest({k: v for k, v in _struct_dict(res).items()
                               if isinstance(v, np.ndarray)
                               or (hasattr(v, "data") and hasattr(v, "unit"))})
    out["moment_maps"] = digest(sup.moment_maps(tpl, np.nan_to_num(img[:128, :160])))

    small = tmod.TemplateSettings(size=5, edge_samples=3, tol=1e-3, workers=2)
    built = tmod.build_template(smod.SensorParameters(), small)
    out["build_small"] = _template_digest(built)
    if not args.skip_default_build:
        built = tmod.build_template(smod.SensorParameters())
        out["build_default"] = _template_digest(built)

    levels = [2e3, 5e3, 1e4, 2e4, 4e4, 6e4, 8e4]
    table = ptc.measure_ptc(flat_pairs(levels), max_lag=3)
    out["measure_ptc"] = digest(table)
    cov = np.asarray(table["cov"])
    out["fit_ptc_exponential"] = digest(ptc.fit_ptc_exponential(np.asarray(table["mu"]),
                                                                cov[:, 0, 0]))
    out["fit_covariance_model"] = digest(ptc.fit_covariance_model(
        np.asarray(table["mu"]), cov, npix=np.asarray(table["npix"])))
    out["read_ptc_text"] = digest(ptc.read_ptc_text(SHARED / "eotest_e2v_ptc_amp05.txt"))
    out["read_acoeff_table"] = digest(aco.read_acoeff_table(SHARED / "itl_covariances_21oct19.txt"))

    out["simulate_flats"] = digest(sims.simulate_flats(built if args.skip_default_build else tpl,
                                                       n_images=16, shape=(8, 8), n_steps=20,
                                                       seed=3))
    a = np.zeros((4, 4))
    a[0, 0], a[1, 0], a[0, 1] = -2e-6, 3e-7, 1.5e-7
    out["simulate_flat_pairs"] = digest(inj.simulate_flat_pairs(
        a, [1e4, 3e4], shape=(64, 64), inject={"cti_serial": (1e-4,)}, seed=4))

    text = json.dumps(out, indent=1, sort_keys=True)
    pathlib.Path(args.out).write_text(text + "\n")
    print(text)
    if args.compare:
        ref = json.loads(pathlib.Path(args.compare).read_text())
        diff = sorted(k for k in ref if k in out and ref[k] != out[k])
        missing = sorted(set(ref) ^ set(out))
        print("differ:", diff or "none", "| only on one side:", missing or "none")
        return 1 if diff else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
