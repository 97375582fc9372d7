"""Figure of a calibration: measured and model a_ij, pulls, parameter correlations."""

import numpy as np

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ["plot_calibration"]


def plot_calibration(result):
    """Three panels of a :class:`~lsst_bfdrift.calibration.tuning.CalibrationResult`.

    Left: abs(a_ij) (1/e) against the lag radius, measured with errors, the
    fitted model, and the final template (refined: equal to the data at the
    measured lags); negative values are open symbols. Middle: the pull map
    (measured - model) / sigma, i serial across, j parallel up. Right: the
    correlation matrix of the fitted parameters.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = result.table
    L = t.max_lag
    i, j = np.meshgrid(np.arange(L + 1), np.arange(L + 1), indexing="ij")
    r = np.hypot(i, j)
    m = t.mask()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    ax = axes[0]
    for arr, style, label in ((t.a, dict(fmt="o", color="k"), "measured"),
                              (result.model, dict(fmt="s", color="tab:blue", mfc="none"),
                               "model fit"),
                              (result.template_acoeffs, dict(fmt="x", color="tab:red"),
                               "template")):
        if arr is None:
            continue
        sel = m & np.isfinite(arr)
        pos = sel & (arr > 0)
        neg = sel & (arr <= 0)
        err = t.sigma if label == "measured" else None
        for part, face in ((pos, None), (neg, "none")):
            if not part.any():
                continue
            kw = dict(style)
            if face is not None and kw.get("fmt") != "x":
                kw["mfc"] = "none"
            ax.errorbar(r[part] + (0.06 if label != "measured" else 0.0), np.abs(arr[part]),
                        yerr=None if err is None else err[part], ls="none", ms=5,
                        label=label if part is pos or not pos.any() else None, **kw)
    ax.set_yscale("log")
    ax.set_xlabel("lag radius sqrt(i^2 + j^2) (px)")
    ax.set_ylabel("|a_ij| (1/e); open: negative")
    ax.set_title(f"chi2/dof = {result.fit.chi2:.1f}/{result.fit.dof}")
    ax.legend(fontsize=8)
    ax = axes[1]
    pulls = np.where(m, result.pulls, np.nan)
    lim = max(3.0, float(np.nanmax(np.abs(pulls))) if np.isfinite(pulls).any() else 3.0)
    im = ax.imshow(pulls.T, origin="lower", cmap="RdBu_r", vmin=-lim, vmax=lim)
    fig.colorbar(im, ax=ax, label="(measured - model) / sigma")
    ax.set_xlabel("i (serial lag)")
    ax.set_ylabel("j (parallel lag)")
    ax.set_title("pulls of the model fit")
    ax = axes[2]
    corr = np.asarray(result.fit.correlation)
    names = result.fit.names
    im = ax.imshow(corr, cmap="RdBu_r", vmin=-1, vmax=1)
    fig.colorbar(im, ax=ax, label="correlation")
    ax.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(len(names)), names, fontsize=8)
    for a_ in range(len(names)):
        for b_ in range(len(names)):
            ax.text(b_, a_, f"{corr[a_, b_]:.2f}", ha="center", va="center", fontsize=7)
    ax.set_title("parameter correlations")
    fig.suptitle(f"calibration of {result.table.source or 'an a-matrix'}", fontsize=10)
    fig.tight_layout()
    return fig
