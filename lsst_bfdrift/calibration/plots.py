"""Figures of a calibration: measured and model a_ij, pulls, parameter correlations;
and, for a calibration with star fields, the held-out slopes and what each data
set constrains."""

import numpy as np

from lsst_bfdrift.utils.plotting import plt  # Agg backend set there

__all__ = ["plot_calibration", "plot_star_calibration"]


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


def plot_star_calibration(result):
    """Three panels of a :class:`~lsst_bfdrift.calibration.star_result.StarCalibrationResult`.

    Left and middle: the size and e1 slopes against flux (per 1e5 e) of the
    **held-out** stars of each field, uncorrected and corrected with the
    a-matrix-only template and with the joint one, with 1-sigma errors (zero
    is the target; the fitted stars are not shown, so the figure is a
    validation; spot series, :func:`~lsst_bfdrift.calibration.spot_fit.calibrate_with_spots`,
    by their held-out spot rows). Right: per fitted direction, the share of
    its information from the stars or spots (the rest from the a-matrix),
    and the chi2 of each data set before and after in the title.

    Returns
    -------
    matplotlib.figure.Figure
    """
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6))
    whats = (("before", "uncorrected", "0.5"), ("flats_only", "a-matrix template", "tab:blue"),
             ("joint", "joint template", "tab:red"))
    fields = list(result.held_out)
    spots = [result.held_out[f].get("kind") == "spots" for f in fields]
    data = "spots" if all(spots) else ("stars and spots" if any(spots) else "stars")
    for ax, key in zip(axes[:2], ("size", "e1")):
        for k, (what, label, color) in enumerate(whats):
            vals = [result.held_out[f][what][key] for f in fields]
            x = np.arange(len(fields)) + 0.2 * (k - 1)
            ax.errorbar(x, [v for v, _ in vals], yerr=[e for _, e in vals], fmt="o",
                        color=color, label=label, capsize=3)
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_xticks(range(len(fields)),
                      [f"{f}\n({result.held_out[f]['n_stars']} "
                       f"{'spot rows' if sp else 'stars'})" for f, sp in zip(fields, spots)],
                      fontsize=8)
        unit = "T (px^2)" if key == "size" else "e1"
        ax.set_ylabel(f"held-out {key} slope: d{unit} per 1e5 e")
        ax.set_title(f"{key} slope of held-out {data} (target 0)")
        ax.legend(fontsize=8)
    ax = axes[2]
    names = list(result.star_information)
    share = [100 * result.star_information[n] for n in names]
    if names:
        ax.barh(range(len(names)), share, color="tab:orange", label=data)
        ax.barh(range(len(names)), [100 - v for v in share], left=share, color="tab:blue",
                label="a-matrix")
        ax.set_yticks(range(len(names)), names, fontsize=8)
        ax.legend(fontsize=8, loc="lower right")
    else:
        ax.text(0.5, 0.5, "no direction entered the fit", ha="center", va="center",
                transform=ax.transAxes)
    ax.set_xlim(0, 100)
    ax.set_xlabel("share of the information (%)")
    c2 = result.chi2
    ax.set_title(f"chi2 a-matrix {c2['flats_only']['amatrix']:.0f} -> "
                 f"{c2['joint']['amatrix']:.0f}, {data} {c2['flats_only']['stars']:.0f} -> "
                 f"{c2['joint']['stars']:.0f}; tension p = {result.tension['p_value']:.2g}",
                 fontsize=9)
    fig.suptitle(f"calibration with {'star fields' if data == 'stars' else data}: held-out "
                 "validation", fontsize=10)
    fig.tight_layout()
    return fig
