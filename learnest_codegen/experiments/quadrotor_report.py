"""The quadrotor study's report: paired per-flight changes, tables and the paired figure.

A median over test flights can improve while most flights get worse (the flights near the
median improve, the others do not), so the headline is paired: per test flight, the relative
change of a KNODE estimator's MSE against its nominal estimator's on the same flight, and over
the flights its mean, the share of flights it improves and the worst flight, per trajectory
type and overall, beside the median. Measured results: ``docs/reports/flights.md``.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

ONBOARD = "onboard EKF"
ALL = "all"


def trajectory_type(name: str) -> str:
    """A flight's trajectory type from its name: ``"B3_figure8_fast_rep1"`` -> ``"figure8"``;
    a simulated run (``"sim_seed3"``) -> ``"sim"``."""
    match = re.match(r"^[A-Za-z]\d+_([A-Za-z0-9]+)_", name)
    if match:
        return match.group(1)
    return re.sub(r"[_\d]+$", "", name.split("_seed")[0]) or name


def change(nominal: float, knode: float) -> float:
    """Relative change of the MSE [%]: positive when KNODE is better."""
    return 100.0 * (nominal - knode) / nominal


@dataclass(frozen=True)
class Paired:
    """Per-flight changes of one KNODE estimator against its nominal one, over a set of flights.

    Attributes
    ----------
    changes : flight -> ``100 (MSE_nominal - MSE_knode) / MSE_nominal`` [%].
    mean, median : of the changes [%].
    improved : flights with a positive change; ``n`` flights in all.
    worst_flight, worst : the flight with the lowest change, and that change [%].
    median_mse : the change of the median MSE over the flights [%] (the paper's figure).
    """

    changes: dict[str, float]
    mean: float
    median: float
    improved: int
    n: int
    worst_flight: str
    worst: float
    median_mse: float

    @classmethod
    def of(cls, nominal: dict[str, float], knode: dict[str, float]) -> "Paired":
        """From per-flight MSEs (flights whose MSE is not finite for both are left out)."""
        flights = [k for k in knode if np.isfinite(knode[k]) and np.isfinite(nominal.get(k, np.nan))]
        changes = {k: change(nominal[k], knode[k]) for k in flights}
        values = np.array(list(changes.values()))
        worst = min(changes, key=changes.get) if changes else ""
        median_mse = (change(float(np.median([nominal[k] for k in flights])),
                             float(np.median([knode[k] for k in flights]))) if flights else float("nan"))
        return cls(changes, float(np.mean(values)) if flights else float("nan"),
                   float(np.median(values)) if flights else float("nan"), int(np.sum(values > 0)),
                   len(flights), worst, changes.get(worst, float("nan")), median_mse)

    @property
    def share_improved(self) -> float:
        return self.improved / self.n if self.n else float("nan")

    def headline(self) -> str:
        """``"mean +4.7 %, 15/16 better, worst -0.3 % (B3_figure8_medium_rep1), median +5.6 %"``."""
        return (f"mean {self.mean:+.1f} %, {self.improved}/{self.n} better, worst {self.worst:+.1f} % "
                f"({self.worst_flight}), median {self.median:+.1f} %")


@dataclass(frozen=True)
class Summary:
    """One study (a training set, or a protocol's folds pooled) with one choice of features.

    Attributes
    ----------
    train : the training flight, or the protocol's name.
    features : the residual's features.
    per_case : test flight -> method label -> scores (``mse``, ``mse_p/v/a``, ``rejected``,
        ``rejected_share``, and for KNODE ``outside``: the share of samples outside the
        model's training range).
    medians : method -> median overall MSE over the test flights.
    velocity_medians : method -> median velocity MSE (the onboard EKF included).
    paired : pair key (:func:`pair_key`: the KNODE label, or "KNODE vs nominal" for another
        nominal estimator than its own) -> group (``"all"`` and each trajectory type) -> :class:`Paired`.
    trained_on : test flight -> the flights its model was trained on.
    by_reference : pair key -> reference -> state group (``p``, ``v``, ``a``) or ``overall``
        (normalised) -> :class:`Paired` over all test flights (:mod:`.quadrotor_states`).
    onboard : KNODE label -> reference -> :class:`Paired` velocity change against the onboard EKF.
    tunings : fold -> the tuning records of its KNODE and nominal estimators.
    trainings : fold -> the model's training record (fitted prior parameters, net kept).
    """

    train: str
    features: str
    per_case: dict[str, dict[str, dict]]
    medians: dict[str, float]
    velocity_medians: dict[str, float]
    paired: dict[str, dict[str, Paired]]
    trained_on: dict[str, list[str]]
    by_reference: dict = field(default_factory=dict)
    onboard: dict = field(default_factory=dict)
    tunings: dict = field(default_factory=dict)
    trainings: dict = field(default_factory=dict)

    @property
    def improvement(self) -> dict[str, float]:
        """KNODE label -> change of the median MSE over all test flights [%] (the paper's)."""
        return {k: groups[ALL].median_mse for k, groups in self.paired.items()}

    def to_json(self) -> dict:
        return asdict(self)


def pair_key(knode: str, nominal: str) -> str:
    """The key of a pair in :attr:`Summary.paired`: the KNODE label against its own nominal
    estimator (``"KNODE-UKF"`` against ``"UKF"``), else ``"KNODE-UKF vs UKF (tuned)"``."""
    return knode if knode == f"KNODE-{nominal}" else f"{knode} vs {nominal}"


def pair_labels(key: str) -> tuple[str, str]:
    """``(KNODE label, nominal label)`` of a :func:`pair_key`."""
    knode, _, nominal = key.partition(" vs ")
    return knode, nominal or knode.removeprefix("KNODE-")


def summarise(nominal: dict[str, dict], knode: dict, pairs: Sequence[tuple[str, str]]) -> Summary:
    """Combine the nominal results and one KNODE study (``train_and_test``'s or a protocol's
    pooled dict) into a :class:`Summary`."""
    per_case = {name: {**nominal[name], **methods} for name, methods in knode["cases"].items()}
    order = [m for k, n in pairs for m in (n, k)] + [ONBOARD]
    labels = [m for m in order if all(m in v for v in per_case.values())]

    def median(key: str, label: str) -> float:
        return float(np.nanmedian([v[label].get(key, np.nan) for v in per_case.values()]))

    medians = {m: median("mse", m) for m in labels if m != ONBOARD}
    velocity = {m: median("mse_v", m) for m in labels}
    groups = {ALL: list(per_case)}
    for name in per_case:
        groups.setdefault(trajectory_type(name), []).append(name)
    paired = {}
    for k, n in pairs:
        if k in medians and n in medians:
            paired[pair_key(k, n)] = {g: Paired.of({c: per_case[c][n]["mse"] for c in names},
                                      {c: per_case[c][k]["mse"] for c in names})
                         for g, names in groups.items()}
    trained_on = knode.get("trained_on") or {c: list(knode.get("train_cases", [knode["train"]]))
                                             for c in per_case}
    from .quadrotor_states import by_reference, onboard_velocity

    states = {pair_key(k, n): by_reference(per_case, k, n, Paired.of) for k, n in pairs
              if k in medians and n in medians}
    onboard = ({k: onboard_velocity(per_case, k, ONBOARD, Paired.of) for k, _ in pairs if k in medians}
               if ONBOARD in labels else {})
    tunings = knode.get("tunings") or ({knode["train"]: knode["tuning"]} if knode.get("tuning") else {})
    trainings = knode.get("trainings") or {knode["train"]: knode.get("training", {})}
    return Summary(knode["train"], knode["features"], per_case, medians, velocity, paired, trained_on,
                   states, onboard, tunings, trainings)


def _cell(methods: dict, label: str) -> str:
    scores = methods.get(label, {})
    if label == ONBOARD:
        return f"-; {scores.get('mse_v', float('nan')):.3g}"
    return f"{scores.get('mse', float('nan')):.4g}; {scores.get('mse_v', float('nan')):.3g}"


def case_table(s: Summary) -> list[str]:
    """Per test flight: every method's MSE (overall; velocity), each KNODE estimator's change,
    the gate's rejections and the share of samples outside the training range."""
    labels = [*s.medians, *([ONBOARD] if ONBOARD in s.velocity_medians else [])]
    knodes = list(s.paired)
    head = ["test flight", *labels, *(f"{k} change" for k in knodes), "gate rejections", "outside range"]
    lines = [f"#### {s.train}, features {s.features!r} (MSE overall; velocity MSE)", "",
             "| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for name, methods in s.per_case.items():
        changes = [f"{s.paired[k][ALL].changes.get(name, float('nan')):+.1f} %" for k in knodes]
        rejected = ", ".join(f"{m} {methods[m].get('rejected', 0)}" for m in s.medians
                             if methods[m].get("rejected"))
        outside = ", ".join(f"{100 * methods[k]['outside']:.0f} %" for k in knodes[:1]
                            if methods[k].get("outside") is not None)
        lines.append(f"| {name} | " + " | ".join([_cell(methods, m) for m in labels] + changes
                                                 + [rejected or "0", outside or "-"]) + " |")
    lines.append("| **median** | " + " | ".join(
        [f"**{s.medians[m]:.4g}**; {s.velocity_medians[m]:.3g}" if m != ONBOARD
         else f"-; {s.velocity_medians[m]:.3g}" for m in labels]
        + [f"{s.paired[k][ALL].median:+.1f} %" for k in knodes] + ["", ""]) + " |")
    return lines + [""]


def paired_table(summaries: Sequence[Summary]) -> list[str]:
    """The headline: per study, KNODE estimator and group, the paired figures beside the median."""
    head = ["train", "features", "estimator", "flights", "mean change", "better", "worst flight",
            "median change", "median-MSE change"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for s in summaries:
        for k, groups in s.paired.items():
            for g, p in groups.items():
                lines.append(f"| {s.train} | {s.features} | {k} | {g} ({p.n}) | **{p.mean:+.1f} %** | "
                             f"{p.improved}/{p.n} | {p.worst:+.1f} % ({p.worst_flight}) | "
                             f"{p.median:+.1f} % | "
                             f"{p.median_mse:+.1f} % |")
    return lines


def markdown(summaries: Sequence[Summary], matrix: Sequence[Summary] = (),
             paper: dict[str, float] | None = None, skipped: dict[str, str] | None = None,
             findings: Sequence[dict] = ()) -> str:
    """The report: per state group and reference, the paired changes of every study (and
    the velocity against the onboard EKF), the tunings chosen, the paired headline of the
    overall MSE (and of the training-flight ``matrix``), each study's per-flight table, and
    what the recording checks found."""
    from ..recordings.references import REFERENCES
    from .quadrotor_states import findings_lines, state_tables, tuning_table

    note = ""
    if paper:
        note = " (the paper's median-MSE change on flights of the training type: " + ", ".join(
            f"{k} {v:+.1f} %" for k, v in paper.items()) + ")"
    refs = {r for s in summaries for v in s.by_reference.values() for r in v}
    lines = ["### Per state group and reference", "",
             "Per test flight and state group, change = 100 (MSE nominal - MSE KNODE) / MSE nominal "
             "(positive is better); overall (normalised) = 100 (1 - mean over the groups of MSE KNODE / "
             "MSE nominal), every group weighing the same. Each cell: the mean over the flights "
             "(flights better / flights, worst flight). References: "
             + "; ".join(f"{k}: {v}" for k, v in REFERENCES.items() if k in refs) + ".", ""]
    for s in summaries:
        lines += state_tables(s)
    lines += tuning_table(summaries)
    lines += ["### Paired per-flight change of KNODE against its nominal estimator (overall MSE, "
              "the paper's reference)" + note, "",
             "Change = 100 (MSE nominal - MSE KNODE) / MSE nominal on the same flight; "
             "positive is better.", "", *paired_table([*summaries, *matrix]), "",
             "### Per test flight", ""]
    for s in summaries:
        lines += case_table(s)
    lines += findings_lines(findings, skipped)
    return "\n".join(lines) + "\n"


def headline(summaries: Sequence[Summary]) -> str:
    """The lines the command prints: one per study and KNODE estimator, overall."""
    return "\n".join(f"{s.train}, {s.features}: {k}: {groups[ALL].headline()}"
                     for s in summaries for k, groups in s.paired.items())


def plot_paired(summaries: Sequence[Summary], path: Path) -> Path:
    """Per study: each test flight's MSE under the nominal and the KNODE estimator joined by a
    line (green: KNODE better, red: worse), box plots behind; log scale."""
    from ..plotting import _save, plt

    fig, axes = plt.subplots(1, len(summaries), figsize=(5.0 * len(summaries), 4.2), squeeze=False)
    for ax, s in zip(axes[0], summaries):
        ticks, names = [], []
        for j, (k, groups) in enumerate(s.paired.items()):
            k_label, n_label = pair_labels(k)
            x0, x1 = 3 * j, 3 * j + 1
            nom = np.array([s.per_case[c][n_label]["mse"] for c in groups[ALL].changes])
            kno = np.array([s.per_case[c][k_label]["mse"] for c in groups[ALL].changes])
            ax.boxplot([nom, kno], positions=[x0, x1], widths=0.5, medianprops={"color": "tab:orange"},
                       showfliers=False)
            for a, b in zip(nom, kno):
                ax.plot([x0, x1], [a, b], color="tab:green" if b < a else "tab:red", alpha=0.7, lw=1,
                        marker="o", ms=2.5)
            p = groups[ALL]
            ax.text(x0 + 0.5, 1.02, f"mean {p.mean:+.1f} %\n{p.improved}/{p.n} better",
                    transform=ax.get_xaxis_transform(), ha="center", va="bottom", fontsize=8)
            ticks += [x0, x1]
            names += [n_label, k_label]
        ax.set_xticks(ticks, names, rotation=20)
        ax.set_yscale("log")
        ax.set_ylabel("MSE over the 9 translational states")
        ax.set_title(f"{s.train}, features {s.features}", fontsize=9, pad=26)
    fig.tight_layout()
    return _save(fig, path)
