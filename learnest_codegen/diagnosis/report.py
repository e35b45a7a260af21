"""The readable side of a diagnosis: ``report.md`` with PNG figures next to ``diagnosis.json``.

Figures (matplotlib, Agg):

* ``residual.png`` - the prior's one-step residual per residual state over time (fit data and
  held-out data), the noise-floor band, and on the held-out data the corrected prior's residual;
* ``regimes.png`` - per residual state, the binned mean residual over its three strongest
  drivers (the variables with the largest correlation ratio);
* ``effects.png`` - the selected effects' in-sample shares of the fit data's gap, and what is
  left in-sample (the verdict follows the held-out figures of ``shrink.png``);
* ``shrink.png`` - the gap before and after: one-step residual (RMS over the residual states, in
  units of the noise floor) and each estimator's MSE, with
  the KNODE model and (in simulation) the true dynamics alongside.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..compilation import ESTIMATORS  # noqa: E402
from .core import Diagnosis  # noqa: E402

MODEL_COLOURS = {"prior": "0.55", "corrected": "tab:orange", "knode": "tab:blue", "true": "black"}


def plot_residual(d: Diagnosis, path: Path) -> Path:
    system, rows = d.system, d.system.residual_state_names
    fig, axes = plt.subplots(len(rows), 1, figsize=(10, 2.4 * len(rows)), sharex=True, squeeze=False)
    t_fit = d.fit_pairs.t
    offset = float(t_fit.max()) if len(t_fit) else 0.0
    t_held = d.heldout_pairs.t + (offset if d.report["runs"] == 1 else 0.0)
    for ax, name in zip(axes[:, 0], rows):
        i = system.state_names.index(name)
        for k, seg in enumerate(np.unique(d.fit_pairs.segment)):  # one line per run
            mask = d.fit_pairs.segment == seg
            ax.plot(t_fit[mask], d.residual[mask, i], lw=0.6, color="0.55",
                    label="prior (fit data)" if k == 0 else None)
        ax.plot(t_held, d.heldout_residuals["prior"][:, i], lw=0.6, color="0.3", label="prior (held out)")
        ax.plot(t_held, d.heldout_residuals["corrected"][:, i], lw=0.6, color="tab:orange",
                label="corrected prior (held out)")
        ax.axhspan(-d.sigma[i], d.sigma[i], color="tab:green", alpha=0.15, label="noise floor")
        ax.set_ylabel(f"{name}' error\n[{system.states[i].unit}/s]")
    axes[0, 0].legend(loc="upper right", fontsize=7, ncol=4)
    axes[-1, 0].set_xlabel("t [s]" + ("" if d.report["runs"] == 1 else " (from each run's start)"))
    fig.suptitle(f"{system.name}: one-step residual of the prior (derivative error)")
    return _save(fig, path)


def plot_regimes(d: Diagnosis, path: Path) -> Path:
    regimes = d.report["regimes"]
    rows = list(regimes["drivers"])
    fig, axes = plt.subplots(len(rows), 3, figsize=(11, 2.6 * len(rows)), squeeze=False)
    for r, state in enumerate(rows):
        for c in range(3):
            ax = axes[r, c]
            drivers = regimes["drivers"][state]
            if c >= len(drivers):
                ax.axis("off")
                continue
            var = drivers[c]["variable"]
            entry = regimes["variables"][var]
            edges = np.asarray(entry["edges"])
            centres = 0.5 * (edges[:-1] + edges[1:])
            mean, rms = np.asarray(entry["mean"][state]), np.asarray(entry["rms"][state])
            ax.bar(centres, rms, width=np.diff(edges) * 0.9, color="0.85", label="RMS")
            ax.plot(centres, mean, "o-", color="tab:red", label="mean")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(f"{state}' vs {var}  (eta^2 {drivers[c]['eta2']:.2f})", fontsize=9)
            if c == 0:
                ax.set_ylabel(f"{state}' error")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"{d.system.name}: where the residual lives (binned over its strongest drivers)")
    return _save(fig, path)


def plot_effects(d: Diagnosis, path: Path) -> Path:
    effects = d.report["effects"]
    names = [e["name"] for e in effects] + ["left in-sample"]
    values = [e["in_sample_share"] for e in effects] + [1.0 - d.report["explained_in_sample"]]
    fig, ax = plt.subplots(figsize=(8, 0.5 * len(names) + 1.5))
    colours = ["tab:orange"] * len(effects) + ["0.6"]
    ax.barh(names[::-1], values[::-1], color=colours[::-1])
    for y, v in enumerate(values[::-1]):
        ax.text(v, y, f" {v:.0%}", va="center", fontsize=8)
    ax.set_xlim(0, 1.15)
    ax.set_xlabel("in-sample share of the fit data's gap")
    closed = d.report.get("heldout_gap_closed")
    ax.set_title(f"{d.system.name}: {d.report['verdict']} (held-out gap closed "
                 f"{'-' if closed is None else format(closed, '.0%')})", fontsize=9)
    return _save(fig, path)


def plot_shrink(d: Diagnosis, path: Path) -> Path:
    shrink = d.report["shrink"]
    panels = ["one_step"] + [k for k in ESTIMATORS if k in shrink]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.5), squeeze=False)
    for ax, key in zip(axes[0], panels):
        entry = shrink[key] if key != "one_step" else shrink[key]["rms_over_floor"]
        labels = [m for m in ("prior", "corrected", "knode", "true") if m in entry]
        values = [max(entry[m], 1e-16) for m in labels]
        ax.bar(labels, values, color=[MODEL_COLOURS[m] for m in labels])
        ax.set_yscale("log")
        if key == "one_step":
            ax.axhline(1.0, color="tab:green", ls="--", label="noise floor")
            ax.legend(fontsize=7)
        ax.set_title({"one_step": "one-step residual RMS / noise floor"}.get(key, f"{key.upper()} MSE"),
                     fontsize=9)
    fig.suptitle(f"{d.system.name}: how far the gap shrinks (held-out data)")
    return _save(fig, path)


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _f(v, fmt=".3g") -> str:
    return "-" if v is None else format(v, fmt)


def markdown(d: Diagnosis, figures: dict[str, str]) -> str:
    r = d.report
    closed = r.get("heldout_gap_closed")
    lines = [f"# Diagnosis of the `{r['system']}` prior", "",
             f"**Verdict: {r['verdict']}**: {r['verdict_reason']}."
             + "".join(f" {n.upper()}: {v}." for n, v in r.get("estimator_verdicts", {}).items()), "",
             f"Two figures: the **held-out gap closed** {_f(closed, '.1%')} (the verdict follows it) and "
             f"the **in-sample share explained** {r['explained_in_sample']:.1%} (of the fit data's gap).", "",
             f"Data: {r['basis']}; {r['fit_pairs']} pairs fitted, {r['heldout_pairs']} held out. "
             f"Source: {r['source']}" + (f" (observer `{r['observer']}`)" if r.get("observer") else "")
             + f". Noise floor: {r['noise_floor']['method']}."
             + (f" Estimators scored against {r['reference']}." if r.get("reference") else ""), ""]
    lines += [f"Skipped `{k}`: {v}" for k, v in r.get("skipped", {}).items()]
    if any(r.get("missing", {}).values()):
        lines.append("Missing cells: " + ", ".join(f"{v} {k}" for k, v in r["missing"].items() if v)
                     + " (inputs held, measurements interpolated, pairs without truth left out).")
    lines += ["", "## 1. Where the gap lies", "",
             "| state | share | snr | RMS residual | floor | unit |", "|---|---|---|---|---|---|"]
    for s in r["where"]:
        mark = "" if s["residual_state"] else " (kinematic)"
        lines.append(f"| {s['state']}{mark} | {s['share']:.0%} | {s['snr']:.3g} | {s['rms']:.3g} | "
                     f"{s['floor']:.3g} | {s['unit']} |")
    lines += ["", "Strongest drivers (correlation ratio eta^2 of the binned mean residual):", ""]
    for state, drivers in r["regimes"]["drivers"].items():
        lines.append(f"- `{state}'`: " + ", ".join(f"{x['variable']} ({x['eta2']:.2f})" for x in drivers))
    if r.get("knode"):
        lines += ["", "KNODE's learned residual against the measured one:", "",
                  "| state | R^2 | corr | learned RMS | measured RMS |", "|---|---|---|---|---|"]
        for s, k in r["knode"].items():
            lines.append(f"| {s} | {_f(k['r2'])} | {_f(k['corr'])} | {_f(k['learned_rms'])} | "
                         f"{_f(k['measured_rms'])} |")
    lines += ["", f"![residual]({figures['residual']})", "", f"![regimes]({figures['regimes']})", "",
              "## 2. Which effect causes it", "",
              "| effect | parameters | +- (block bootstrap) | in-sample share | held-out score alone "
              "| aliases |",
              "|---|---|---|---|---|---|"]
    for e in r["effects"] + r.get("rejected_effects", []):
        params = ", ".join(f"{k} = {v:.4g}" for k, v in {**e["params"], **e.get("derived", {})}.items())
        params += "".join(f"; as {n}: {q['param']} = {q['value']:.4g} {q['unit']}"
                          for n, q in e.get("equivalent", {}).items())
        unc = ", ".join(f"{k}: {v:.2g} {e['units'][k]}" for k, v in e["uncertainty"].items())
        name = e["name"] + (" (REJECTED: worse held out)" if e in r.get("rejected_effects", []) else "")
        lines.append(f"| {name} | {params} | {unc} | {e['in_sample_share']:.0%} | {e['score']:.0%} | "
                     f"{', '.join(e['aliases']) or '-'} |")
    if not r["effects"] and not r.get("rejected_effects"):
        lines.append("| (none selected) | | | | | |")
    sel = r["selection"]
    for dr in sel.get("dropped", []):
        lines.append(f"\nDropped after others entered: `{dr['effect']}` (t = {dr['t']:.2g}).")
    for w in sel.get("exchanged", []):
        lines.append(f"\nExchanged on re-test ({w['why']}): {', '.join(f'`{a}`' for a in w['added'])} "
                     f"instead of `{w['removed']}`.")
    for b in sel.get("blocked", []):
        lines.append(f"\nNot entered, its parameter differs between runs: `{b['effect']}` (per run "
                     + ", ".join(", ".join(f"{v:.3g}" for v in col) for col in b.get("per_run", [])) + ").")
    for w in sel.get("swapped", []):
        lines.append(f"\nEquivalent on these data, the prior's own parameter kept: `{w['added']}` "
                     f"instead of `{w['removed']}`.")
    if sel.get("refit", "converged").startswith("failed"):
        lines.append(f"\n**Refit failed**: {sel['refit']}.")
    if r.get("consistency"):
        lines += ["", f"Consistency across runs ({r['folds']}):", "",
                  "| effect | pooled | median per run | spread | sign agrees | consistent |",
                  "|---|---|---|---|---|---|"]
        for c in r["consistency"]:
            lines.append(f"| {c['effect']} ({c['param']}) | {c['pooled']:.4g} | {c['median']:.4g} | "
                         f"{c['spread']:.2g} | {c['sign_agreement']:.0%} | "
                         f"{'yes' if c['consistent'] else 'NO'} |")
    stop = r["selection"]["stopped_at"]
    if stop and stop.get("effect"):
        lines += ["", f"Selection stopped at `{stop['effect']}`: {stop['reason']} "
                      f"(t = {stop['t']:.2g}, held-out gain {stop['gain_abs']:.3g} against "
                      f"{stop['gain_needed']:.3g} needed of a remaining gap of {stop['remaining_gap']:.3g} "
                      f"noise units^2, size {stop['size']:.3g} vs needed {stop['size_needed']:.3g})."]
    lines += ["", f"![effects]({figures['effects']})", "", "## 3. How far it shrinks (held-out data)", "",
              "| quantity | prior | corrected | KNODE | true | closed | closed by KNODE | verdict |",
              "|---|---|---|---|---|---|---|---|"]
    for key, entry in r["shrink"].items():
        if not isinstance(entry, dict):
            continue
        lines.append(f"| {key} ({entry['metric']}) | {_f(entry.get('prior'))} | "
                     f"{_f(entry.get('corrected'))} | {_f(entry.get('knode'))} | {_f(entry.get('true'))} | "
                     f"{_f(entry.get('closed'), '.1%')} | {_f(entry.get('closed_knode'), '.1%')} | "
                     f"{entry.get('verdict', '-')} |")
    lines += ["", f"![shrink]({figures['shrink']})", ""]
    return "\n".join(lines)


def write_report(d: Diagnosis, out: str | Path) -> Path:
    """Write the figures and ``report.md`` into ``out``; returns the report's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figures = {"residual": plot_residual(d, out / "residual.png").name,
               "regimes": plot_regimes(d, out / "regimes.png").name,
               "effects": plot_effects(d, out / "effects.png").name,
               "shrink": plot_shrink(d, out / "shrink.png").name}
    path = out / "report.md"
    path.write_text(markdown(d, figures))
    return path
