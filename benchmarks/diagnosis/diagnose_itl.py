"""The electrostatic model against the measured ITL a_ij, and the diagnosis (issue 6).

1. Reads ../shared/data/measured/itl_covariances_21oct19.txt, establishes the
   axis assignment from the data and whether a00 was set by the sum rule.
2. Fits xi0, xi_cs, channel_depth and v_bss to lags <= 8 (a00 left out when
   set by the sum rule); prints values, errors, correlations, chi2 per ring
   of lag radius and the time the fit took; ships the linearised model as
   ``lsst_bfdrift/data/itl_acoeff_basis.json``.
3. Runs the diagnosis (base model + effects library) on the table and writes
   the report with figures to ``docs/_static/diagnose_itl/``.
4. Runs the diagnosis on the measured e2v PTC (eotest_e2v_ptc_amp05.txt).
5. Closure on covariances measured by the PTC tools: flat pairs simulated
   with the fitted ITL pattern, a_ij measured by ``fit_covariance_model``,
   the (linearised) electrostatic fit of those a_ij against the truth.

Prints everything and writes ``benchmarks/diagnosis/diagnose_itl_results.txt`` and
``.json``.

    python benchmarks/diagnosis/diagnose_itl.py [--reuse-fit]

``--reuse-fit`` takes the electrostatic fit from the previous results JSON
(the fit is the slow part: ~10 template evaluations per iteration).
"""

import argparse
import io
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import command_line, write_results  # noqa: E402

from lsst_bfdrift.ptc.acoeffs import AcoeffTable, read_acoeff_table
from lsst_bfdrift.calibration.acoeff_model import (LinearBasis, default_basis_path,
                                                   electrostatic_acoeffs, fit_acoeffs)
from lsst_bfdrift.diagnosis.effects_fit import Observations, diagnose  # noqa: E402
from lsst_bfdrift.simulation.flats import simulate_flat_pairs  # noqa: E402
from lsst_bfdrift.utils.io import atomic_output  # noqa: E402
from lsst_bfdrift.ptc.covariances import measure_ptc, read_ptc_text  # noqa: E402
from lsst_bfdrift.ptc.full_model import fit_covariance_model  # noqa: E402
from lsst_bfdrift.diagnosis.report import write_report  # noqa: E402
from lsst_bfdrift.physics.sensor import SensorParameters  # noqa: E402

DATA = os.path.join(HERE, "..", "..", "..", "shared", "data", "measured")
if not os.path.isdir(DATA):
    DATA = "/work/shared/data/measured"
ITL = os.path.join(DATA, "itl_covariances_21oct19.txt")
E2V = os.path.join(DATA, "eotest_e2v_ptc_amp05.txt")
OUT = os.path.join(HERE, "diagnose_itl_results")
OUT_JSON = OUT + ".json"
FIG_DIR = os.path.join(HERE, "..", "..", "docs", "_static", "diagnose_itl")


class Tee(io.StringIO):
    def write(self, s):
        sys.stdout.write(s)
        return super().write(s)


def print_steps(out, d):
    for s in d.steps:
        worst = "; ".join(f"{w['block']}({w['i']},{w['j']}) {w['pull']:+.2f}"
                          for w in s["largest_residuals"][:3])
        print(f"  {s['label']:<22s} chi2/dof = {s['chi2_dof']:.3f} ({s['chi2']:.1f}/{s['dof']}),"
              f" rms pull {s['rms_pull']:.3f}, rms residual {s['rms_residual']:.3g}; "
              f"largest: {worst}", file=out)
        for e in s["effects"][-1:]:
            print("      " + e["name"] + ": " + ", ".join(
                f"{k} = {v:.4g} +- {e['errors'][k]:.2g}" for k, v in list(e["params"].items())[:6]),
                file=out)
    for k, r in enumerate(d.candidates):
        print(f"  round {k + 1}: " + ", ".join(f"{c['name']} dBIC {c['delta_bic']:+.1f}"
                                               for c in r[:-1]), file=out)
    if d.not_identifiable:
        print("  not identifiable: " + "; ".join(f"{k}: {v}" for k, v in
                                                 d.not_identifiable.items()), file=out)
    print(f"  effects_added = {d.effects_added}; chi2_dof_before = {d.chi2_dof_before:.3f}; "
          f"chi2_dof_after = {d.chi2_dof_after:.3f}", file=out)
    print(f"  verdict: {d.verdict}", file=out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--reuse-fit", action="store_true")
    args = ap.parse_args()
    out = Tee()
    results = {}
    table = read_acoeff_table(ITL)
    print(f"ITL table: lags <= {table.max_lag}; {table.axis_note}", file=out)

    # 1-2: electrostatic fit
    if args.reuse_fit:
        with open(OUT_JSON) as fh:
            fit_d = json.load(fh)["itl_fit"]
        basis = LinearBasis.from_dict(fit_d["basis"])
        print("(electrostatic fit reused from the previous results file)", file=out)
    else:
        p0 = SensorParameters(xi0=4722.4, channel_depth=0.56159, collection_height=0.5)
        fit = fit_acoeffs(table, p0, progress=True)
        basis = LinearBasis.from_fit(fit, note="electrostatic fit to the ITL a_ij, lags <= 8 "
                                     "(benchmarks/diagnosis/diagnose_itl.py)")
        fit_d = fit.as_dict()
        fit_d["basis"] = basis.to_dict()
        fit_d["params"] = fit.params.to_dict()
        with atomic_output(default_basis_path()) as tmp:
            with open(tmp, "w") as fh:
                json.dump(basis.to_dict(), fh)
    print("electrostatic fit, lags <= 8 (a00 out of chi2): " + ", ".join(
        f"{n} = {fit_d['values'][n]:.5g} +- {fit_d['errors'][n]:.2g}" for n in fit_d["names"]),
        file=out)
    print(f"  chi2 = {fit_d['chi2']:.2f} for {fit_d['dof']} dof (chi2/dof = "
          f"{fit_d['chi2_dof']:.3f}); {fit_d['n_evaluations']} model evaluations, "
          f"{fit_d['seconds']:.0f} s", file=out)
    corr = np.array(fit_d["correlation"])
    print("  correlations: " + ", ".join(
        f"{fit_d['names'][i]}/{fit_d['names'][j]} {corr[i, j]:+.3f}"
        for i in range(len(corr)) for j in range(i + 1, len(corr))), file=out)
    print("  chi2 by lag radius (ring: chi2/lags): " + ", ".join(
        f"{k}: {v[0]:.1f}/{v[1]}" for k, v in fit_d["chi2_by_radius"].items()), file=out)
    m, a, s = (np.array(fit_d[k]) for k in ("model", "data", "sigma"))
    for (i, j) in ((0, 1), (1, 0), (1, 1), (0, 2), (2, 0)):
        print(f"  a{i}{j}: measured {a[i, j]:.4g} +- {s[i, j]:.2g}, model {m[i, j]:.4g}, "
              f"pull {(a[i, j] - m[i, j]) / s[i, j]:+.2f}", file=out)
    pulls = np.where(np.arange(9)[:, None] + np.arange(9)[None, :] == 0, np.nan, (a - m) / s)
    print("  pull map (measured - model) / sigma, rows serial lag i = 0..8, columns parallel "
          "lag j = 0..8 (a00 not fitted):", file=out)
    for i in range(pulls.shape[0]):
        print("    " + " ".join("   -- " if np.isnan(v) else f"{v:+6.2f}" for v in pulls[i]),
              file=out)
    print(f"  anisotropy a01/a10: measured {a[0, 1] / a[1, 0]:.3f}, model "
          f"{m[0, 1] / m[1, 0]:.3f}; model a00 {m[0, 0]:.4g} (measured {a[0, 0]:.4g}, "
          "set by the sum rule)", file=out)
    # 2b: the previous calibration (xi0 and channel depth fitted to a01, a10, a11
    # only; benchmarks/calibration/calibrate_paper.py) evaluated on all 80 lags
    # (on the paper's nominal sensor, the base of that fit)
    prev = electrostatic_acoeffs(SensorParameters.paper().replace(
        xi0=4722.4, channel_depth=0.56159, collection_height=0.5), max_lag=8)
    msk = table.mask()
    chi_prev = float(np.sum(((table.a - prev) / table.sigma)[msk] ** 2))
    print(f"previous calibration (xi0 4722.4, channel depth 0.5616; nearest neighbours "
          f"only) on all 80 lags: chi2 = {chi_prev:.2f} (chi2/80 = {chi_prev / 80:.3f}); "
          f"a01/a10 = {prev[0, 1] / prev[1, 0]:.3f}; largest pulls " + ", ".join(
              f"a{i}{j} {((table.a - prev) / table.sigma)[i, j]:+.2f}" for i, j in
              sorted(np.argwhere(msk).tolist(), key=lambda ij: -abs(
                  ((table.a - prev) / table.sigma)[ij[0], ij[1]]))[:4]), file=out)
    results["previous_calibration"] = {"chi2": chi_prev, "n_lags": 80,
                                       "ratio_01_10": float(prev[0, 1] / prev[1, 0])}
    results["itl_fit"] = fit_d
    results["axis_note"] = table.axis_note
    if not args.reuse_fit:  # keep the slow part even if a later step fails
        with atomic_output(OUT_JSON) as tmp:
            with open(tmp, "w") as fh:
                json.dump({"command": command_line(__file__), **results}, fh, indent=1,
                          default=float)

    # 3: diagnosis on the table
    t = time.perf_counter()
    d = diagnose(Observations.from_table(table), basis)
    print(f"diagnosis of the ITL table ({time.perf_counter() - t:.1f} s):", file=out)
    print_steps(out, d)
    results["itl_diagnosis"] = d.as_dict()
    write_report(d.as_dict(), FIG_DIR, extra={"electrostatic_fit": {
        k: fit_d[k] for k in ("names", "values", "errors", "chi2", "dof", "seconds")}})

    # 3b: sensitivity: were the quoted errors scatter rather than errors of the
    # mean, they would be smaller; scale them so that the base fit has chi2/dof = 1
    k = float(np.sqrt(d.chi2_dof_before))
    ds = diagnose(Observations.from_table(AcoeffTable(table.a, table.sigma * k,
                                                      exclude_a00=True)), basis)
    print(f"diagnosis with the ITL errors scaled by {k:.3f} (base chi2/dof = 1):", file=out)
    print_steps(out, ds)
    results["itl_diagnosis_scaled_errors"] = {"scale": k, **ds.as_dict()}

    # 4: diagnosis on the e2v PTC
    mu, var = read_ptc_text(E2V)
    dp = diagnose(Observations.from_ptc(mu, var), basis)
    print("diagnosis of the e2v PTC (errors scaled so that the base fit has chi2/dof = 1):",
          file=out)
    print_steps(out, dp)
    results["e2v_ptc_diagnosis"] = dp.as_dict()

    # 5: closure on covariances measured by the PTC tools
    L = 4
    truth = basis.a(list(basis.x0.values()), L)
    levels = np.linspace(1e4, 9e4, 10)
    t = time.perf_counter()
    pairs = simulate_flat_pairs(truth, levels, shape=(256, 256), n_steps=40, seed=11)
    ptc = measure_ptc(pairs, max_lag=L)
    cm = fit_covariance_model(ptc["mu"], ptc["cov"], npix=ptc["npix"], fit_b=False)
    meas = AcoeffTable(cm["a"], cm["a_err"], source="simulated flats, PTC tools")
    lin = fit_acoeffs(meas, SensorParameters.from_dict(fit_d["params"]),
                      model=lambda p: basis.a([getattr(p, n) for n in basis.names], L))
    print(f"closure on a_ij measured by the PTC tools from simulated flats (10 pairs "
          f"256 x 256, {time.perf_counter() - t:.1f} s): " + ", ".join(
              f"{n} = {lin.values[n]:.5g} +- {lin.errors[n]:.2g} (truth {basis.x0[n]:.5g}, "
              f"pull {(lin.values[n] - basis.x0[n]) / lin.errors[n]:+.2f})" for n in lin.names)
          + f"; chi2/dof = {lin.chi2 / lin.dof:.2f}", file=out)
    results["ptc_tools_closure"] = {"values": lin.values, "errors": lin.errors,
                                    "truth": basis.x0, "chi2": lin.chi2, "dof": lin.dof}

    write_results(OUT, out.getvalue().removesuffix("\n").split("\n"), results, script=__file__,
                  json_default=float)


if __name__ == "__main__":
    main()
