"""Figures of the flat-field and star simulations."""

import numpy as np

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ['plot_flat_simulation', 'plot_star_history', 'STAR_PANEL_TITLES']


def plot_flat_simulation(table, template=None):
    """Covariances against mean of a flat simulation (like the paper's Fig. 6).

    Left: C00 (e^2) with the Poisson line; right: C01, C10, C11 (e^2) with
    the first-order guides a_ij mu^2 from the template, both estimators.
    """
    mu = np.asarray(table["mu"])
    paper = np.asarray(table["paper"]) * mu[:, None, None]
    pairs = np.asarray(table["pairs"])
    err = np.asarray(table["pairs_err"])
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    ax0.plot(mu, paper[:, 0, 0], "o", ms=3, label="all pairs (paper)")
    ax0.errorbar(mu, pairs[:, 0, 0], err[:, 0, 0], fmt=".", ms=2, label="per pair (LSST)")
    ax0.plot(mu, mu, "k--", lw=1, label="Poisson")
    ax0.set_xlabel("mean (e)")
    ax0.set_ylabel("C00 (e$^2$)")
    ax0.legend()
    a = None
    if template is not None:
        c = template.center
        a = np.log(template.moments().area) / template.charge
    for (di, dj), col in (((0, 1), "C0"), ((1, 0), "C1"), ((1, 1), "C2")):
        ax1.plot(mu, paper[:, di, dj], "o", ms=3, color=col, label=f"C{di}{dj} all pairs")
        ax1.errorbar(mu, pairs[:, di, dj], err[:, di, dj], fmt=".", ms=2, color=col, alpha=0.5,
                     label=f"C{di}{dj} per pair (LSST)")
        if a is not None:
            ax1.plot(mu, a[c + dj, c + di] * mu**2, "--", color=col, lw=1,
                     label=f"a{di}{dj} mu$^2$ (template)")
    ax1.set_xlabel("mean (e)")
    ax1.set_ylabel("C$_{ij}$ (e$^2$)")
    ax1.legend(fontsize=8)
    return fig


#: Title of each panel of :func:`plot_star_history`, [row, column].
STAR_PANEL_TITLES = (("central pixel", "size with and without BF", "FWHM growth by BF",
                      "size change by BF"),
                     ("ellipticity", "orientation", "arrival rates",
                      "ellipticity change by BF"))


def plot_star_history(history, *, title=None):
    """A star simulation against counts (like the paper's Fig. 7).

    Panels: central pixel counts, T = sigma_x^2 + sigma_y^2 with and without
    BF, FWHM growth by BF (RSS difference), ellipticity and orientation, the
    arrival rates, and (right column) BF minus square pixels: the size change
    dT (px^2) and the ellipticity change de1, de2. Each panel has a title
    (:data:`STAR_PANEL_TITLES`).

    Parameters
    ----------
    history : astropy.table.Table
        From :meth:`~lsst_bfdrift.simulation.stars.StarSimulation.run`.
    title : str, optional
        Figure title: the run's parameters (PSF, FWHM, flux, template).

    Returns
    -------
    matplotlib.figure.Figure
    """
    h = history
    n = np.asarray(h["counts"])
    fig, ax = plt.subplots(2, 4, figsize=(17, 7), constrained_layout=True)
    ax[0, 3].plot(n, np.asarray(h["T"]) - np.asarray(h["T_nominal"]), ".-", color="C3")
    ax[0, 3].axhline(0.0, color="k", lw=0.8)
    ax[0, 3].set_ylabel("BF minus square pixels: $\\Delta T$ (px$^2$)")
    ax[0, 3].set_xlabel("counts (e)")
    ax[1, 3].plot(h["central"], np.asarray(h["e1"]) - np.asarray(h["e1_nominal"]), ".-",
                  label="$\\Delta e_1$")
    ax[1, 3].plot(h["central"], np.asarray(h["e2"]) - np.asarray(h["e2_nominal"]), ".-",
                  label="$\\Delta e_2$")
    ax[1, 3].axhline(0.0, color="k", lw=0.8)
    ax[1, 3].set_ylabel("BF minus square pixels: ellipticity")
    ax[1, 3].set_xlabel("central pixel counts (e)")
    ax[1, 3].legend()
    ax[0, 0].plot(n, h["central"], ".-")
    ax[0, 0].set_ylabel("central pixel counts (e)")
    ax[0, 1].plot(n, h["T"], ".-", label="with BF")
    ax[0, 1].plot(n, h["T_nominal"], "--", label="square pixels")
    ax[0, 1].set_ylabel("$\\sigma_x^2 + \\sigma_y^2$ (px$^2$)")
    ax[0, 1].legend()
    rss = np.sqrt(np.clip(np.asarray(h["T"]) - np.asarray(h["T_nominal"]), 0, None) / 2)
    ax[0, 2].plot(h["central"], 2.3548 * rss, ".-")
    ax[0, 2].set_xlabel("central pixel counts (e)")
    ax[0, 2].set_ylabel("FWHM growth, RSS (px)")
    e = np.hypot(h["e1"], h["e2"])
    e0 = np.hypot(h["e1_nominal"], h["e2_nominal"])
    ax[1, 0].plot(h["central"], e, ".-", label="with BF")
    ax[1, 0].plot(h["central"], e0, "--", label="square pixels")
    ax[1, 0].set_ylabel("ellipticity |e|")
    ax[1, 0].legend()
    ax[1, 1].plot(h["central"], h["theta"], ".-", label="with BF")
    ax[1, 1].plot(h["central"], h["theta_nominal"], "--", label="square pixels")
    ax[1, 1].set_ylabel("orientation (deg from serial axis)")
    for col in h.colnames:
        if col.startswith("rate_"):
            ax[1, 2].plot(n, h[col], ".-", ms=2, label=col[5:].replace("_", ","))
    ax[1, 2].set_ylabel("arrivals per conversion")
    ax[1, 2].legend(fontsize=7, ncol=3)
    for r, row in enumerate(STAR_PANEL_TITLES):
        for c_, name in enumerate(row):
            ax[r, c_].set_title(name, fontsize=10)
    if title:
        fig.suptitle(title)
    for a in ax.ravel():
        a.ticklabel_format(axis="x", style="sci", scilimits=(0, 0))
        if not a.get_xlabel():
            a.set_xlabel("counts (e)" if a in (ax[0, 0], ax[0, 1], ax[1, 2]) else
                         "central pixel counts (e)")
    return fig
