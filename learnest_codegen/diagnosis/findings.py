"""The findings of a diagnosis as JSON and as a few lines for the terminal."""

from __future__ import annotations

from typing import Sequence

from ..compilation import ESTIMATORS
from ..systems import System
from .effects import DERIVED, Effect
from .selection import EffectFit


def step_json(effects: Sequence[Effect], step: dict | None) -> dict | None:
    if step is None or step.get("index") is None:
        return step
    return {**step, "effect": effects[step["index"]].name}


def effects_json(system: System, effects: Sequence[Effect], fit: EffectFit) -> list[dict]:
    """One entry per selected effect; the columns of a multi-parameter effect (``Effect.group``)
    are one entry with all their parameters (and, for the ``a/X`` + ``1/X`` pattern of a gain over
    a time constant, the derived ``X`` and ``a`` under ``"derived"``)."""
    out, done = [], set()
    t_of = {st["index"]: float(st["t"]) for st in fit.steps}
    for k, j in enumerate(fit.chosen):
        e = effects[j]
        if e.group and e.group in done:
            continue
        ks = [i for i, jj in enumerate(fit.chosen) if effects[jj].group == e.group] if e.group else [k]
        cols = [effects[fit.chosen[i]] for i in ks]
        params = {c.param: float(fit.theta[i]) for c, i in zip(cols, ks)}
        how, target = e.channel.split(":", 1)
        if how == "param":
            params[target] = float(system.params[target] + fit.theta[k])
        entry = {"kind": e.kind, "state": e.state, "channel": e.channel,
                 "name": f"{e.group}({target})" if e.group else e.name,
                 "params": params,
                 "uncertainty": {c.param: float(fit.theta_std[i]) for c, i in zip(cols, ks)},
                 "units": {c.param: c.unit for c in cols},
                 "physical": bool(all(c.physical(float(fit.theta[i])) for c, i in zip(cols, ks))),
                 "in_sample_share": float(sum(fit.explained[i] for i in ks)),
                 "score": float(fit.scores[k]), "t": t_of.get(j, float("nan")),
                 "aliases": sorted({effects[a].name for i in ks for a in fit.aliases[i]
                                    if effects[a].group != e.group or not e.group}),
                 "description": "; ".join(c.description for c in cols)}
        if not e.group and e.derived is not None:
            entry["derived"] = e.derived(float(fit.theta[k]))
        if not e.group and fit.equivalents and fit.equivalents[k]:
            entry["equivalent"] = {effects[d].name: {"value": v, "param": effects[d].param,
                                                     "unit": effects[d].unit}
                                   for d, v in fit.equivalents[k].items()}
        if e.group:
            done.add(e.group)
            rates = [p for p in params if p.startswith("1/")] if e.group not in DERIVED else []
            derived = DERIVED[e.group](params) if e.group in DERIVED else {}
            for rate in rates:
                x = rate[2:]
                if params[rate] != 0:
                    derived[x] = 1.0 / params[rate]
                    for p, v in params.items():
                        if p.endswith("/" + x) and p != rate:
                            derived[p[:-len(x) - 1]] = v / params[rate]
            if derived:
                entry["derived"] = derived
        out.append(entry)
    return sorted(out, key=lambda d: -d["in_sample_share"])


def summary(report: dict) -> str:
    """A few lines for the terminal: the verdict with the rule that gave it, the two figures (the
    held-out gap closed, which decides, and the in-sample share explained), then the details."""
    closed = report.get("heldout_gap_closed")
    lines = [f"{report['system']}: {report['verdict']} - held-out gap closed "
             f"{'-' if closed is None else format(closed, '.1%')}, in-sample share explained "
             f"{report['explained_in_sample']:.1%} (source: {report['source']})",
             f"  why: {report['verdict_reason']}", f"  data: {report['basis']}"]
    for name, why in report.get("skipped", {}).items():
        lines.append(f"  skipped {name}: {why}")
    gaps = report.get("missing", {})
    if any(gaps.values()):
        lines.append("  missing cells: " + ", ".join(f"{v} {k}" for k, v in gaps.items() if v)
                     + " (inputs held, measurements interpolated, pairs without truth left out)")
    for s in report["where"]:
        if s["residual_state"]:
            lines.append(f"  {s['state']:>10}': share {s['share']:.0%}, snr {s['snr']:.3g}")
    for label, key in (("", "effects"), ("rejected: ", "rejected_effects")):
        for e in report.get(key, []):
            p = ", ".join(f"{k}={v:.4g}" for k, v in {**e["params"], **e.get("derived", {})}.items())
            against = [n.upper() for n, v in e.get("estimators", {}).items() if v == "rejected"]
            note = f"; rejected for the {' and the '.join(against)}" if against and not label else ""
            lines.append(f"  {label}{e['name']}: {p} (+-{next(iter(e['uncertainty'].values())):.2g}), "
                         f"{e['in_sample_share']:.0%} of the in-sample gap{note}")
    for c in report.get("consistency", []):
        if not c["consistent"]:
            lines.append(f"  {c['effect']} ({c['param']}): NOT the same on every run (per run "
                         + ", ".join("-" if v is None else f"{v:.3g}" for v in c["per_run"])
                         + f"; sign agrees on {c['sign_agreement']:.0%})")
    for b in report.get("selection", {}).get("blocked", []):
        lines.append(f"  {b['effect']}: not entered, its parameter differs between runs")
    one = report["shrink"]["one_step"]
    lines.append(f"  held-out one-step gap {one['before']:.4g} -> {one['after']:.4g} noise units^2"
                 + (f" (closed {one['closed']:.1%})" if one.get("closed") is not None else ""))
    for name in ESTIMATORS:
        if name in report["shrink"]:
            s = report["shrink"][name]
            lines.append(f"  {name.upper()} held-out MSE {s['before']:.4g} -> {s['after']:.4g}"
                         + (f" (closed {s['closed']:.0%})" if s.get("closed") is not None else "")
                         + (f", the data support {s['supported']:.4g} ({s['above_supported']:+.0%})"
                            if s.get("supported") else "")
                         + f": {s['verdict']}")
    return "\n".join(lines)
