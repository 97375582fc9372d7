"""Corrections on galsim.SiliconSensor stars (issue 5, item 5).

Runs the equivalent of ``bfdrift validate-stars --json`` for Moffat and
Kolmogorov PSFs (lsst_itl_50_8, FWHM 0.6-0.9", |e| <= 0.05, random sub-pixel
centres, 1e4 to 1.5e6 e, sky 1000 e collected through the sensor with the
star) and writes ``benchmarks/validate_stars_results.json`` / ``.txt``.
Run from the repository root::

    python benchmarks/validate_stars.py [--n-stars 200]
"""

import argparse
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from lsst_bfdrift.template import DistortionTemplate  # noqa: E402
from lsst_bfdrift.validation import draw_star_pairs, validate_stars  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n-stars", type=int, default=200)
    ap.add_argument("--psf", nargs="+", default=["moffat", "kolmogorov"])
    ap.add_argument("--sky", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=20151)
    ap.add_argument("--out", default=os.path.join(HERE, "validate_stars_results"))
    args = ap.parse_args()
    tpl = DistortionTemplate.from_galsim("lsst_itl_50_8", match_areas=True)
    out = {"sensor": "lsst_itl_50_8", "sky": args.sky, "sky_through_sensor": True,
           "n_stars": args.n_stars, "template": "galsim:lsst_itl_50_8 (area matched)",
           "units": "slopes per 1e5 e: fractional change of T = Ixx + Iyy, change of e1/e2",
           "psfs": {}}
    lines = []
    for psf in args.psf:
        pairs = draw_star_pairs(args.n_stars, psf=psf, sky=args.sky, seed=args.seed,
                                progress=True)
        res = validate_stars(pairs, tpl, sky=args.sky, progress=True)
        unc = res["uncorrected"]["size_slope"]
        uerr = res["uncorrected"]["e_slope"]
        lines.append(f"{psf}: {args.n_stars} stars, sky {args.sky:g} e through the sensor")
        for k, v in res.items():
            v["size_slope_fraction_of_uncorrected"] = v["size_slope"] / unc
            lines.append(
                f"  {k:12s} size slope {v['size_slope']:+.3e} +- {v['size_slope_err']:.1e} "
                f"({100 * v['size_slope'] / unc:+6.1f} +- {100 * v['size_slope_err'] / unc:.1f}"
                f" % of uncorrected)  e1 slope {v['e_slope']:+.2e} +- {v['e_slope_err']:.1e} "
                f"({100 * v['e_slope'] / uerr:+6.1f} %)  n={v['n_stars']}")
        d, a = res["drift"]["size_slope"], res["astier23"]["size_slope"]
        lines.append(f"  target (|drift| <= 3 % of uncorrected and <= 0.5 |astier23|): "
                     f"|drift| = {100 * abs(d) / unc:.1f} %, |drift|/|astier23| = "
                     f"{abs(d) / abs(a):.2f}")
        out["psfs"][psf] = res
        print("\n".join(lines[-(len(res) + 2):]), flush=True)
    with open(args.out + ".json", "w") as fh:
        json.dump(out, fh, indent=2)
    with open(args.out + ".txt", "w") as fh:
        fh.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
