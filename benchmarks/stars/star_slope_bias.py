"""Bias of the no-truth slopes on brighter-fatter-free GalSim star fields.

Star fields without any sensor effect: GalSim photon shooting of Moffat
stars (beta 3.5, FWHM 0.7-0.95" and PSF ellipticity varying over the field
as in :func:`~lsst_bfdrift.simulation.skysim.simulate_star_field`), fluxes
log-uniform 1e4-1.5e6 e, photons binned on square pixels (no
galsim.SiliconSensor, so no brighter-fatter effect), Poisson sky of 1000 e
and 5 e read noise, 2048 x 2048 px, 800 stars, each field its own seed. The
catalog is the package's (:class:`~lsst_bfdrift.calibration.star_fit.StarField`:
photutils detection, HSM adaptive moments); the size (ln T), e1 and e2
slopes against flux of :func:`~lsst_bfdrift.catalogs.slopes.fit_flux_slope`
must be zero. Each field is fitted with the noise-bias terms of the
package (1/SNR^2 and 1e5/F) and with the 1/SNR^2 term alone; the script
prints each field's slopes and the weighted mean over the fields with its
error and chi^2::

    python benchmarks/stars/star_slope_bias.py [--fields 36] [--cache /tmp/ssb]

Writes ``benchmarks/stars/star_slope_bias_results.txt`` / ``.json``. About 20 s
per field on one core (the catalogs are cached in ``--cache``).

``--silicon SENSOR`` draws the fields as ``benchmarks/stars/calibrate_stars.py``
draws its own, with galsim.SiliconSensor (its diffusion, and the sky
collected through the sensor around each star) at zero brighter-fatter
strength (:func:`~lsst_bfdrift.simulation.skysim.simulate_star_field`,
``strength=0``; about 200 s per field); ``--n-boot`` gives the slope errors
the star calibration uses (the larger of the formal error and the
bootstrap's), whose chi^2 about the mean tests them::

    python benchmarks/stars/star_slope_bias.py --silicon lsst_itl_50_8 --fields 12 \
        --n-boot 100 --out benchmarks/stars/star_slope_bias_silicon_results
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import write_results  # noqa: E402

from lsst_bfdrift.calibration.star_fit import StarField  # noqa: E402
from lsst_bfdrift.catalogs.slopes import FLUX_UNIT, fit_flux_slope, select_stars  # noqa: E402
from lsst_bfdrift.simulation.skysim import _field_psf, _positions, simulate_star_field  # noqa: E402


def bf_free_field(seed, *, size=2048, n_stars=800, sky=1000.0, read_noise=5.0,
                  fwhm=(0.7, 0.95), e_range=0.04, stamp=31, pixel_scale=0.2):
    """A star field without brighter-fatter effect (GalSim photons on square pixels), e."""
    import galsim

    rng = np.random.default_rng(seed)
    half = stamp // 2
    img = np.zeros((size, size))
    for x, y in _positions(rng, n_stars, (size, size), half + 1, 32.0):
        f = float(np.exp(rng.uniform(np.log(1e4), np.log(1.5e6))))
        prof = _field_psf(galsim, x, y, f, (size, size), fwhm=fwhm, e_range=e_range)[0]
        ix, iy = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
        st = galsim.ImageD(stamp, stamp, scale=pixel_scale)
        prof.drawImage(st, method="phot", rng=galsim.BaseDeviate(int(rng.integers(1, 2**30))),
                       offset=(x - ix, y - iy))
        img[iy - half:iy + half + 1, ix - half:ix + half + 1] += st.array
    img += rng.poisson(sky, img.shape) + rng.normal(0.0, read_noise, img.shape)
    return img


def silicon_field(seed, sensor):
    """A star field of ``benchmarks/stars/calibrate_stars.py``'s recipe drawn by
    galsim.SiliconSensor at zero brighter-fatter strength, e."""
    # no boundary updates: at zero strength the boundaries do not move
    return simulate_star_field((2048, 2048), 800, sensor=sensor, strength=0.0,
                               flux=(1e4, 1.5e6), sky=1000.0, seed=seed, updates=1,
                               min_nrecalc=1e12)["image"]


def catalog(seed, cache, silicon=None):
    """The usable stars' columns (x, y, flux, snr, T, e1, e2) of field ``seed``."""
    tag = f"ssb_{silicon}_{seed}" if silicon else f"ssb_{seed}"
    path = None if cache is None else os.path.join(cache, tag + ".npz")
    if path is not None and os.path.isfile(path):
        return dict(np.load(path))
    sf = StarField(silicon_field(seed, silicon) if silicon else bf_free_field(seed))
    cat = sf.catalog
    ok = select_stars(cat, sf.min_snr)
    cols = {"x": cat["x"].value[ok], "y": cat["y"].value[ok], "flux": cat["flux"].value[ok],
            "snr": np.asarray(cat["snr"], float)[ok], "T": cat["T"].value[ok],
            "e1": np.asarray(cat["e1"])[ok], "e2": np.asarray(cat["e2"])[ok]}
    if path is not None:
        np.savez(path, **cols)
    return cols


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fields", type=int, default=36)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--cache", default=None, help="directory of cached catalogs")
    ap.add_argument("--silicon", default=None, metavar="SENSOR",
                    help="draw with galsim.SiliconSensor of this sensor at zero BF strength")
    ap.add_argument("--n-boot", type=int, default=0,
                    help="bootstrap resamples of each slope error (0: the formal error)")
    ap.add_argument("--out", default=os.path.join(HERE, "star_slope_bias_results"))
    args = ap.parse_args(argv)
    if args.cache:
        os.makedirs(args.cache, exist_ok=True)
    frame = (1023.5, 1023.5, 1024.0, 1024.0)
    models = {"1/SNR^2 + 1e5/F (package)": True, "1/SNR^2 alone": "snr"}
    how = (f"galsim.SiliconSensor {args.silicon} at zero strength, sky through the sensor"
           if args.silicon else "photons on square pixels")
    errs = (f"errors: larger of formal and {args.n_boot}-sample bootstrap" if args.n_boot
            else "formal errors")
    lines = [f"{args.fields} brighter-fatter-free GalSim fields (2048^2 px, 800 Moffat stars, "
             f"{how}, sky 1000 e); slopes per 1e5 e (size: of ln T); {errs}"]
    print(lines[0], flush=True)
    out = {"machine": "2 cores", "fields": []}
    t0 = time.time()
    for k in range(args.fields):
        seed = args.first_seed + k
        c = catalog(seed, args.cache, args.silicon)
        row = {"seed": seed, "n_stars": int(c["x"].size)}
        for name, terms in models.items():
            for q in ("size", "e1", "e2"):
                val = np.log(c["T"]) if q == "size" else c[q]
                r = fit_flux_slope(c["x"], c["y"], c["flux"] / FLUX_UNIT, val, c["snr"],
                                   flux=c["flux"], noise_term=terms, n_boot=args.n_boot,
                                   seed=seed, frame=frame)
                row[f"{name}:{q}"] = (r["slope"], r["slope_err"])
        out["fields"].append(row)
        p = row["1/SNR^2 + 1e5/F (package):size"]
        s = row["1/SNR^2 alone:size"]
        line = (f"  field {seed:3d}: {row['n_stars']} stars; size {p[0]:+.2e} +- {p[1]:.1e} "
                f"(1/SNR^2 alone {s[0]:+.2e} +- {s[1]:.1e}); {time.time() - t0:.0f} s")
        print(line, flush=True)
        lines.append(line)
    out["means"] = {}
    for name in models:
        for q in ("size", "e1", "e2"):
            v = np.array([r[f"{name}:{q}"] for r in out["fields"]])
            w = 1.0 / v[:, 1] ** 2
            mean = float(np.sum(w * v[:, 0]) / w.sum())
            err = float(w.sum() ** -0.5)
            chi2 = float(np.sum(w * (v[:, 0] - mean) ** 2))
            out["means"][f"{name}:{q}"] = {"mean": mean, "err": err, "chi2": chi2,
                                           "dof": len(v) - 1}
            lines.append(f"  {name:27s} {q:4s} mean {mean:+.2e} +- {err:.1e} "
                         f"({mean / err:+.1f} sigma), chi2 about the mean {chi2:.1f} / {len(v) - 1}")
            print(lines[-1], flush=True)
    write_results(args.out, lines, out, script=__file__)
    return 0


if __name__ == "__main__":
    sys.exit(main())
