"""Calibrate the bundled default template to the measured ITL a-matrix.

The default describes one real sensor: the LSST ITL sensor whose area
coefficients a_ij (9 x 9 lags, i serial, j parallel) are in
``shared/data/measured/itl_covariances_21oct19.txt`` (Poisson_CCD
repository). :func:`lsst_bfdrift.calibration.tuning.calibrate` fits every
lag, a00 included: in this file a00 equals minus the sum of the other lags
(the area sum rule, which BF obeys), so including it imposes the sum rule on
the model. The parameters are chosen by the data from the candidates,
starting from Rasmussen 2015's structure with the ITL fit of the
collected-charge dipole (xi0 = 2952 e, channel depth 0.368 um, collection
height 0.5 um). The fitted values, rounded to four significant digits, are
the defaults of :class:`~lsst_bfdrift.physics.sensor.SensorParameters`
(``SensorParameters()`` is this sensor); the template is built from them
with the bundled settings and its areas refined to the measured a_ij where
they differ from the model significantly.

Prints the fit, writes ``benchmarks/calibration/calibrate_default_results.txt`` /
``.json``; with ``--write`` it also writes ``lsst_bfdrift/data/
default_template.fits`` and ``default_template_config.json``::

    python benchmarks/calibration/calibrate_default.py [--write]
"""

import argparse
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402
ROOT = os.path.join(HERE, "..", "..")

from lsst_bfdrift.ptc.acoeffs import read_acoeff_table  # noqa: E402
from lsst_bfdrift.calibration.fit_model import CHARGE  # noqa: E402
from lsst_bfdrift.calibration.tuning import calibrate, refine_template  # noqa: E402
from lsst_bfdrift.physics.sensor import SensorParameters  # noqa: E402
from lsst_bfdrift.templates.template import TemplateSettings, build_template  # noqa: E402
from lsst_bfdrift.utils.io import write_json  # noqa: E402

ITL = os.path.join(ROOT, "..", "shared", "data", "measured", "itl_covariances_21oct19.txt")
DATA = os.path.join(ROOT, "lsst_bfdrift", "data")
#: the start: Rasmussen 2015's structure with the charge dipole of the earlier ITL fit
START = SensorParameters.paper().replace(xi0=2952.0, channel_depth=0.368,
                                         clock_separation=0.52, collection_height=0.5)
#: settings of the shipped default template
SETTINGS = TemplateSettings(size=21, edge_samples=32, aggressor_charge=CHARGE, tol=1e-5)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true",
                    help="write the default template and its config into lsst_bfdrift/data")
    args = ap.parse_args(argv)
    table = read_acoeff_table(ITL)
    table.exclude_a00 = False  # a00 in the fit (its sum-rule value)
    table.source = "shared/data/measured/itl_covariances_21oct19.txt (LSST ITL sensor)"
    res = calibrate(table, start=START, build=False)
    f = res.fit
    rounded = {n: float(f"{f.values[n]:.4g}") for n in f.names}
    params = START.replace(**rounded)
    lines = [f"default calibration: {table.source}, 9 x 9 lags, a00 included; "
             f"{res.seconds['total']:.0f} s",
             "  " + ", ".join(f"{n} = {f.values[n]:.5g} +- {f.errors[n]:.2g}"
                              + (" (at its bound)" if n in f.at_bound else "")
                              for n in f.names),
             f"  chi2 = {f.chi2:.2f} for {f.dof} dof (p = {f.p_value:.3g}); worst lags: "
             + ", ".join(f"a{i}{j} {p:+.2f}" for (i, j), p in f.worst(3)),
             f"  a00: measured {table.a[0, 0]:.4e} +- {table.sigma[0, 0]:.1e}, model "
             f"{f.model[0, 0]:.4e}; a01 {table.a[0, 1]:.4e} / {f.model[0, 1]:.4e}; "
             f"a10 {table.a[1, 0]:.4e} / {f.model[1, 0]:.4e}",
             "  correlation: " + np.array2string(np.asarray(f.correlation), precision=3),
             f"  SensorParameters() defaults: {rounded}"]
    print("\n".join(lines))
    write_results(os.path.join(HERE, "calibrate_default_results"), lines,
                  {**res.summary(), "rounded": rounded}, script=__file__, json_default=float)
    if args.write:
        if params != SensorParameters():
            print("note: SensorParameters() differs from the fit; update its defaults to",
                  rounded)
        tpl = build_template(params, SETTINGS)
        tpl = refine_template(tpl, table)
        tpl.meta["calibration"] = {
            "source": table.source, "names": f.names, "values": f.values, "errors": f.errors,
            "covariance": np.asarray(f.covariance).tolist(), "chi2": f.chi2, "dof": f.dof,
            "p_value": f.p_value, "refined": True, "a00_in_fit": True, "max_lag": 8,
            "fit": "benchmarks/calibration/calibrate_default.py", "defaults": rounded,
            "uncertainty": {"kind": "data", "sigma": table.sigma.tolist()}}
        tpl.save(os.path.join(DATA, "default_template.fits"), overwrite=True)
        write_json(os.path.join(DATA, "default_template_config.json"),
                   {"sensor": params.to_dict(), "template": SETTINGS.to_dict(),
                    "provenance": {k: v for k, v in tpl.meta["calibration"].items()
                                   if k != "uncertainty"}}, indent=2, default=float)
        print("wrote the default template and its config into", DATA)
    return 0


if __name__ == "__main__":
    sys.exit(main())
