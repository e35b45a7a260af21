"""The quadrotor study per state group and per reference: the figures that hold or not.

An overall MSE can improve while a state group gets worse (on the flights the acceleration
makes 92-93 % of it), and a change against a long-window reference can come from smoothing as
much as the reference does. So each pair of estimators is compared per state group (position,
velocity, acceleration) and per reference (the central-difference velocity and each
Savitzky-Golay window), paired per flight (:class:`~.quadrotor_report.Paired`), beside a
normalised overall change (:func:`~learnest_codegen.evaluation.normalised_change`: every group
weighs the same). A claim holds only if it holds at every reference.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..evaluation import normalised_change
from .quadrotor_cases import GROUP_NAMES

OVERALL = "overall"
COLUMNS = (*GROUP_NAMES, OVERALL)


def references_of(per_case: dict[str, dict[str, dict]]) -> list[str]:
    """The references the flights are scored against: the central differences first, then the
    Savitzky-Golay windows from the shortest, then any other (``truth`` in simulation)."""
    names = {name for methods in per_case.values() for scores in methods.values()
             for name in scores.get("by_reference", {})}

    def order(name: str):
        if name.startswith("cd_"):
            return (0, 0.0, name)
        if name.startswith("sg_") and name.endswith("s"):
            try:
                return (1, float(name[3:-1]), name)
            except ValueError:
                pass
        return (2, 0.0, name)

    return sorted(names, key=order)


def _group(scores: dict, reference: str, group: str) -> float:
    return scores.get("by_reference", {}).get(reference, {}).get(group, np.nan)


def by_reference(per_case: dict[str, dict[str, dict]], knode: str, nominal: str, paired_of) -> dict:
    """Reference -> column (``p``, ``v``, ``a``, ``overall``) -> ``paired_of(nominal MSEs,
    knode MSEs)`` over the flights (``overall``: 1 against the mean ratio)."""
    out = {}
    for ref in references_of(per_case):
        row = {}
        for g in GROUP_NAMES:
            nom = {c: _group(m.get(nominal, {}), ref, g) for c, m in per_case.items()}
            kn = {c: _group(m.get(knode, {}), ref, g) for c, m in per_case.items()}
            if any(np.isfinite(v) for v in kn.values()):
                row[g] = paired_of(nom, kn)
        ratios = {}
        for c, m in per_case.items():
            b, e = m.get(nominal, {}).get("by_reference", {}).get(ref), m.get(knode, {}).get(
                "by_reference", {}).get(ref)
            if b and e:
                ratios[c] = 1.0 - normalised_change(e, b) / 100.0
        if ratios:
            row[OVERALL] = paired_of(dict.fromkeys(ratios, 1.0), ratios)
        out[ref] = row
    return out


def onboard_velocity(per_case: dict[str, dict[str, dict]], knode: str, onboard: str, paired_of) -> dict:
    """Reference -> paired velocity change of ``knode`` against the onboard EKF."""
    out = {}
    for ref in references_of(per_case):
        nom = {c: _group(m.get(onboard, {}), ref, "v") for c, m in per_case.items()}
        kn = {c: _group(m.get(knode, {}), ref, "v") for c, m in per_case.items()}
        if any(np.isfinite(v) for v in nom.values()):
            out[ref] = paired_of(nom, kn)
    return out


def _cell(p) -> str:
    if p is None or not p.n:
        return "-"
    return f"{p.mean:+.1f} % ({p.improved}/{p.n}, worst {p.worst:+.1f} %)"


def state_tables(summary) -> list[str]:
    """Per pair: a table of references (rows) by state group and normalised overall (columns)."""
    lines = []
    for key, refs in summary.by_reference.items():
        lines += [f"#### {key}: {summary.train}, features {summary.features!r}", "",
                  "| reference | " + " | ".join(GROUP_NAMES[g] if g in GROUP_NAMES else "overall (normalised)"
                                               for g in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
        for ref in sorted(refs, key=references_of(summary.per_case).index):
            lines.append(f"| {ref} | " + " | ".join(_cell(refs[ref].get(g)) for g in COLUMNS) + " |")
        lines.append("")
    if summary.onboard:
        onboard = summary.onboard
        lines += [f"#### Velocity against the onboard EKF: {summary.train}, features {summary.features!r}",
                  "", "| reference | " + " | ".join(onboard) + " |", "|---" * (len(onboard) + 1) + "|"]
        for ref in references_of(summary.per_case):
            lines.append(f"| {ref} | " + " | ".join(_cell(v.get(ref)) for v in onboard.values()) + " |")
        lines.append("")
    return lines


def _scales(record: dict) -> str:
    groups = record.get("groups") or []
    parts = [f"process x{record.get('process_scale', 1):g}"]
    for names, scale in zip(groups, record.get("measurement_scales") or []):
        parts.append(f"{'/'.join(names)} x{record.get('measurement_scale', 1) * scale:g}")
    if not groups:
        parts.append(f"measurement x{record.get('measurement_scale', 1):g}")
    return "; ".join(parts)


def tuning_table(summaries: Sequence) -> list[str]:
    """The tunings chosen on each fold's training flights, their criterion, the gate's
    rejections on those flights, and whether a scale sits on the grid's edge."""
    rows = []
    for s in summaries:
        for fold, record in (s.tunings or {}).items():
            for model, estimators in (("KNODE", {k: v for k, v in record.items() if k != "nominal"}),
                                      ("nominal", record.get("nominal", {}))):
                for est, r in estimators.items():
                    edge = ", ".join("/".join(g) for g in r.get("edge", [])) or "no"
                    rows.append(f"| {fold} | {s.features} | {model} {est} | {_scales(r)} | "
                                f"{r.get('criterion', float('nan')):.3f} | "
                                f"{100 * r.get('rejected_share', float('nan')):.2f} % | "
                                f"{r.get('gate_widened', 0)} | {edge} |")
    if not rows:
        return []
    return ["### Noise tuned on the training flights", "",
            "Chosen by predicting the raw position measurements 1 sample, 0.1 s and 0.5 s ahead "
            "of each estimate (criterion: mean log MSE, lower is better); the gate's rejections "
            "are on the training flights' outputs; 'gate widened' counts doublings of every std "
            "that kept them under 1 %.", "",
            "| fold | features | estimator | scales | criterion | gate rejects | gate widened | "
            "on the grid's edge |", "|---|---|---|---|---|---|---|---|", *rows, ""]


def findings_lines(findings: Sequence[dict], skipped: dict[str, str] | None) -> list[str]:
    """The recordings' check findings and the recordings left out, one line each."""
    if not findings and not skipped:
        return []
    from ..recordings.checks import Finding

    lines = ["### Recordings checked", ""]
    lines += [f"- {Finding(**f).line()}" for f in findings]
    listed = {f["recording"] for f in findings if f.get("action") == "left out"}
    lines += [f"- {k}: left out: {v}" for k, v in (skipped or {}).items() if k not in listed]
    return lines + [""]
