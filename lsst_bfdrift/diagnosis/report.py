"""Markdown report of a diagnosis, with PNG figures (atomic writes).

:func:`write_report` writes ``DIR/report.md``, ``DIR/diagnosis.json`` and
figures: residual (pull) maps per lag before and after the effects were
added, and chi2 per lag before and after.
"""

import json
import os

import numpy as np

from lsst_bfdrift.utils.io import atomic_output

__all__ = ["pull_map", "write_report", "diagnosis_markdown", "template_change_lines",
           "notable_not_excluded"]


def pull_map(per_lag, block="a"):
    """Array [i, j] of per-lag chi2 and the signed mean pull of one block."""
    keys = [v for v in per_lag.values() if v["block"] == block]
    if not keys:
        return None, None
    L = max(max(v["i"], v["j"]) for v in keys)
    chi = np.full((L + 1, L + 1), np.nan)
    pull = np.full((L + 1, L + 1), np.nan)
    for v in keys:
        chi[v["i"], v["j"]] = v["chi2"]
        pull[v["i"], v["j"]] = float(np.mean(v["pull"]))
    return chi, pull


def _figures(result, outdir):
    # matplotlib (and utils.plotting, which imports it): heavy, only when figures are drawn
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lsst_bfdrift.utils.plotting import save_figure

    files = []
    blocks = sorted({v["block"] for v in result["residuals_before"].values()} - {"M"})
    if result["kind"] != "ptc":
        for blk in blocks:
            fig, axes = plt.subplots(1, 2, figsize=(9, 4))
            for ax, key, title in zip(axes, ("residuals_before", "residuals_after"),
                                      ("before", "after")):
                _, pull = pull_map(result[key], blk)
                im = ax.imshow(pull.T, origin="lower", cmap="RdBu_r", vmin=-4, vmax=4)
                ax.set_xlabel("serial lag i")
                ax.set_ylabel("parallel lag j")
                ax.set_title(f"{blk}: mean pull {title}")
                fig.colorbar(im, ax=ax, shrink=0.8)
            name = f"pull_map_{blk}.png"
            save_figure(fig, os.path.join(outdir, name))
            plt.close(fig)
            files.append(name)
    if result.get("levels") and result["kind"] == "flats":
        name = "residuals_vs_mean.png"
        fig = _residuals_vs_mean(result, plt)
        save_figure(fig, os.path.join(outdir, name))
        plt.close(fig)
        files.append(name)
    fig, ax = plt.subplots(figsize=(9, 3.5))
    keys = list(result["residuals_before"])
    x = np.arange(len(keys))
    for key, lab, off in (("residuals_before", "before", -0.2), ("residuals_after", "after",
                                                                  0.2)):
        ax.bar(x + off, [result[key][k]["chi2"] for k in keys], width=0.4, label=lab)
    ax.set_xticks(x)
    ax.set_xticklabels(keys, rotation=90, fontsize=6)
    ax.set_ylabel("chi2 per lag")
    ax.set_yscale("log")
    ax.legend()
    fig.tight_layout()
    save_figure(fig, os.path.join(outdir, "chi2_per_lag.png"))
    plt.close(fig)
    files.append("chi2_per_lag.png")
    return files


def _residuals_vs_mean(result, plt):
    """Pulls against the mean signal, before and after the added effects: the
    means against EXPTIME ('M') and the lags (0, 0), (0, 1), (1, 0) and the
    worst lag of the difference-image covariances."""
    mu = np.asarray(result["levels"], float)
    keys = [k for k in ("M0,0", "C0,0", "C0,1", "C1,0") if k in result["residuals_before"]]
    worst = result.get("worst_lag")
    if worst and worst not in keys and worst in result["residuals_before"]:
        keys.append(worst)
    from matplotlib.ticker import NullFormatter  # matplotlib: heavy, only for figures

    fig, axes = plt.subplots(1, len(keys), figsize=(2.6 * len(keys), 3.2), squeeze=False)
    for ax, k in zip(axes[0], keys):
        for key, lab, mk in (("residuals_before", "base model", "o"),
                             ("residuals_after", "after", "x")):
            pull = np.asarray(result[key][k]["pull"], float)
            ax.plot(mu[:pull.size], pull, mk, ms=3, label=lab)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("mean signal (ADU)")
        ax.set_title("means vs EXPTIME" if k == "M0,0" else k, fontsize=9)
    axes[0][0].set_ylabel("pull (residual / error)")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    return fig


def diagnosis_markdown(result, figures=()):
    """Markdown text of a diagnosis dictionary (``Diagnosis.as_dict()``)."""
    lines = ["# bfdrift diagnosis", "", f"Input kind: **{result['kind']}** "
             f"({result['n_points']} data points). {result.get('note', '')}", ""]
    lines += ["| stage | chi2/dof | chi2 | dof | rms pull | rms residual "
              "| largest residual lags |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for s in result["steps"]:
        worst = "; ".join(f"{w['block']}({w['i']},{w['j']})"
                          + (f"@{w['level']}" if result["kind"] != "table" else "")
                          + f" {w['pull']:+.1f}" for w in s["largest_residuals"][:3])
        lines.append(f"| {s['label']} | {s['chi2_dof']:.3f} | {s['chi2']:.1f} | {s['dof']} | "
                     f"{s['rms_pull']:.3f} | {s['rms_residual']:.3g} | {worst} |")
    lines += ["", "## Effects added", ""]
    if not result["effects_added"]:
        lines.append("None.")
    for s in result["steps"][1:]:
        e = s["effects"][-1]
        shown = list(e["params"].items())[:6]
        lines.append(f"- **{e['name']}**: " + ", ".join(
            f"{k} = {v:.4g} +- {e['errors'][k]:.2g}" for k, v in shown)
            + (" ..." if len(e["params"]) > 6 else ""))
    lines += ["", "## Candidates per round (delta BIC; negative pays)", ""]
    for k, r in enumerate(result["candidates"]):
        cv = r[-1]
        lines.append(f"{k + 1}. " + ", ".join(f"{c['name']} {c['delta_bic']:+.1f}" for c in r[:-1])
                     + f" (cross-validated chi2: before {cv['cv_chi2_before']:.1f}, best "
                     + ("-" if cv["cv_chi2_best"] is None else f"{cv['cv_chi2_best']:.1f}") + ")")
    if result.get("template_change"):
        lines += ["", "## What the added effects change in the BF calibration", ""]
        lines += template_change_lines(result["template_change"])
    ne = notable_not_excluded(result)
    if ne:
        lines += ["", "## Not excluded, and what it would change", "",
                  "Effects tried and not added (below the threshold) that would move the "
                  "base a00 or a01 by 1 sigma or more if they were there:", ""]
        for d in ne:
            p = ", ".join(f"{k} = {v:.3g} +- {d['errors'][k]:.2g}"
                          for k, v in list(d["params"].items())[:3])
            lines.append(f"- **{d['effect']}** (delta BIC {d['delta_bic']:+.1f}; {p}): "
                         f"a00 {d['a00'][0]:.4g} +- {d['a00'][1]:.2g} "
                         f"({d['a00_shift_sd']:+.1f} sigma), a01 {d['a01'][0]:.4g} +- "
                         f"{d['a01'][1]:.2g} ({d['a01_shift_sd']:+.1f} sigma)")
    lines += _observables_markdown(result.get("observables"))
    lines += ["", "## Not identifiable from this input", ""]
    lines += [f"- {k}: {v}" for k, v in result["not_identifiable"].items()] or ["(none)"]
    lines += ["", "## Verdict", "", result["verdict"], ""]
    for f in figures:
        lines += [f"![{f}]({f})", ""]
    return "\n".join(lines)


def notable_not_excluded(result, threshold=1.0):
    """The entries of a diagnosis' ``not_excluded`` that would move the base a00
    or a01 by at least ``threshold`` of the final fit's errors (report and CLI)."""
    return [d for d in result.get("not_excluded") or []
            if max(abs(d["a00_shift_sd"]), abs(d["a01_shift_sd"])) >= threshold]


def template_change_lines(tc):
    """Markdown lines of :func:`~lsst_bfdrift.diagnosis.consequence.template_change`."""
    if not tc.get("available"):
        return [f"Not assessed: {tc.get('reason', 'no result')}."]
    i, j = tc["largest_shift_lag"]
    s = tc["shift"][f"{i},{j}"]
    lines = [f"Base model a_ij without and with the effects: largest shift at a{i}{j}, "
             f"{s['before']:.4g} -> {s['after']:.4g} 1/e ({tc['largest_shift']:+.1f} sigma)."]
    for key in ("0,0", "0,1", "1,0"):
        if key in tc["shift"]:
            v = tc["shift"][key]
            lines.append(f"- a{key.replace(',', '')}: {v['before']:.4g} -> {v['after']:.4g} "
                         f"+- {v['error']:.2g} ({v['sigma']:+.1f} sigma)")
    if not tc["changed"]:
        lines.append(f"No a_ij moved by more than {tc['threshold']:g} sigma: the calibrated "
                     "template does not change.")
        return lines
    for side, t in tc.get("templates", {}).items():
        lines.append(f"- template calibrated {side}: a00 {_num(t['a00'], '.4g')}, a01 "
                     f"{_num(t['a01'], '.4g')}, a10 {_num(t['a10'], '.4g')} (chi2/dof "
                     f"{t['chi2_dof']:.2f})")
    st = tc.get("stars")
    if st:
        lines.append(f"- stars (noise-free Gaussians, FWHM {st['fwhm_px']:g} px, "
                     f"{st['fluxes'][0]:.0e}-{st['fluxes'][-1]:.1e} e, the package's forward "
                     f"model): correcting with the template calibrated without the effects "
                     f"leaves {100 * st['size_left']:+.1f} % of the size-flux slope and "
                     f"{100 * st['e1_left']:+.1f} % of the e1-flux slope, if the final model "
                     "is right (> 0 under-, < 0 over-corrected)")
    return lines


def _num(v, fmt=".3g"):
    return "-" if v is None else format(v, fmt)


def _observables_markdown(findings):
    """Lines of the 'Observables beside the fit' section (empty without findings)."""
    if not findings:
        return []
    lines = ["", "## Observables beside the fit", "",
             "Checks the base BF model predicts exactly; they do not change the fit.", "",
             "| observable | available | value | error | sign | chi2 / dof | p | finding | "
             "moved by |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, f in findings.items():
        if not f["available"]:
            lines.append(f"| {name} | no | - | - | - | - | - | not available with these data "
                         f"({f['reason']}) | {', '.join(f.get('moved_by', [])) or '-'} |")
            continue
        chi = "-" if f.get("chi2") is None else f"{f['chi2']:.1f} / {f['dof']}"
        lines.append(f"| {name} | yes | {_num(f['value'])} {f.get('unit', '')} | "
                     f"{_num(f['error'], '.2g')} | {f['sign'] or '-'} | {chi} | "
                     f"{_num(f['p_value'], '.2g')} | "
                     f"{'**detected**' if f['detected'] else 'none'} | "
                     f"{', '.join(f.get('moved_by', [])) or '-'} |")
    lines.append("")
    for name, f in findings.items():
        if f["available"]:
            lev = ", ".join(f"{v:.4g}" for v in f.get("levels", [])[:8])
            lines.append(f"- **{name}** ({f.get('quantity', '')}"
                         + (f"; levels {lev} ADU" if lev and f["detected"] else "") + "): "
                         + f["description"])
    return lines


def write_report(result, outdir, *, extra=None):
    """Write ``report.md``, ``diagnosis.json`` and figures into ``outdir``.

    Parameters
    ----------
    result : dict
        ``Diagnosis.as_dict()``.
    outdir : str
        Directory (created).
    extra : dict, optional
        More JSON content (e.g. the electrostatic fit).

    Returns
    -------
    list of str
        Paths written.
    """
    os.makedirs(outdir, exist_ok=True)
    figs = _figures(result, outdir)
    md = diagnosis_markdown(result, figs)
    out = []
    with atomic_output(os.path.join(outdir, "report.md")) as tmp:
        with open(tmp, "w") as fh:
            fh.write(md)
    out.append(os.path.join(outdir, "report.md"))
    payload = dict(result)
    if extra:
        payload.update(extra)
    with atomic_output(os.path.join(outdir, "diagnosis.json")) as tmp:
        with open(tmp, "w") as fh:
            json.dump(payload, fh, indent=1, default=float)
    out.append(os.path.join(outdir, "diagnosis.json"))
    return out + [os.path.join(outdir, f) for f in figs]
