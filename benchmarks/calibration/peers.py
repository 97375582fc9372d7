"""This package's route against LSST's two, from the same sensor data, on the same stars.

The chain LSST runs (a-matrix -> model -> shifts or kernel -> correction) and
this package's, side by side (:mod:`lsst_bfdrift.calibration.routes`):

* ``electrostatic``: the drift model calibrated to the a-matrix
  (:func:`~lsst_bfdrift.calibration.tuning.calibrate`), corrected by ``drift``;
* ``astier23`` (DP2): the Astier & Regnault 2023 model fitted to the
  a-matrix, its per-edge shifts, corrected by ``astier23``;
* ``coulton18`` (DP1): the kernel of the measured a-matrix, corrected by
  ``coulton18``;
* for reference, GalSim's own file (the true template) corrected by ``drift``;
* to tell the links of the chain apart (template against correction
  method): the Astier & Regnault template corrected by ``drift``, and the
  true template corrected by ``astier23``; the calibrated template
  cropped to GalSim's window (``electrostatic, window``: GalSim's files move
  no boundary beyond lag 3, so this is what the model's far field does); and
  GalSim's file matched to its own pixel areas, the a-matrix, instead of its
  photons' transfers (``true template (areas)``: what a perfect area model
  would leave on GalSim's stars).

Inputs per GalSim sensor model (lags 0..``--lags``, default 3: GalSim's
sensor files stop about 4 px from the aggressor, so its a_ij beyond lag 3
describe the file's window, not a sensor):

(a) ``noise-free``: GalSim's own a-matrix
    (:func:`~lsst_bfdrift.simulation.galsim_twins.galsim_acoeffs`) with
    cp_pipe-scale errors, 3 % of each a_ij plus 1e-9 per electron (about 1 %
    of a01);
(b) ``draw k``: that a-matrix plus Gaussian noise of those errors (seeded per
    sensor and draw);
(c) ``flats`` (``--flats``): a-matrix fitted to GalSim flat pairs, every flat
    its own exposure (:func:`~lsst_bfdrift.simulation.flats.simulate_flat_pairs`,
    engine 'galsim').

Every route corrects the same paired GalSim stars (Moffat and Kolmogorov,
drawn by galsim.SiliconSensor with a no-BF twin; the stars of
``calibrate_sensor.py``). Printed, as % of the uncorrected slope: size, e1
and e2 left (e2, which has no brighter-fatter slope of its own, in % of the
uncorrected e1 slope) with errors from the stars, and the paired differences between
routes (per-star differences: the stars' scatter cancels; the package's route
against each LSST route and against the true template). Each route states
a precision from its own input errors: the rms difference between the
corrected slopes with ``--draws-stated`` templates drawn from them (the
calibrated template's stored uncertainty; the Astier & Regnault fit's
parameter covariance; the a-matrix errors through the kernel) and with the
route's own template (as the Task's ``uncertainty_draws`` state the flux
moved; the spread among few draws alone misses their offset); its coverage
is the fraction of cases (sensor x input x PSF x size, e1) whose residual
lies within that precision combined with the stars' error. The residual is
the calibration's error plus the correction method's own floor (what the
method leaves with the truth: GalSim's file, or for the kernel the kernel of
GalSim's noise-free a-matrix), and a precision drawn from the input errors
states only the first: a second coverage compares it with the calibration
error alone, the route's residual minus its method's with the truth, paired
on the same stars. The electrostatic route's precision is given twice: with
the template's whole stored uncertainty (the a_ij errors and the fitted
parameters' modes beyond the areas,
:func:`~lsst_bfdrift.calibration.tuning.parameter_modes`) and from the
a_ij errors alone (``electrostatic, a_ij errors alone``; the same seeds).
Run::

    python benchmarks/calibration/peers.py [--sensors ...] [--lags 3] [--draws 3]
        [--n-stars 200 [N ...]] [--pairs CACHE_PREFIX] [--flats] [--out PREFIX]
"""

import argparse
import json
import os
import sys
import time
import zlib

import numpy as np

from calibrate_sensor import flats_table, star_pairs

from lsst_bfdrift.calibration.astier23_model import Astier23Parameters, astier23_shifts
from lsst_bfdrift.calibration.routes import MODELS, ROUTE_METHODS, calibrate_route
from lsst_bfdrift.calibration.fit_model import MODEL_NUMERICS
from lsst_bfdrift.ptc.acoeffs import AcoeffTable, near_field_response
from lsst_bfdrift.simulation.galsim_twins import galsim_acoeffs
from lsst_bfdrift.templates.edge_shifts import template_from_edge_shifts
from lsst_bfdrift.templates.galsim_io import import_galsim_sensor
from lsst_bfdrift.templates.refine import (combine_templates, curl_free_template, draw_templates,
                                          template_difference, without_parameter_modes)
from lsst_bfdrift.utils.errors import InputError
from lsst_bfdrift.validation.stars import per_star_residuals, slope_through_origin

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402
REPO = os.path.dirname(os.path.dirname(HERE))

#: cp_pipe-scale errors: relative part and floor (per electron).
REL_ERROR, ERROR_FLOOR = 0.03, 1e-9
#: Quantities compared: column of per_star_residuals' rows, name.
QUANTITIES = ((0, "size"), (1, "e1"), (2, "e2"))
#: What each route's calibration aims at: its correction method with the truth
#: (GalSim's file; for the kernel, the kernel of GalSim's noise-free a-matrix).
#: The route's residual minus this one's, paired on the same stars, is the error
#: its calibration makes; the rest is the correction method's own floor.
CALIBRATION_REFERENCE = {"electrostatic": "true template",
                         "astier23": "true template, astier23",
                         "coulton18": "coulton18, GalSim's a-matrix"}


def amatrix_inputs(sensor, lags, draws):
    """(name, AcoeffTable) of GalSim's noise-free a-matrix and its noisy draws."""
    a = galsim_acoeffs(sensor, lags)
    sigma = REL_ERROR * np.abs(a) + ERROR_FLOOR
    out = [("noise-free", AcoeffTable(a, sigma, source=f"GalSim {sensor} a-matrix"))]
    rng = np.random.default_rng(zlib.crc32(f"peers:{sensor}".encode()))
    for k in range(draws):
        out.append((f"draw {k}", AcoeffTable(a + sigma * rng.standard_normal(a.shape), sigma,
                                             source=f"GalSim {sensor} a-matrix, draw {k}")))
    return a, out


def moved_window(template):
    """Smallest odd side of the central block that holds every boundary the
    template moves (7 for GalSim's files: they move nothing beyond lag 3)."""
    for m in range(1, template.size + 1, 2):
        inner = template.cropped(m)
        if all(np.abs(full).sum() <= np.abs(part).sum() * (1 + 1e-12) for full, part in (
                (template.vedge_d, inner.vedge_d), (template.hedge_d, inner.hedge_d),
                (template.corner_d, inner.corner_d))):
            return m
    return template.size


#: The electrostatic template's areas (its curl-free part) with the divergence-free
#: part of the Astier & Regnault template: which link of the chain loses e1.
HYBRID = "electrostatic areas, astier23 curl"

#: The electrostatic route's stated precision from its a_ij errors alone (its
#: template's uncertainty without the parameter modes), beside the full one.
AREAS_ONLY = "electrostatic, a_ij errors alone"
STATED_ROUTE = {AREAS_ONLY: "electrostatic"}


def areas_only(template):
    """A copy of a calibrated template whose stored uncertainty has no parameter modes."""
    return combine_templates(template, [], [], meta={
        **template.meta, "calibration": without_parameter_modes(template.meta.get("calibration"))})


def stated_templates(route, table, n, seed):
    """Templates drawn from the route's own input uncertainty (its stated precision)."""
    rng = np.random.default_rng(seed)
    if route.model == "electrostatic":
        return draw_templates(route.template, n, seed=seed)
    if route.model == "astier23":
        m = route.product
        names = list(m.free_params)
        mean = np.array([m.fit_params[k] for k in names])
        out = []
        fit_range = m.fit_range
        base = route.template.meta["astier23_fit"]["params"]
        for x in rng.multivariate_normal(mean, m.covariance, size=n):
            p = Astier23Parameters(**{**base, **dict(zip(names, x))})
            out.append(template_from_edge_shifts(*astier23_shifts(p, fit_range - 1),
                                                 size=route.template.size))
        return out
    out = []
    for _ in range(n):
        noisy = AcoeffTable(table.a + table.sigma * rng.standard_normal(table.a.shape),
                            table.sigma)
        out.append(calibrate_route(noisy, "coulton18").template)
    return out


def slopes(fluxes, rows):
    """{quantity: (slope, error)} of per-star rows, measurable stars."""
    ok = np.isfinite(fluxes)
    return {q: slope_through_origin(fluxes[ok], rows[ok, col]) for col, q in QUANTITIES}, ok


def paired(res, a, b, fl, ok, den):
    """{quantity: (slope, error)} in % of the paired per-star difference a - b (the
    stars' scatter cancels)."""
    good = ok & np.isfinite(res[a][0]) & np.isfinite(res[b][0])
    d = {}
    for col, q in QUANTITIES:
        diff = res[a][1][a][good, col] - res[b][1][b][good, col]
        sl, se = slope_through_origin(fl[good], diff)
        d[q] = (100 * sl / den[q], 100 * se / abs(den[q]))
    return d


def run_case(pairs, templates, args):
    """Corrected residual rows of every route's template on one set of stars."""
    out = {}
    for name, (tpl, method) in templates.items():
        fl, rows = per_star_residuals(pairs, tpl, methods={name: {"method": method}},
                                      sky=1000.0)
        out[name] = (fl, rows)
    return out


def rms_lines(sensors):
    """Per route and data set: the root mean square (and mean) over the sensor-input-PSF rows
    of the size and e1 slopes left (%), inputs split into noise-free and drawn."""
    rows = {}
    for sensor, per_input in sensors.items():
        for name, per_psf in per_input.items():
            kind = "noise-free" if name == "noise-free" else (
                "flats" if name.startswith("flats") else "draws")
            for tab in per_psf.values():
                for route in MODELS + ("true template",):
                    if isinstance(tab.get(route), dict) and "size" in tab[route]:
                        rows.setdefault((route, kind), []).append(
                            (tab[route]["size"][0], tab[route]["e1"][0]))
                    cal = tab.get(route, {}).get("calibration error")
                    if cal and not (route == "coulton18" and kind == "noise-free"):
                        rows.setdefault((f"{route}, calibration", kind), []).append(
                            (cal["size"][0], cal["e1"][0]))
                # the links of e1: templates against the truth, paired
                for name in (HYBRID, "astier23 shifts, drift"):
                    d = tab.get(f"{name} minus true template")
                    if d:
                        rows.setdefault((f"{name} - truth", kind), []).append(
                            (d["size"][0], d["e1"][0]))
    out = ["root mean square (mean) over the sensor-input-PSF rows of the % left:"]
    for (route, kind), v in sorted(rows.items(), key=lambda kv: (kv[0][1], kv[0][0])):
        a = np.array(v)
        rms, mean = np.sqrt(np.mean(a ** 2, axis=0)), a.mean(axis=0)
        out.append(f"  {kind:10s} {route:25s} {len(v):2d} rows: size {rms[0]:5.1f} "
                   f"({mean[0]:+5.1f}), e1 {rms[1]:5.1f} ({mean[1]:+5.1f})")
    return out


def coverage_lines(sensors):
    """Coverage of each stated precision per PSF and quantity, from the stored rows
    (|residual| <= stated (+) star error; |calibration error| <= stated (+) its error)."""
    cases = {}
    for per_input in sensors.values():
        for label, per_psf in per_input.items():
            for psf, tab in per_psf.items():
                for route in MODELS:
                    r = tab.get(route) or {}
                    for key in ("stated", "stated (a_ij errors alone)"):
                        st = r.get(key)
                        if st is None or r.get(f"{key}_refused"):
                            continue
                        name = route if key == "stated" else AREAS_ONLY
                        cal = r["calibration error"]
                        for q in ("size", "e1"):
                            c = cases.setdefault((name, psf, q), [[], []])
                            c[0].append(abs(r[q][0]) <= np.hypot(st[q], r[q][1]))
                            if not (route == "coulton18" and label == "noise-free"):
                                c[1].append(abs(cal[q][0]) <= np.hypot(st[q], cal[q][1]))
    out = ["coverage per PSF and quantity: residuals covered / cases; calibration errors "
           "covered / cases"]
    for (name, psf, q), (tot, cal) in sorted(cases.items()):
        out.append(f"  {name:32s} {psf:10s} {q:4s} {sum(tot):2d} / {len(tot):2d}; "
                   f"{sum(cal):2d} / {len(cal):2d}")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sensors", nargs="+",
                    default=["lsst_itl_50_8", "lsst_e2v_50_8", "lsst_itl_50_32",
                             "lsst_e2v_50_32"])
    ap.add_argument("--psf", nargs="+", default=["moffat", "kolmogorov"])
    ap.add_argument("--lags", type=int, default=3, help="largest lag of the a-matrix used")
    ap.add_argument("--model-numerics", choices=sorted(MODEL_NUMERICS), default="fit",
                    help="numerical settings of the electrostatic fit's model a_ij: the fit's "
                         "(MODEL_SETTINGS) or converged ones (CONVERGED_MODEL_SETTINGS)")
    ap.add_argument("--draws", type=int, default=3, help="noisy draws of each a-matrix")
    ap.add_argument("--draws-stated", type=int, default=6,
                    help="templates drawn from each route's uncertainty (stated precision)")
    ap.add_argument("--n-stars", type=int, nargs="+", default=[200],
                    help="stars per PSF: one number, or one per sensor")
    ap.add_argument("--pairs", help="cache prefix for the drawn stars and flats' covariances")
    ap.add_argument("--flats", action="store_true", help="also calibrate from GalSim flats")
    ap.add_argument("--flat-size", type=int, default=400)
    ap.add_argument("--pairs-per-level", type=int, default=2)
    ap.add_argument("--flat-max-lag", type=int, default=3)
    ap.add_argument("--flat-steps", type=int, default=40)
    ap.add_argument("--out", default=os.path.join(HERE, "peers_results"))
    ap.add_argument("--summarize", nargs="+", metavar="JSON",
                    help="only print the root-mean-square summary of earlier results files "
                         "(read, not rewritten)")
    args = ap.parse_args(argv)
    if len(args.n_stars) not in (1, len(args.sensors)):
        ap.error(f"--n-stars takes one number or one per sensor ({len(args.sensors)}), "
                 f"got {len(args.n_stars)}")
    n_stars = dict(zip(args.sensors, args.n_stars * len(args.sensors)
                       if len(args.n_stars) == 1 else args.n_stars))
    if args.summarize:
        sensors = {}
        for path in args.summarize:
            with open(path) as fh:
                sensors.update(json.load(fh)["sensors"])
        print("\n".join(rms_lines(sensors) + coverage_lines(sensors)))
        return
    lines, out = [], {"sensors": {}, "errors": {"relative": REL_ERROR, "floor": ERROR_FLOOR},
                      "lags": args.lags}
    coverage = {m: [] for m in MODELS + (AREAS_ONLY,)}
    cal_coverage = {m: [] for m in MODELS + (AREAS_ONLY,)}
    unbounded = {m: 0 for m in MODELS + (AREAS_ONLY,)}

    def say(s):
        print(s, flush=True)
        lines.append(s)

    def save(*, partial):
        """Write what is done (after every input, so that a long run keeps its cases)."""
        cov = "; ".join(f"{m} {np.mean(c):.0%} of {len(c)}" + (
            f" ({unbounded[m]} cases left out: some of its drawn templates beyond the model's "
            "range)" if unbounded[m] else "") for m, c in coverage.items() if c)
        cal = "; ".join(f"{m} {np.mean(c):.0%} of {len(c)}" for m, c in cal_coverage.items()
                        if c)
        head = ("(partial: the run goes on) " if partial else "") + (
            "coverage of the stated precision (|residual| <= stated (+) stars, size and e1): "
            + cov + "\ncoverage of the calibration error (|paired residual minus the method's "
            "with the truth| <= stated (+) paired error, size and e1): " + cal)
        if not partial:
            say(head)
            for line in rms_lines(out["sensors"]):
                say(line)
        out["coverage"] = {m: {"fraction": float(np.mean(c)), "cases": len(c)}
                           for m, c in coverage.items() if c}
        out["calibration_coverage"] = {m: {"fraction": float(np.mean(c)), "cases": len(c)}
                                       for m, c in cal_coverage.items() if c}
        text = lines + ([head] if partial else [])
        write_results(args.out, text, {"complete": not partial, **out}, script=__file__,
                      json_default=float)

    say(f"routes: {', '.join(f'{m} ({ROUTE_METHODS[m]})' for m in MODELS)}; a-matrix lags "
        f"0..{args.lags}, errors {REL_ERROR:.0%} + {ERROR_FLOOR:g}/e; % of the uncorrected "
        "slope, errors from the stars")
    if args.model_numerics != "fit":
        say(f"electrostatic fit's model a_ij: {args.model_numerics} numerics "
            f"{MODEL_NUMERICS[args.model_numerics]}")
    for sensor in args.sensors:
        rec = out["sensors"][sensor] = {}
        truth_a, inputs = amatrix_inputs(sensor, args.lags, args.draws)
        if args.flats:
            tab, _ = flats_table(sensor, args)
            inputs.append(("flats", tab))
        true_tpl = import_galsim_sensor(sensor, match="transfers")
        true_areas = import_galsim_sensor(sensor, match="areas")
        window = moved_window(true_tpl)
        # the kernel route's truth: the kernel of GalSim's noise-free a-matrix
        c18_truth = calibrate_route(inputs[0][1], "coulton18").template
        psf_pairs = {}
        for psf in args.psf:
            pairs, seed, cost = star_pairs(sensor, psf,
                                           argparse.Namespace(**{**vars(args),
                                                                 "n_stars": n_stars[sensor]}))
            psf_pairs[psf] = pairs
            say(f"{sensor} {psf}: {len(pairs)} stars (seed {seed})"
                + (f", drawn in {cost:.0f} s" if cost else ""))
        for k, (label, table) in enumerate(inputs):
            t0 = time.time()
            routes = {}
            for m in MODELS:
                kw = ({"allow_poor_fit": True,
                       "model_settings": MODEL_NUMERICS[args.model_numerics]}
                      if m == "electrostatic" else {})
                routes[m] = calibrate_route(table, m, **kw)
            fits = "; ".join(f"{m} chi2 {r.chi2:.1f}/{r.dof}" for m, r in routes.items()
                             if m != "coulton18")
            say(f" {sensor}, {label}: {fits}; {time.time() - t0:.0f} s")
            # the near-field response S1 that the size correction follows
            nf = routes["electrostatic"].product.near_field
            s1_truth = near_field_response(truth_a)[0]
            say(f"  electrostatic S1 = a00 + 2 (a01 + a10) + 4 a11 / GalSim's: fitted model "
                f"{nf['model'] / s1_truth:.3f}, refined template {nf['template'] / s1_truth:.3f}")
            stated = {m: stated_templates(r, table, args.draws_stated,
                                          seed=zlib.crc32(f"{sensor}:{label}:{m}".encode()))
                      for m, r in routes.items()}
            # the same draws without the parameter modes: the a_ij errors alone
            stated[AREAS_ONLY] = draw_templates(
                areas_only(routes["electrostatic"].template), args.draws_stated,
                seed=zlib.crc32(f"{sensor}:{label}:electrostatic".encode()))
            es_t = routes["electrostatic"].template
            ar_t = routes["astier23"].product.template(
                size=es_t.size, edge_samples=es_t.fractions.size, charge=es_t.charge)
            hybrid = combine_templates(curl_free_template(es_t), [
                template_difference(ar_t, curl_free_template(ar_t))], [1.0])
            rec[label] = {}
            for psf, pairs in psf_pairs.items():
                templates = {m: (r.template, r.method) for m, r in routes.items()}
                templates["true template"] = (true_tpl, "drift")
                # the links of the chain: each template with the other method
                templates["astier23 shifts, drift"] = (routes["astier23"].template, "drift")
                templates["true template, astier23"] = (true_tpl, "astier23")
                # the calibrated template within GalSim's window (its files move no
                # boundary beyond lag 3): what the model's far field does to the stars
                templates["electrostatic, window"] = (
                    routes["electrostatic"].template.cropped(window), "drift")
                # GalSim's file matched to its own pixel areas (its a-matrix) rather
                # than to its photons' transfers: the template an area model aims at
                templates["true template (areas)"] = (true_areas, "drift")
                templates[CALIBRATION_REFERENCE["coulton18"]] = (c18_truth, "coulton18")
                # which link loses e1: the electrostatic template's areas with the
                # Astier & Regnault template's divergence-free part
                templates[HYBRID] = (hybrid, "drift")
                res = run_case(pairs, templates, args)
                fl, base_rows = next(iter(res.values()))
                u, ok = slopes(fl, base_rows["uncorrected"])
                row = rec[label][psf] = {"uncorrected": u}
                # e2 has no brighter-fatter slope of its own (the symmetry): its
                # slope left is given in % of the uncorrected e1 slope
                den = {q: (u[q][0] if q != "e2" else abs(u["e1"][0])) for _, q in QUANTITIES}
                for name, (fl_n, rows) in res.items():
                    s, _ = slopes(fl_n, rows[name])
                    row[name] = {q: (100 * s[q][0] / den[q], 100 * s[q][1] / abs(den[q]))
                                 for _, q in QUANTITIES}
                    say(f"  {psf:10s} {name:14s} " + "  ".join(
                        f"{q} {row[name][q][0]:+6.1f} +- {row[name][q][1]:4.1f}"
                        for _, q in QUANTITIES))
                # paired differences (same stars): package minus each LSST route
                for other in ("astier23", "coulton18", "true template", "true template (areas)",
                              "electrostatic, window"):
                    d = row[f"electrostatic minus {other}"] = paired(
                        res, "electrostatic", other, fl, ok, den)
                    say(f"  {psf:10s} paired electrostatic - {other}: " + "  ".join(
                        f"{q} {d[q][0]:+6.1f} +- {d[q][1]:4.1f}" for _, q in QUANTITIES))
                for name in (HYBRID, "astier23 shifts, drift"):
                    d = row[f"{name} minus true template"] = paired(
                        res, name, "true template", fl, ok, den)
                    say(f"  {psf:10s} paired {name} - true template: " + "  ".join(
                        f"{q} {d[q][0]:+6.1f} +- {d[q][1]:4.1f}" for _, q in QUANTITIES))
                # stated precision and its coverage
                for name in MODELS + (AREAS_ONLY,):
                    m = STATED_ROUTE.get(name, name)
                    vals = {q: [] for _, q in QUANTITIES}
                    refused = 0
                    for tpl in stated[name]:
                        try:
                            fl_d, rows_d = per_star_residuals(
                                pairs, tpl, methods={m: {"method": ROUTE_METHODS[m]}},
                                sky=1000.0)
                        except InputError:
                            # a draw so strong that the Task refuses the stars (beyond the
                            # model's range): counted; the spread is of the others
                            refused += 1
                            continue
                        s, _ = slopes(fl_d, rows_d[m])
                        for _, q in QUANTITIES:
                            vals[q].append(100 * s[q][0] / den[q])
                    # rms about the route's own template's residual (its offset counts)
                    st = {q: float(np.sqrt(np.mean((np.asarray(v) - row[m][q][0]) ** 2)))
                          if v else float("inf") for q, v in vals.items()}
                    key = "stated" if name == m else "stated (a_ij errors alone)"
                    row[m][key] = st
                    row[m][f"{key}_refused"] = refused
                    # the calibration's own error: paired against its method with the truth
                    ref = CALIBRATION_REFERENCE[m]
                    cal = row[m]["calibration error"] = paired(res, m, ref, fl, ok, den)
                    if not refused and not (m == "coulton18" and label == "noise-free"):
                        # (the kernel of the noise-free a-matrix is its own reference)
                        for q in ("size", "e1"):
                            cal_coverage[name].append(bool(
                                abs(cal[q][0]) <= np.hypot(st[q], cal[q][1])))
                    for q in ("size", "e1"):
                        resid, star_err = row[m][q]
                        if refused:  # a stated precision without bound tests nothing
                            unbounded[name] += 1
                            continue
                        covered = abs(resid) <= np.hypot(st[q], star_err)
                        coverage[name].append(bool(covered))
                    if name == m:
                        say(f"  {psf:10s} {m:14s} calibration error (against {ref}): "
                            + "  ".join(f"{q} {cal[q][0]:+6.1f} +- {cal[q][1]:4.1f}"
                                        for _, q in QUANTITIES))
                    say(f"  {psf:10s} {name:14s} stated +- " + ", ".join(
                        f"{q} {st[q]:.1f}" for _, q in QUANTITIES) + (
                        f" ({refused} of {len(stated[name])} drawn templates beyond the "
                        "model's range, left out)" if refused else ""))
            save(partial=True)
    save(partial=False)


if __name__ == "__main__":
    main()
