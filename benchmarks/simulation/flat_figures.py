"""Figure-6-like plots: C_ij / mu against mu of simulated flats.

Run from the repository root::

    python benchmarks/simulation/flat_figures.py [--n-images 1024] [--steps 250]

For the paper's two responsivities (d ln A00 / Q = -1e-5 and -3.3e-5 per e,
the bundled template's displacements attributed to the matching charge,
:func:`lsst_bfdrift.simulation.flats.with_responsivity`) a stack of periodic flats
is filled in steps of 1000 e (the paper: 1024 images, 250 cycles) and the
paper's all-pairs covariances C_ij / mu are plotted against mu, with the
model of Astier et al. 2019 (:func:`lsst_bfdrift.ptc.full_model.covariance_model`, third
order, gain 1) evaluated with the template's linear response alpha_ij
(:func:`lsst_bfdrift.simulation.flats.template_area_coefficients`) at the
effective signal of the discrete filling. Writes
``docs/_static/simulations/flat_cov_resp1e-5.png`` and ``flat_cov_resp3.3e-5.png``
and a text summary
``benchmarks/simulation/flat_figures_results.txt``.
"""

import argparse
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))  # benchmarks/, for _common
from _common import command_line  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from lsst_bfdrift.utils.io import atomic_output  # noqa: E402
from lsst_bfdrift.ptc.full_model import covariance_model  # noqa: E402
from lsst_bfdrift.simulation.flats import (simulate_flats, template_area_coefficients,  # noqa: E402
                                      with_responsivity)
from lsst_bfdrift.templates.template import load_default_template  # noqa: E402

LAGS = [((0, 1), "C0"), ((1, 0), "C1"), ((1, 1), "C2"), ((0, 2), "C3"), ((2, 0), "C4")]


def figure(tab, alpha, resp, step):
    """Two panels: C00/mu and the neighbour C_ij/mu against mu, with the model."""
    mu = np.asarray(tab["mu"], float)
    paper = np.asarray(tab["paper"])  # C_ij / mu, [k, di, dj]
    # discrete filling: charge of step k sees the boundaries of steps < k, so the
    # model's BF terms act on mu - step (first order: a mu (1 - step / mu))
    x = np.clip(mu - step, 0.0, None)
    L = alpha.shape[0] - 1
    model = covariance_model(x, 1.0, alpha, np.zeros_like(alpha), np.zeros_like(alpha))
    model = model / np.where(x > 0, x, 1.0)[:, None, None]
    model[mu < 3 * step] = np.nan  # the continuous model needs several fill steps
    # a series in a mu: drawn while |a00 mu| <= 0.6, beyond its reach
    model[np.abs(alpha[0, 0]) * x > 0.6] = np.nan
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.3), constrained_layout=True)
    ax0.plot(mu / 1e3, paper[:, 0, 0], "o", ms=2.5, label="simulation (all pairs)")
    ax0.plot(mu / 1e3, model[:, 0, 0], "k-", lw=1,
             label=r"Astier et al. 2019, 3rd order, template $a_{ij}$ ($|a_{00}\mu| \leq 0.6$)")
    expo = np.expm1(2 * alpha[0, 0] * x) / (2 * alpha[0, 0] * np.where(x > 0, x, 1.0))
    ax0.plot(mu / 1e3, np.where(mu < 3 * step, np.nan, expo), "k:", lw=1,
             label="exponential (a$_{00}$ only)")
    ax0.axhline(1.0, color="0.6", lw=0.8)
    ax0.set_xlabel(r"$\mu$ (ke)")
    ax0.set_ylabel(r"$C_{00}/\mu$")
    ax0.set_ylim(0, 1.1)
    ax0.legend(fontsize=8)
    ax0.set_title(f"d ln A$_{{00}}$/Q = {resp:g} per e")
    for (di, dj), col in LAGS:
        if max(di, dj) > L:
            continue
        ax1.plot(mu / 1e3, paper[:, di, dj], "o", ms=2.5, color=col,
                 label=f"$C_{{{di}{dj}}}/\\mu$")
        ax1.plot(mu / 1e3, model[:, di, dj], "-", color=col, lw=1)
    ax1.axhline(0.0, color="0.6", lw=0.8)
    shown = np.concatenate([paper[:, di, dj] for (di, dj), _ in LAGS if max(di, dj) <= L])
    lo, hi = np.percentile(shown, [0.5, 99.5])
    ax1.set_ylim(lo - 0.1 * (hi - lo), hi + 0.25 * (hi - lo))
    ax1.set_xlabel(r"$\mu$ (ke)")
    ax1.set_ylabel(r"$C_{ij}/\mu$ (lines: model, $|a_{00}\mu| \leq 0.6$)")
    ax1.legend(fontsize=8, ncol=2)
    return fig


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n-images", type=int, default=1024)
    ap.add_argument("--steps", type=int, default=250)
    ap.add_argument("--step", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=6)
    ap.add_argument("--outdir", default=os.path.relpath(
        os.path.join(HERE, "..", "..", "docs", "_static", "simulations")))
    ap.add_argument("--results", default=os.path.join(HERE, "flat_figures_results.txt"))
    args = ap.parse_args()
    os.makedirs(args.outdir, exist_ok=True)
    base = load_default_template()
    lines = []
    for resp in (-1e-5, -3.3e-5):
        tpl = with_responsivity(base, resp)
        alpha = template_area_coefficients(tpl, max_lag=3)["alpha"]
        t0 = time.perf_counter()
        tab = simulate_flats(tpl, n_images=args.n_images, shape=(16, 16), step=args.step,
                             n_steps=args.steps, max_lag=3, seed=args.seed, progress=True)
        dt = time.perf_counter() - t0
        fig = figure(tab, alpha, resp, args.step)
        path = os.path.join(args.outdir, {-1e-5: "flat_cov_resp1e-5.png",
                                          -3.3e-5: "flat_cov_resp3.3e-5.png"}[resp])
        with atomic_output(path) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        plt.close(fig)
        last = tab[-1]
        k10 = int(np.argmin(np.abs(np.asarray(tab["mu"]) - 1e4)))
        lines.append(f"responsivity {resp:g} per e: {args.n_images} flats 16x16, {args.steps} "
                     f"steps of {args.step:.0f} e, {dt:.0f} s; alpha00 {alpha[0, 0]:.4e}, "
                     f"alpha01 {alpha[0, 1]:.4e}, alpha10 {alpha[1, 0]:.4e} per e; "
                     f"at mu = {tab['mu'][k10]:.0f}: C00/mu {tab['paper'][k10][0, 0]:.4f}, "
                     f"C01/mu {tab['paper'][k10][0, 1]:.5f}, C10/mu {tab['paper'][k10][1, 0]:.5f}; "
                     f"at mu = {last['mu']:.0f}: C00/mu {last['paper'][0, 0]:.4f}; "
                     f"figure {path}")
    text = "\n".join(lines) + "\n"
    print(text, end="")
    with atomic_output(args.results) as tmp:
        with open(tmp, "w") as fh:
            fh.write(f"# command: {command_line(__file__)}\n" + text)


if __name__ == "__main__":
    main()
