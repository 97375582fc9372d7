"""Cross-check of the star simulation against galsim.SiliconSensor.

Run from the repository root::

    python benchmarks/simulation/galsim_crosscheck.py [--n-stars 24] [--out PREFIX]
    python benchmarks/simulation/galsim_crosscheck.py --sensor lsst_e2v_50_8 \
        --variants match_areas match_transfers \
        --out benchmarks/simulation/galsim_crosscheck_e2v_results

For each star the same photons (GalSim photon shooting, Gaussian PSF) are
accumulated three ways, in the same order and with the boundaries updated
every ``nrecalc`` conversions in all of them:

* ``galsim``: ``galsim.SiliconSensor(SENSOR, diffusion_factor=0,
  nrecalc=...)`` (one OpenMP thread, see below);
* ``ours``: :class:`lsst_bfdrift.simulation.stars.StarSimulation` with the template
  imported from the same sensor file: shared (tiling) boundaries with the
  corners matched to GalSim's pixel areas (``match="areas"``, the
  default import); shared boundaries with the edge samples matched to
  GalSim's effective per-edge transfers (``match='transfers'``, measured at
  1e4 e, and ``match_transfers_1e5`` at the file's 1e5 e); shared boundaries with every edge and corner taken from
  the pixel nearest the aggressor (``match="none"``); and GalSim's own
  layout and assignment rule (``layout='galsim'``: per-edge polylines with
  their own corner copies, nominal pixel first, random fallback);
* ``nominal``: the photons binned on the undistorted grid (the BF-free twin).

The brighter-fatter size change of a star is dT/T = T / T_nominal - 1 with T
= Ixx + Iyy (unweighted moments over the stamp). Slopes of dT/T against
flux (through the origin, per 1e5 e) are fitted for each simulator, with
errors from the scatter of the stars, and the paired ratio ours / galsim
(slope of the per-star differences) with its error; the same for the
ellipticity change de1 = e1 - e1_nominal (the e1 the correction must
remove). A deterministic check
of the boundary models alone compares the pixel areas of one charge image
(GalSim's ``calculate_pixel_areas`` against ours).

GalSim runs with one OpenMP thread: on a loaded 2-core machine its OpenMP
barriers made it 50x slower (see ``docs/benchmarks.rst``); its results do
not depend on the thread count (each batch's photons see fixed boundaries).
Prints and writes ``<out>.txt`` and ``<out>.json``.
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.simulation.stars import StarSimulation, image_moments  # noqa: E402
from lsst_bfdrift.geometry.superpose import moment_maps  # noqa: E402

SENSOR = "lsst_itl_50_8"


def _slope(x, y):
    """Least-squares slope through the origin and its error from the scatter."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    s = np.sum(x * y) / np.sum(x * x)
    r = y - s * x
    return float(s), float(np.sqrt(np.sum(r * r) / max(x.size - 1, 1) / np.sum(x * x)))


def star_photons(flux, *, fwhm=0.7, stamp=31, pixel_scale=0.2, seed=0):
    """Photon positions of one Gaussian star in GalSim's image frame
    (pixel i centred on x = i, i = 1..stamp), centred near the stamp centre
    with a random sub-pixel offset."""
    import galsim
    rng = np.random.default_rng(seed)
    img = galsim.ImageD(stamp, stamp, scale=pixel_scale)
    galsim.Gaussian(fwhm=fwhm).withFlux(flux).drawImage(
        img, method="phot", save_photons=True, rng=galsim.BaseDeviate(int(seed) + 1),
        offset=tuple(rng.uniform(-0.5, 0.5, 2)))
    c = img.true_center
    return np.asarray(img.photons.x) + c.x, np.asarray(img.photons.y) + c.y


def galsim_image(x, y, *, stamp=31, nrecalc=1000, seed=0, qdist=3, sensor=SENSOR):
    """Accumulate photons (GalSim frame) with galsim.SiliconSensor, no diffusion."""
    import galsim
    p = galsim.PhotonArray(x.size)
    p.x = x
    p.y = y
    p.flux = np.ones(x.size)
    sens = galsim.SiliconSensor(sensor, diffusion_factor=0.0, nrecalc=nrecalc, qdist=qdist,
                                rng=galsim.BaseDeviate(int(seed) + 7))
    im = galsim.ImageD(stamp, stamp, scale=0.2)
    sens.accumulate(p, im)
    return im.array.copy()


def our_image(template, x, y, *, stamp=31, nrecalc=1000, layout="shared", seed=0, qdist=None,
              galsim_box=True):
    """Accumulate the same photons with StarSimulation (GalSim frame -> ours: -1)."""
    sim = StarSimulation(template, stamp_size=stamp, update_every=nrecalc, layout=layout,
                         seed=seed, qdist=qdist, galsim_box=galsim_box)
    sim.add(x - 1.0, y - 1.0)
    return sim.image.copy(), sim.nominal_image.copy()


#: GalSim runs: name -> qdist (3 is GalSim's default; 4 = the whole 9 x 9 file)
GALSIM_RUNS = {"galsim_q3": 3, "galsim_q4": 4}


def default_variants(sensor=SENSOR, names=None):
    """Our variants: name -> (template, layout, qdist, galsim_box); ``names``
    keeps only those (all by default)."""
    imported = {}

    def raw():  # imported once, shared by the variants that use it
        if "none" not in imported:
            imported["none"] = import_galsim_sensor(sensor, match="none")
        return imported["none"]

    make = {"match_areas": lambda: (import_galsim_sensor(sensor, match="areas"), "shared",
                                    None, False),
            "match_transfers": lambda: (import_galsim_sensor(sensor, match="transfers"),
                                        "shared", None, False),
            "match_transfers_1e5": lambda: (import_galsim_sensor(
                sensor, match="transfers", transfer_charge=None, transfer_cells=2000),
                "shared", None, False),
            "nearest_pixel": lambda: (raw(), "shared", None, False),
            "galsim_layout_q3_exactbox": lambda: (raw(), "galsim", 3, False),
            "galsim_layout_q3": lambda: (raw(), "galsim", 3, True),
            "galsim_layout_q4": lambda: (raw(), "galsim", None, True)}
    unknown = sorted(set(names or ()) - set(make))
    if unknown:
        raise SystemExit(f"unknown variants {unknown}; choose from {sorted(make)}")
    return {k: f() for k, f in make.items() if names is None or k in names}


def crosscheck(fluxes, *, fwhm=0.7, stamp=31, nrecalc=1000, seed=2015, variants=None,
               galsim_runs=None, progress=False, sensor=SENSOR):
    """Per-star dT/T of each GalSim run and each of our variants; slopes and
    paired ratios (each variant against each GalSim run)."""
    import galsim
    threads = galsim.utilities.get_omp_threads()
    galsim.utilities.set_omp_threads(1)
    variants = variants if variants is not None else default_variants(sensor)
    galsim_runs = galsim_runs if galsim_runs is not None else GALSIM_RUNS
    names = list(galsim_runs) + list(variants)
    seconds = {k: 0.0 for k in names}
    rows = []
    try:
        for k, f in enumerate(fluxes):
            x, y = star_photons(f, fwhm=fwhm, stamp=stamp, seed=seed + 17 * k)
            images = {}
            for name, qd in galsim_runs.items():
                t0 = time.perf_counter()
                images[name] = galsim_image(x, y, stamp=stamp, nrecalc=nrecalc, seed=seed + k,
                                            qdist=qd, sensor=sensor)
                seconds[name] += time.perf_counter() - t0
            nominal = None
            for name, (tpl, layout, qd, gbox) in variants.items():
                t0 = time.perf_counter()
                images[name], nominal = our_image(tpl, x, y, stamp=stamp, nrecalc=nrecalc,
                                                  layout=layout, seed=seed + k, qdist=qd,
                                                  galsim_box=gbox)
                seconds[name] += time.perf_counter() - t0
            mom = {n: image_moments(images[n]) for n in names}
            nom = image_moments(nominal)
            t_nom = nom["T"]
            out = {"flux": float(x.size),
                   "bf_moved": float(np.abs(images[next(iter(galsim_runs))] - nominal).sum() / 2)}
            for v in variants:
                for g in galsim_runs:
                    out[f"moved:{v}/{g}"] = float(np.abs(images[v] - images[g]).sum() / 2)
            out.update({n: mom[n]["T"] / t_nom - 1.0 for n in names})
            out.update({"e1:" + n: mom[n]["e1"] - nom["e1"] for n in names})
            rows.append(out)
            if progress:
                print(f"  star {k + 1}/{len(fluxes)}: flux {x.size:.0f}, dT/T " + ", ".join(
                    f"{n} {out[n]:.5e}" for n in names), file=sys.stderr)
    finally:
        galsim.utilities.set_omp_threads(threads)
    f5 = np.array([r["flux"] for r in rows]) / 1e5
    res = {"sensor": sensor, "n_stars": len(rows), "fwhm": fwhm, "nrecalc": nrecalc,
           "seconds": seconds, "stars": rows, "slopes": {}, "ratios": {}, "e1_slopes": {},
           "e1_ratios": {}}
    for n in names:
        s, e = _slope(f5, [r[n] for r in rows])
        res["slopes"][n] = {"slope": s, "slope_err": e}
        s, e = _slope(f5, [r["e1:" + n] for r in rows])
        res["e1_slopes"][n] = {"slope": s, "slope_err": e}
    for v in variants:
        for g in galsim_runs:
            d, de = _slope(f5, [r[v] - r[g] for r in rows])
            sg = res["slopes"][g]["slope"]
            res["ratios"][f"{v}/{g}"] = {"ratio": 1.0 + d / sg, "ratio_err": de / sg,
                                         "diff_slope": d, "diff_slope_err": de,
                                         "photons_elsewhere": sum(r[f"moved:{v}/{g}"]
                                                                  for r in rows)}
            d, de = _slope(f5, [r["e1:" + v] - r["e1:" + g] for r in rows])
            sg = res["e1_slopes"][g]["slope"]
            res["e1_ratios"][f"{v}/{g}"] = {"ratio": 1.0 + d / sg, "ratio_err": abs(de / sg)}
    res["photons_total"] = float(sum(r["flux"] for r in rows))
    res["photons_moved_by_bf"] = float(sum(r["bf_moved"] for r in rows))
    for r in rows:  # keep the json small: drop the per-pair photon counts
        for key in [k for k in r if k.startswith("moved:")]:
            r.pop(key)
    return res


def area_check(*, stamp=31, peak=2e5, sigma=1.5, sensor=SENSOR):
    """Pixel areas of one Gaussian charge image: GalSim's against ours."""
    import galsim
    jj, ii = np.mgrid[:stamp, :stamp]
    c = stamp // 2 + 0.25
    q = np.round(peak * np.exp(-0.5 * ((ii - c) ** 2 + (jj - c) ** 2) / sigma**2))
    ag = galsim.SiliconSensor(sensor, diffusion_factor=0.0).calculate_pixel_areas(
        galsim.ImageD(q.copy(), scale=0.2)).array
    w = q * ((ii - c) ** 2 + (jj - c) ** 2)
    out = {"charge": float(q.sum()), "galsim_A00": float(ag[stamp // 2, stamp // 2]),
           "galsim_area_sum_minus_npix": float(ag.sum() - stamp**2)}
    for name, ma in (("match_areas", True), ("nearest_pixel", False)):
        a = moment_maps(import_galsim_sensor(sensor, match="areas" if ma else "none"), q).area
        out[name] = {"A00": float(a[stamp // 2, stamp // 2]),
                     "max_abs_area_diff": float(np.abs(a - ag).max()),
                     # change of the r^2-weighted area deficit, the lever of the size change
                     "r2_weighted_deficit_ratio": float(((a - 1) * w).sum() / ((ag - 1) * w).sum())}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n-stars", type=int, default=24)
    ap.add_argument("--fmin", type=float, default=2e5)
    ap.add_argument("--fmax", type=float, default=2e6)
    ap.add_argument("--fwhm", type=float, default=0.7)
    ap.add_argument("--nrecalc", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=2015)
    ap.add_argument("--sensor", default=SENSOR, help="GalSim sensor name")
    ap.add_argument("--variants", nargs="+", default=None,
                    help="our variants to run (default: all)")
    ap.add_argument("--out", default=os.path.join(HERE, "galsim_crosscheck_results"))
    args = ap.parse_args()
    variants = default_variants(args.sensor, args.variants)
    fluxes = np.geomspace(args.fmin, args.fmax, args.n_stars)
    t0 = time.perf_counter()
    res = crosscheck(fluxes, fwhm=args.fwhm, nrecalc=args.nrecalc, seed=args.seed, progress=True,
                     sensor=args.sensor, variants=variants)
    res["wall_seconds"] = time.perf_counter() - t0
    res["areas"] = area_check(sensor=args.sensor)
    lines = [f"GalSim cross-check, {args.sensor}: {res['n_stars']} Gaussian stars "
             f"FWHM {args.fwhm}\", "
             f"flux {args.fmin:.0e}..{args.fmax:.0e} e, same photons, nrecalc = update_every = "
             f"{args.nrecalc}, no diffusion; {res['wall_seconds']:.0f} s"]
    for n, v in res["slopes"].items():
        lines.append(f"  {n:25s} dT/T slope {v['slope'] * 100:.5f} +- {v['slope_err'] * 100:.5f} "
                     f"% per 1e5 e")
    lines.append(f"  paired ratios of the slopes (same photons), ours / GalSim, and photons "
                 f"landing in another pixel than GalSim's (of {res['photons_total']:.0f}; "
                 f"the BF effect moves {res['photons_moved_by_bf']:.0f} in galsim_q3):")
    for n, v in res["ratios"].items():
        lines.append(f"    {n:38s} {v['ratio']:.4f} +- {v['ratio_err']:.4f}   "
                     f"{v['photons_elsewhere']:.0f}")
    lines.append("  ellipticity: de1 slope (per 1e5 e) and paired ratios ours / GalSim:")
    for n, v in res["e1_slopes"].items():
        lines.append(f"    {n:25s} de1 slope {v['slope']:.3e} +- {v['slope_err']:.1e}")
    for n, v in res["e1_ratios"].items():
        lines.append(f"    {n:38s} {v['ratio']:.4f} +- {v['ratio_err']:.4f}")
    a = res["areas"]
    lines.append(f"  areas of one charge image ({a['charge']:.3g} e, peak 2e5): GalSim A00 "
                 f"{a['galsim_A00']:.5f}, area sum - npix {a['galsim_area_sum_minus_npix']:.2e}")
    for name in ("match_areas", "nearest_pixel"):
        b = a[name]
        lines.append(f"    {name:13s} A00 {b['A00']:.5f}, max |A - A_galsim| "
                     f"{b['max_abs_area_diff']:.2e}, r^2-weighted deficit ratio "
                     f"{b['r2_weighted_deficit_ratio']:.4f}")
    lines.append("  seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in res["seconds"].items()))
    text = "\n".join(lines) + "\n"
    print(text, end="")
    write_results(args.out, lines, res, script=__file__, json_default=float, indent=2)


if __name__ == "__main__":
    main()
