"""Does a star field measure what a correction leaves? Fields with a brighter-fatter-free twin.

The star route (:func:`~lsst_bfdrift.calibration.star_fit.calibrate_with_stars`)
trusts the size-flux slope that a field shows after a drift correction. This
script checks that slope against truth. It redraws the star fields of
``benchmarks/stars/calibrate_stars.py`` (same seeds, so the brighter-fatter image
is identical to that script's cached field) with their twin: the same
photons, diffusion, sky and read noise, collected by galsim.SiliconSensor
with no brighter-fatter effect
(:func:`~lsst_bfdrift.simulation.skysim.simulate_star_field`, ``twin=True``).
Each field is corrected by drift with GalSim's own sensor file (imported
with transfer-matched edges; on paired stars it leaves +0.7 % (ITL) and
+1.9 % (e2v) of the size slope), and both images are measured on the same
detections (:class:`~lsst_bfdrift.calibration.star_fit.StarField`). Printed
per field, per 1e5 e:

* the uncorrected size (ln T) and e1 slopes with their bootstrap errors;
* the corrected slopes and the twin's slopes, as % of the uncorrected:
  the twin has no brighter-fatter effect, so its slope is the field's own
  measurement noise (its star sample, photons and sky), which the
  corrected image shares;
* corrected minus twin, as % of the effect (uncorrected minus twin), with
  the error of a straight-line fit to the per-star differences of ln T
  (or e1) against flux: what the correction leaves, with the field's noise
  cancelled.

A field route that measures corrections right shows corrected minus twin
near the paired stars' residual, whatever the corrected slope itself
shows. With ``--templates-from DIR`` the fields are also corrected with the
templates that ``benchmarks/stars/calibrate_stars.py --save-templates DIR``
calibrated (flats-only, flats+stars): corrected minus twin is then the
truth of what those templates leave on a field's stars, with the field's
noise cancelled. The flats+stars template was fitted to these fields'
noisy slopes, so this is a truth check on its training fields, not a
held-out validation (the paired stars of ``calibrate_stars.py`` are). A
last block gives the inverse-variance mean over fields per template::

    python benchmarks/stars/field_twins.py [--sensors lsst_itl_50_8 lsst_e2v_50_8]
        [--fields 0 | --fields lsst_itl_50_8=2,3 lsst_e2v_50_8=0] [--cache /tmp/cst]
        [--templates-from /tmp/cs_templates]

Writes ``benchmarks/stars/field_twins_results.txt`` / ``.json``. Drawing a
2048 x 2048 field of 800 stars with its twin takes about 24 min on one core
(cached in ``--cache``).
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

from calibrate_stars import field_seed, ivw_mean, twin_cache_path  # noqa: E402
from lsst_bfdrift.calibration.star_fit import StarField  # noqa: E402
from lsst_bfdrift.catalogs.slopes import FLUX_UNIT  # noqa: E402
from lsst_bfdrift.simulation.skysim import simulate_star_field  # noqa: E402
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor  # noqa: E402
from lsst_bfdrift.templates.template import DistortionTemplate  # noqa: E402


def twin_field(sensor, k, args):
    """Field k of ``benchmarks/stars/calibrate_stars.py`` with its BF-free twin (cached)."""
    seed = field_seed(sensor, k)
    path = twin_cache_path(sensor, args, seed)
    if os.path.isfile(path):
        d = np.load(path)
        return d["bf"], d["truth"], seed, 0.0
    t0 = time.time()
    f = simulate_star_field((args.field_size,) * 2, args.field_stars, sensor=sensor,
                            flux=(1e4, 1.5e6), sky=1000.0, seed=seed, twin=True,
                            progress=True)
    tmp = path + ".tmp.npz"
    np.savez(tmp, bf=f["image"], truth=f["truth_image"])
    os.replace(tmp, path)
    return f["image"], f["truth_image"], seed, time.time() - t0


def difference_slope(flux, q_corr, q_twin):
    """Slope (per 1e5 e) of the per-star difference against flux, with an
    intercept, and its error from the scatter."""
    x = flux / FLUX_UNIT
    d = q_corr - q_twin
    a = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(a, d, rcond=None)
    r = d - a @ coef
    cov = np.linalg.inv(a.T @ a) * np.sum(r * r) / max(x.size - 2, 1)
    return float(coef[1]), float(np.sqrt(cov[1, 1]))


def sensor_templates(sensor, directory):
    """GalSim's own sensor file (transfer-matched edges) and, when ``directory``
    holds them, the calibrated templates of ``benchmarks/stars/calibrate_stars.py
    --save-templates`` (SENSOR_flats.fits, SENSOR_joint.fits)."""
    out = {"GalSim file": import_galsim_sensor(sensor, match="transfers")}
    for tag, name in (("flats", "flats-only"), ("joint", "flats+stars")):
        path = os.path.join(directory or "", f"{sensor}_{tag}.fits")
        if directory and os.path.isfile(path):
            out[name] = DistortionTemplate.load(path)
    return out


def fields_of(sensor, specs):
    """The field numbers of ``sensor`` in ``--fields`` (k, or SENSOR=k,k)."""
    out = []
    for spec in specs:
        name, _, ks = spec.rpartition("=")
        if name in ("", sensor):
            out += [int(k) for k in ks.split(",") if k]
    return out


_TEMPLATES = {}


def measure_field(job, args):
    """One field and its twin, corrected with each template: (printed lines, JSON row,
    [((sensor, quantity, template), (% of the effect, error))])."""
    sensor, k = job
    if (sensor, args.templates_from) not in _TEMPLATES:  # once per process and sensor
        _TEMPLATES[sensor, args.templates_from] = sensor_templates(sensor, args.templates_from)
    templates = _TEMPLATES[sensor, args.templates_from]
    lines, entries = [], []
    bf_img, twin_img, seed, cost = twin_field(sensor, k, args)
    t0 = time.time()
    bf = StarField(bf_img, name=f"field{k}")
    # the twin measured on the same detections: the same stars, row by row
    twin = StarField(twin_img, name=f"field{k} twin", detections=bf.detections)
    use = bf.usable & twin.usable
    before = bf.slopes(None, use, n_boot=args.n_boot, seed=1)
    free = twin.slopes(None, use, n_boot=args.n_boot, seed=1)
    flux = np.asarray(bf.catalog["flux"].value)[use]
    row = {"sensor": sensor, "field": k, "seed": seed, "n_stars": int(use.sum()),
           "draw_seconds": cost}
    lines.append(f"{sensor} field {k} (seed {seed}, {int(use.sum())} stars"
                 + (f", drawn in {cost:.0f} s" if cost else ", cached") + ")")
    for q, col in (("size", "T"), ("e1", "e1")):
        b = before[q][0]
        effect = b - free[q][0]
        row[q] = {"before": before[q], "twin": free[q], "effect": effect, "templates": {}}
        lines.append(f"  {q:4s}: uncorrected {b:+.3e} +- {before[q][1]:.1e}; twin (no BF) "
                     f"{free[q][0]:+.3e} ({100 * free[q][0] / b:+.1f} % of uncorrected)")
        qt = np.asarray(getattr(twin.catalog[col], "value", twin.catalog[col]), float)[use]
        for name, tpl in templates.items():
            corr = bf.slopes(tpl, use, n_boot=args.n_boot, seed=1)
            cat_c = bf.corrected_catalog(tpl)
            qc = np.asarray(getattr(cat_c[col], "value", cat_c[col]), float)[use]
            d, d_err = (difference_slope(flux, np.log(qc), np.log(qt)) if q == "size"
                        else difference_slope(flux, qc, qt))
            row[q]["templates"][name] = {"corrected": corr[q],
                                         "corrected_minus_twin": (d, d_err)}
            entries.append(((sensor, q, name), (100 * d / effect, 100 * d_err / abs(effect))))
            lines.append(f"        {name:12s} corrected {corr[q][0]:+.3e} "
                         f"({100 * corr[q][0] / b:+.1f} +- {100 * corr[q][1] / abs(b):.1f} %); "
                         f"corrected - twin per star {d:+.2e} +- {d_err:.1e} "
                         f"({100 * d / effect:+.1f} +- {100 * d_err / abs(effect):.1f}"
                         " % of the effect)")
    row["measure_seconds"] = time.time() - t0
    return lines, row, entries


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+", default=["lsst_itl_50_8", "lsst_e2v_50_8"])
    ap.add_argument("--fields", nargs="+", default=["0"],
                    help="field numbers of benchmarks/stars/calibrate_stars.py: k (every sensor) "
                         "or "
                         "SENSOR=k,k (that sensor)")
    ap.add_argument("--field-stars", type=int, default=800)
    ap.add_argument("--field-size", type=int, default=2048)
    ap.add_argument("--n-boot", type=int, default=100)
    ap.add_argument("--cache", default="/tmp/cst")
    ap.add_argument("--templates-from", metavar="DIR",
                    help="also correct with DIR/SENSOR_flats.fits and DIR/SENSOR_joint.fits "
                         "(benchmarks/stars/calibrate_stars.py --save-templates)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="fields measured (and drawn) in parallel processes")
    ap.add_argument("--out", default=os.path.join(HERE, "field_twins_results"))
    args = ap.parse_args(argv)
    os.makedirs(args.cache, exist_ok=True)
    lines, rec = [], {"machine": f"{platform.machine()}, {os.cpu_count()} cores", "fields": []}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    say(f"Star fields with a brighter-fatter-free twin ({args.field_size}^2 px, "
        f"{args.field_stars} stars, seeds of benchmarks/stars/calibrate_stars.py), corrected by "
        f"drift with GalSim's own sensor file"
        + (" and the calibrated templates" if args.templates_from else "")
        + f"; slopes per 1e5 e; {rec['machine']}")
    jobs = [(sensor, k) for sensor in args.sensors for k in fields_of(sensor, args.fields)]
    if args.jobs > 1 and len(jobs) > 1:
        from concurrent.futures import ProcessPoolExecutor
        with ProcessPoolExecutor(min(args.jobs, len(jobs))) as pool:
            results = list(pool.map(measure_field, jobs, [args] * len(jobs)))
    else:
        results = [measure_field(job, args) for job in jobs]
    summary = {}
    for out_lines, row, entries in results:  # in the order of --sensors and --fields
        for ln in out_lines:
            say(ln)
        rec["fields"].append(row)
        for key, v in entries:
            summary.setdefault(key, []).append(v)
    for sensor in args.sensors:  # the twins' slopes against zero: the fields' noise
        rows = [r for r in rec["fields"] if r["sensor"] == sensor]
        if len(rows) > 1:
            for q in ("size", "e1"):
                chi2 = float(sum((r[q]["twin"][0] / r[q]["twin"][1]) ** 2 for r in rows))
                say(f"{sensor} twins (no BF), {q} slopes against zero with their bootstrap "
                    f"errors: chi2 {chi2:.1f} / {len(rows)}")
    if summary:
        say("Mean over fields (inverse-variance), corrected - twin, % of the effect:")
    rec["means"] = []
    for (sensor, q, name), v in summary.items():
        pct, err = np.array(v).T
        m, m_err, chi2 = ivw_mean(pct, err)
        rec["means"].append({"sensor": sensor, "quantity": q, "template": name,
                             "n_fields": int(pct.size), "mean": m, "mean_err": m_err,
                             "chi2": chi2})
        say(f"  {sensor} {q:4s} {name:12s} {m:+6.1f} +- {m_err:.1f} % ({pct.size} fields, "
            f"chi2 {chi2:.1f} / {pct.size - 1})")
    write_results(args.out, lines, rec, script=__file__, json_default=float)
    return 0


if __name__ == "__main__":
    sys.exit(main())
