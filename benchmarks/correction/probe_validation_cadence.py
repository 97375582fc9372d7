r"""Probe: do validate-stars residuals depend on GalSim's boundary-update cadence?

Investigation script (no library change). Re-draws the bright Moffat stars of
``benchmarks/correction/validate_stars.py`` (same seed 20151, same 200-star random
sequence, same per-star seeds; only stars with flux >= ``--fmin`` are
simulated) through ``galsim.SiliconSensor`` (BF twin strength 1 and BF-free
twin strength 1e-9, same photons and sensor seed) with

* a slow cadence: ``updates=100``, ``min_nrecalc=1e4`` (GalSim's own
  ``nrecalc`` default; about 100 boundary updates per exposure);
* the cadence of validate-stars (the default of
  :func:`~lsst_bfdrift.validation.stars.draw_star_pairs` and of
  ``bfdrift validate-stars``): ``updates=1000``, ``min_nrecalc=100``
  (about 1000 boundary updates per exposure);
* a faster one: ``updates=3000``, ``min_nrecalc=30`` (convergence check);
* GalSim ``qdist=4`` (boundary changes computed one pixel further out than
  GalSim's default 3) at the 100- and the 1000-update cadence
  (``updates:min_nrecalc:qdist``);

and measures the residual size and e1 slopes of every correction method with
the area-matched GalSim template, plus (same pairs, no redraw) the template
imported with ``match="none"``. Run from the repository root::

    python benchmarks/correction/probe_validation_cadence.py --cadences \
        100:1e4 1000:100 3000:30 1000:100:4 100:1e4:4
    python benchmarks/correction/probe_validation_cadence.py --qdist-templates --cadences \
        1000:100:4 100:1e4:4

(the second call re-reads the pairs saved in /tmp by the first, and corrects
the qdist=4 pairs with the template area-matched to GalSim qdist=4). The
"paired" lines are slopes of per-star differences between two runs of the
same stars (or two methods on the same images), which cancel the star-to-star
scatter that dominates the single-run errors. Writes
``benchmarks/correction/probe_validation_cadence_results.txt`` / ``.json``.
"""

import argparse
import contextlib
import functools
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import command_line, write_results  # noqa: E402

from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.utils.io import write_json, write_text  # noqa: E402
from lsst_bfdrift.simulation.galsim_twins import accumulate_twins, shoot_stamp_photons, sky_box  # noqa: E402
from lsst_bfdrift.simulation.stars import make_psf  # noqa: E402
from lsst_bfdrift.validation.stars import per_star_residuals, residual_slopes  # noqa: E402
from lsst_bfdrift.validation.stars import slope_through_origin as _slope  # noqa: E402

METHODS = ("coulton18", "astier23", "drift")


@contextlib.contextmanager
def galsim_qdist(qdist):
    """Temporarily make galsim.SiliconSensor default to ``qdist`` (probe only)."""
    import galsim
    orig = galsim.SiliconSensor
    if qdist is not None:
        galsim.SiliconSensor = functools.partial(orig, qdist=int(qdist))
    try:
        yield
    finally:
        galsim.SiliconSensor = orig


def bright_pairs(*, n_stars=200, fmin=3e5, nmax=None, updates=100, min_nrecalc=1e4, qdist=None,
                 sensor="lsst_itl_50_8", fwhm=(0.6, 0.9), emax=0.05, flux=(1e4, 1.5e6),
                 sky=1000.0, stamp=41, pixel_scale=0.2, seed=20151, sky_radius=8):
    """Same random sequence as validation.draw_star_pairs (Moffat, sky through the sensor),
    simulating only stars with flux >= fmin."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n_stars):
        f = float(np.exp(rng.uniform(np.log(flux[0]), np.log(flux[1]))))
        fw = float(rng.uniform(*fwhm))
        e = float(rng.uniform(0, emax))
        beta = float(rng.uniform(0, 180))
        s1, s2, s3 = (int(v) for v in rng.integers(1, 2**30, 3))
        offset = rng.uniform(-0.5, 0.5, 2)
        if f < fmin or (nmax is not None and len(out) >= nmax):
            continue
        prof = make_psf("moffat", fw, e=e, beta=beta).withFlux(f)
        rng_sky = np.random.default_rng(s3)
        x, y, fl = shoot_stamp_photons(prof, stamp, pixel_scale=pixel_scale, seed=s1, offset=offset)
        lo, hi, inner = sky_box(stamp, sky_radius)
        with galsim_qdist(qdist):
            images, _ = accumulate_twins(
                x, y, fl, (1.0, 1e-9), sensor=sensor, seed=s2, stamp=stamp,
                pixel_scale=pixel_scale, sky=sky, box=(lo, hi), rng=rng_sky, updates=updates,
                min_nrecalc=min_nrecalc)
        noise = rng_sky.poisson(sky, (stamp, stamp)).astype(float)
        outside = np.ones((stamp, stamp), bool)
        outside[inner, inner] = False
        noise = np.where(outside, noise, 0.0)
        out.append({"bf": images[0] + noise, "truth": images[1] + noise, "flux": f, "fwhm": fw,
                    "index": i})
    return out


def table(title, res, lines):
    unc = res["uncorrected"]["size_slope"]
    uerr = res["uncorrected"]["e_slope"]
    lines.append(title)
    for k, v in res.items():
        lines.append(
            f"  {k:12s} size slope {v['size_slope']:+.3e} +- {v['size_slope_err']:.1e} "
            f"({100 * v['size_slope'] / unc:+6.2f} +- {100 * v['size_slope_err'] / unc:.2f}"
            f" % of uncorrected)  e1 slope {v['e_slope']:+.2e} +- {v['e_slope_err']:.1e} "
            f"({100 * v['e_slope'] / uerr:+6.1f} +- {100 * v['e_slope_err'] / abs(uerr):.1f} %)"
            f"  n={v['n_stars']}")
    d, a = res["drift"]["size_slope"], res["astier23"]["size_slope"]
    lines.append(f"  |drift|/|astier23| (size) = {abs(d) / abs(a):.2f}")
    print("\n".join(lines[-(len(res) + 2):]), flush=True)


def per_star_rows(pairs, template, sky=1000.0):
    """Per-star residuals of each method against the twin
    (:func:`lsst_bfdrift.validation.stars.per_star_residuals`; NaN where unmeasurable)."""
    return per_star_residuals(pairs, template, methods=METHODS, sky=sky)


def paired(base, other, label, lines):
    """Slope (per 1e5 e) of the per-star change between two runs of the same stars."""
    fb, rb = base
    fo, ro = other
    ok = np.isfinite(fb) & np.isfinite(fo)
    unc = _slope(fb[ok], rb["uncorrected"][ok, 0])[0]
    ue1 = _slope(fb[ok], rb["uncorrected"][ok, 1])[0]
    lines.append(f" paired change {label} (same {ok.sum()} stars; % of the first run's "
                 f"uncorrected slope)")
    res = {}
    for k in rb:
        ds, dse = _slope(fb[ok], ro[k][ok, 0] - rb[k][ok, 0])
        de, dee = _slope(fb[ok], ro[k][ok, 1] - rb[k][ok, 1])
        res[k] = {"size": ds, "size_err": dse, "e1": de, "e1_err": dee}
        lines.append(f"  {k:12s} d(size slope) {100 * ds / unc:+6.2f} +- {100 * dse / unc:.2f} %"
                     f"   d(e1 slope) {100 * de / ue1:+6.1f} +- {100 * dee / abs(ue1):.1f} %")
    print("\n".join(lines[-(len(rb) + 1):]), flush=True)
    return res


def qdist_templates(args):
    """Saved pairs drawn with GalSim qdist=q, corrected with the template area-matched to q."""
    with open(args.out + ".json") as fh:
        out = json.load(fh)
    with open(args.out + ".txt") as fh:
        lines = fh.read().splitlines()
    for cad in args.cadences:
        parts = cad.split(":")
        if len(parts) < 3:
            continue
        qd = int(parts[2])
        d = np.load(f"/tmp/probe5_pairs_{cad.replace(':', '_')}.npz")
        pairs = [{"bf": b, "truth": t, "flux": float(f)}
                 for b, t, f in zip(d["bf"], d["truth"], d["flux"])]
        with galsim_qdist(qd):
            tpl_q = import_galsim_sensor("lsst_itl_50_8", match="areas")
        tag = f"pairs of {cad}, template match='areas' with GalSim qdist={qd}"
        rows_q = per_star_rows(pairs, tpl_q)
        res = residual_slopes(*rows_q)
        table(f" {tag}", res, lines)
        out["runs"][cad][f"match_areas_qdist{qd}"] = res
        tpl_m = import_galsim_sensor("lsst_itl_50_8", match="areas")
        out["runs"][cad][f"paired_template_qdist{qd}"] = paired(
            per_star_rows(pairs, tpl_m), rows_q,
            f"template qdist={qd}-matched minus qdist=3-matched, {cad}", lines)
    # the files now come from the previous run's command(s) and this one
    heads = ([ln for ln in lines if ln.startswith("# command: ")]
             + [f"# command: {command_line(__file__)}"])
    lines = heads + [ln for ln in lines if not ln.startswith("# command: ")]
    out["command"] = " && ".join(h[len("# command: "):] for h in heads)
    write_json(args.out + ".json", out, indent=2)
    write_text(args.out + ".txt", "\n".join(lines) + "\n")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fmin", type=float, default=3e5)
    ap.add_argument("--nmax", type=int, default=None)
    ap.add_argument("--cadences", nargs="+", default=["100:1e4", "1000:100"],
                    help="updates:min_nrecalc[:qdist] per run")
    ap.add_argument("--out", default=os.path.join(HERE, "probe_validation_cadence_results"))
    ap.add_argument("--qdist-templates", action="store_true",
                    help="only: re-evaluate the saved qdist=4 pairs (from a previous run) with "
                         "the template area-matched to GalSim qdist=4, appending to the results")
    args = ap.parse_args()
    if args.qdist_templates:
        return qdist_templates(args)
    tpl_m = import_galsim_sensor("lsst_itl_50_8", match="areas")
    tpl_n = import_galsim_sensor("lsst_itl_50_8", match="none")
    lines = [f"Moffat stars of validate_stars (seed 20151, 200-star sequence), flux >= "
             f"{args.fmin:g} e, sky 1000 e through the sensor, lsst_itl_50_8"]
    out = {"fmin": args.fmin, "runs": {}}
    for cad in args.cadences:
        parts = cad.split(":")
        upd, mn = float(parts[0]), float(parts[1])
        qd = int(parts[2]) if len(parts) > 2 else None
        t0 = time.process_time()
        w0 = time.time()
        pairs = bright_pairs(fmin=args.fmin, nmax=args.nmax, updates=upd, min_nrecalc=mn,
                             qdist=qd)
        t_draw, w_draw = time.process_time() - t0, time.time() - w0
        t0 = time.process_time()
        rows = per_star_rows(pairs, tpl_m)
        res_m = residual_slopes(*rows)
        t_val = time.process_time() - t0
        tag = f"updates={upd:g}, min_nrecalc={mn:g}, qdist={qd or 3}"
        lines.append(f"[{tag}] draw {t_draw:.0f} s CPU ({w_draw:.0f} s wall), "
                     f"validate {t_val:.0f} s CPU, {len(pairs)} stars "
                     f"(flux {min(p['flux'] for p in pairs):.3g}-"
                     f"{max(p['flux'] for p in pairs):.3g} e)")
        table(f" template match='areas', {tag}", res_m, lines)
        run = {"updates": upd, "min_nrecalc": mn, "qdist": qd or 3, "draw_cpu_s": t_draw,
               "validate_cpu_s": t_val, "match_areas_true": res_m,
               "indices": [p["index"] for p in pairs]}
        rows_n = per_star_rows(pairs, tpl_n)
        res_n = residual_slopes(*rows_n)
        table(f" template match='none', {tag}", res_n, lines)
        run["match_areas_false"] = res_n
        fl, rr = rows
        ok = np.isfinite(fl)
        unc = _slope(fl[ok], rr["uncorrected"][ok, 0])[0]
        ue1 = _slope(fl[ok], rr["uncorrected"][ok, 1])[0]
        for m in ("drift", "coulton18"):
            ds, dse = _slope(fl[ok], rr[m][ok, 0] - rr["astier23"][ok, 0])
            de, dee = _slope(fl[ok], rr[m][ok, 1] - rr["astier23"][ok, 1])
            run[f"{m}_minus_astier23"] = {"size": ds, "size_err": dse, "e1": de, "e1_err": dee}
            lines.append(f" paired {m} minus astier23 residual (match='areas', {tag}): size "
                         f"{100 * ds / unc:+.2f} +- {100 * dse / unc:.2f} %, e1 "
                         f"{100 * de / ue1:+.1f} +- {100 * dee / abs(ue1):.1f} % of uncorrected")
            print(lines[-1], flush=True)
        run["paired_template"] = paired(rows, rows_n,
                                        f"template match='none' minus 'areas', {tag}", lines)
        if cad != args.cadences[0]:
            run["paired_vs_first"] = paired(first_rows, rows,
                                            f"{tag} minus {args.cadences[0]}", lines)
        else:
            first_rows = rows
        out["runs"][cad] = run
        np.savez_compressed(f"/tmp/probe5_pairs_{cad.replace(':', '_')}.npz",
                            bf=np.array([p["bf"] for p in pairs]),
                            truth=np.array([p["truth"] for p in pairs]),
                            flux=np.array([p["flux"] for p in pairs]))
        write_results(args.out, lines, out, script=__file__, indent=2)


if __name__ == "__main__":
    main()
