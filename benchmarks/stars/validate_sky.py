"""Sky validation on a GalSim SiliconSensor star field (issue 7).

A 1024 x 1024 field of 160 Moffat stars (FWHM 0.7" to 0.95" across x, PSF
ellipticity varying over the field, 1e4 to 1.5e6 e, sky 800 e, read noise
5 e) is drawn by galsim.SiliconSensor (lsst_itl_50_8) with strength 1, and
with the same photons, diffusion and noise at strength 1e-9 (paired truth).
The sky around each star is collected through the sensor with its photons
(``simulate_star_field`` defaults). The corrections use the template
imported from the same sensor file (``import_galsim_sensor``), not
the package default.

1. ``validate_sky`` (no truth used) on the BF image with both correction
   routes, and on the BF-free twin (the null: no detection expected).
2. With the paired truth: slopes against flux of T / T_truth - 1 and of
   e1 - e1_truth for the recorded, catalog-corrected (history 1/2 and, as
   a check of the time-history argument, 1) and pixel-corrected (Task,
   method drift) catalogs, and the star-by-star agreement of the routes.

Run from the repository root::

    python benchmarks/stars/validate_sky.py [--size 1024] [--n-stars 160]

Prints and writes ``benchmarks/stars/validate_sky_results.txt`` / ``.json`` and the
figure ``docs/_static/sky_validation.png``.
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
from lsst_bfdrift.catalogs.catalog import measure_stars  # noqa: E402
from lsst_bfdrift.validation.shape_correction import correct_catalog  # noqa: E402
from lsst_bfdrift.validation.sky import validate_sky  # noqa: E402
from lsst_bfdrift.simulation.skysim import simulate_star_field  # noqa: E402
from lsst_bfdrift.correction.task import BrighterFatterDriftConfig, BrighterFatterDriftTask  # noqa: E402


def _slope(f, v):
    """Least-squares slope through the origin and its error from the scatter."""
    s = np.sum(f * v) / np.sum(f * f)
    r = v - s * f
    return float(s), float(np.sqrt(np.sum(r * r) / max(len(f) - 1, 1) / np.sum(f * f)))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--n-stars", type=int, default=160)
    p.add_argument("--seed", type=int, default=2026)
    args = p.parse_args(argv)
    lines = []

    def say(s=""):
        print(s, flush=True)
        lines.append(s)

    t0 = time.perf_counter()
    field = simulate_star_field((args.size, args.size), args.n_stars, strength=1.0, twin=True,
                                seed=args.seed, progress=True)
    t_sim = time.perf_counter() - t0
    bf, truth_img = field["image"], field["truth_image"]
    tpl = import_galsim_sensor("lsst_itl_50_8", match="transfers")
    say(f"field {args.size} x {args.size}, {args.n_stars} stars, galsim.SiliconSensor "
        f"lsst_itl_50_8 strength 1 (+ paired strength 1e-9 twin): drawn in {t_sim:.0f} s")

    out = {"size": args.size, "n_stars": args.n_stars, "seed": args.seed}
    t0 = time.perf_counter()
    v = validate_sky(bf, template=tpl, route="both")
    t_val = time.perf_counter() - t0
    vnull = validate_sky(truth_img, template=tpl, route="catalog")
    out["validate_sky_bf"] = v.summary
    out["validate_sky_null"] = vnull.summary
    say(f"\n1. validate_sky without truth ({t_val:.1f} s, both routes; {v.summary['n_stars_used']}"
        f" of {v.summary['n_detections']} detections used)")
    say("   slopes per 1e5 e (size: fractional T), +- error, z")
    rows = [("BF image, before", v.summary["before"])]
    rows += [(f"BF image, {r} route", v.summary["after"][r]) for r in ("catalog", "pixel")]
    rows += [("BF-free twin, before", vnull.summary["before"]),
             ("BF-free twin, catalog route", vnull.summary["after"]["catalog"])]
    for name, rel in rows:
        say(f"   {name:30s} " + "  ".join(
            f"{k} {rel[k]['slope']:+.2e} +- {rel[k]['slope_err']:.1e} (z {rel[k]['z']:+.1f})"
            for k in ("size", "e1", "e2")))
    say(f"   size vs magnitude (LSST style), BF image: before "
        f"{v.summary['before']['size_mag']['slope']:+.2e} +- "
        f"{v.summary['before']['size_mag']['slope_err']:.1e} per mag, catalog route "
        f"{v.summary['after']['catalog']['size_mag']['slope']:+.2e}")
    say(f"   verdict (BF image): {v.summary['verdict']}")
    say(f"   verdict (BF-free twin, uncorrected): bf_detected_before = "
        f"{vnull.summary['bf_detected_before']} (z = {vnull.summary['before']['size']['z']:+.1f})")

    # 2. paired truth
    cat = v.catalog
    truth = measure_stars(truth_img)
    t0 = time.perf_counter()
    cat_half = correct_catalog(cat, bf, template=tpl, history=0.5)
    t_cat = time.perf_counter() - t0
    cat_one = correct_catalog(cat, bf, template=tpl, history=1.0)
    t0 = time.perf_counter()
    res = BrighterFatterDriftTask(config=BrighterFatterDriftConfig(compute_geometry=False),
                                  template=tpl).run(bf)
    pix = measure_stars(res.exposure)
    t_pix = time.perf_counter() - t0

    def match(c):
        return np.array([int(np.argmin(np.hypot(c["x"].value - x, c["y"].value - y)))
                         for x, y in zip(cat["x"].value, cat["y"].value)])

    it, ip = match(truth), match(pix)
    ok = cat["use"] & truth["use"][it] & pix["use"][ip] & (np.asarray(cat["snr"]) > 30)
    f = cat["flux"].value[ok] / 1e5
    tt = truth["T"].value[it][ok]
    e1t = np.asarray(truth["e1"])[it][ok]
    e2t = np.asarray(truth["e2"])[it][ok]
    variants = {"recorded": cat, "catalog (history 1/2)": cat_half,
                "catalog (history 1)": cat_one, "pixel (Task drift)": pix}
    idx = {"recorded": None, "catalog (history 1/2)": None, "catalog (history 1)": None,
           "pixel (Task drift)": ip}
    say(f"\n2. against the paired BF-free truth ({int(ok.sum())} stars, SNR > 30): slopes per "
        "1e5 e through the origin")
    out["paired"] = {}
    base = None
    for name, c in variants.items():
        sel = (lambda a: a[idx[name]][ok]) if idx[name] is not None else (lambda a: a[ok])
        s_t = _slope(f, sel(c["T"].value) / tt - 1)
        s_1 = _slope(f, sel(np.asarray(c["e1"])) - e1t)
        s_2 = _slope(f, sel(np.asarray(c["e2"])) - e2t)
        base = s_t[0] if base is None else base
        out["paired"][name] = {"size_slope": s_t[0], "size_slope_err": s_t[1],
                               "e1_slope": s_1[0], "e1_slope_err": s_1[1],
                               "e2_slope": s_2[0], "e2_slope_err": s_2[1],
                               "size_fraction_of_recorded": s_t[0] / base}
        say(f"   {name:24s} size {s_t[0]:+.3e} +- {s_t[1]:.1e} ({100 * s_t[0] / base:+6.1f} %)"
            f"  e1 {s_1[0]:+.2e} +- {s_1[1]:.1e}  e2 {s_2[0]:+.2e} +- {s_2[1]:.1e}")
    d_cat = (cat_half["T"].value - cat["T"].value)[ok]
    d_pix = (pix["T"].value[ip] - cat["T"].value)[ok]
    bright = f > 3.0
    rel = (d_pix[bright] - d_cat[bright]) / np.abs(d_cat[bright])
    out["route_agreement"] = {"n_bright": int(bright.sum()),
                              "median_rel_diff_dT": float(np.median(rel)),
                              "rms_rel_diff_dT": float(np.sqrt(np.mean(rel ** 2))),
                              "mean_dT_over_T_catalog": float(np.mean(d_cat[bright] / tt[bright])),
                              "mean_dT_over_T_pixel": float(np.mean(d_pix[bright] / tt[bright]))}
    say(f"   route agreement, {int(bright.sum())} stars > 3e5 e: correction dT pixel vs catalog "
        f"median relative difference {np.median(rel):+.3f}, rms {np.sqrt(np.mean(rel ** 2)):.3f}; "
        f"mean dT/T {out['route_agreement']['mean_dT_over_T_catalog']:+.2e} (catalog), "
        f"{out['route_agreement']['mean_dT_over_T_pixel']:+.2e} (pixel)")
    out["timing_s"] = {"simulation": t_sim, "validate_sky_both": t_val,
                       "catalog_correction": t_cat, "pixel_task_plus_catalog": t_pix}
    say(f"\ntimes: catalog-level correction {t_cat:.1f} s (maps + moments of "
        f"{len(cat)} stars), pixel-level Task + new catalog {t_pix:.1f} s")

    from lsst_bfdrift.utils.plotting import save_figure
    from lsst_bfdrift.validation.plots import plot_sky_validation
    png = os.path.join(HERE, "..", "..", "docs", "_static", "sky_validation.png")
    save_figure(plot_sky_validation(v), png)
    write_results(os.path.join(HERE, "validate_sky_results"), lines, out, script=__file__,
                  json_default=float, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
