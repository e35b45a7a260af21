"""Running estimators on runs, scoring them against truth or a reference, and timing them.

Scores are per state group as well as overall: one group can dominate an overall MSE (on the
quadrotor flights the acceleration makes 92-93 % of it), so :func:`group_mse` gives each
group's MSE against a reference that may cover only some states (NaN elsewhere), and
:func:`normalised_change` an overall change in which every group weighs the same (each
group's MSE divided by the baseline estimator's MSE of that group).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from .data import Run
from .errors import DataError, ShapeError
from .estimators.contract import takes_missing_outputs


@dataclass(frozen=True)
class EstimateResult:
    """An estimator's output on one run.

    Attributes
    ----------
    label : e.g. ``"KNODE-MHE (C)"``.
    x_hat : (T, nx) estimates.
    seconds_per_step : mean wall time of one estimator step [s].
    rejections : outputs the innovation gate rejected over the run (0 for a clean run).
    """

    label: str
    x_hat: np.ndarray
    seconds_per_step: float
    rejections: int = 0

    def mse(self, x_true: np.ndarray) -> float:
        """Mean over samples and states of the squared error, the paper's metric."""
        return mse(self.x_hat, x_true)


def mse(x_hat: np.ndarray, x_true: np.ndarray) -> float:
    """Overall mean-squared error ``mean((x_hat - x_true)**2)`` over samples and states."""
    if x_hat.shape != x_true.shape:
        raise ShapeError(f"mse: estimate shape {x_hat.shape} != truth shape {x_true.shape}")
    return float(np.mean((x_hat - x_true) ** 2))


def mse_per_state(x_hat: np.ndarray, x_true: np.ndarray) -> np.ndarray:
    """(nx,) mean-squared error of each state."""
    return np.mean((x_hat - x_true) ** 2, axis=0)


def state_groups(system) -> dict[str, list[int]]:
    """The system's states grouped by unit (``"m": [0, 1, 2]``, ``"m/s": [3, 4, 5]``, ...),
    in order of first appearance: the groups whose errors are comparable numbers."""
    groups: dict[str, list[int]] = {}
    for i, signal in enumerate(system.states):
        groups.setdefault(signal.unit or "1", []).append(i)
    return groups


def group_mse(x_hat: np.ndarray, reference: np.ndarray, groups: dict[str, list[int]]) -> dict[str, float]:
    """Group -> MSE of ``x_hat`` against ``reference`` (both ``(T, n)``) over the group's
    states and the samples where the reference has values (NaN in the reference: no
    reference there); a group with no reference value at all is left out."""
    if x_hat.shape[0] != reference.shape[0]:
        raise ShapeError(f"group_mse: {x_hat.shape[0]} estimates against {reference.shape[0]} "
                         "reference samples")
    out = {}
    for name, idx in groups.items():
        ref = reference[:, idx]
        ok = np.isfinite(ref)
        if ok.any():
            out[name] = float(np.mean((x_hat[:, idx][ok] - ref[ok]) ** 2))
    return out


def normalised_change(estimate: dict[str, float], baseline: dict[str, float]) -> float:
    """The change [%] of the mean over the groups both score of ``MSE_g / MSE_g(baseline)``:
    ``100 (1 - mean_g ratio_g)``, positive when ``estimate`` is better; every group weighs
    the same whatever its units."""
    groups = [g for g in estimate if g in baseline and baseline[g] > 0]
    if not groups:
        return float("nan")
    return 100.0 * (1.0 - float(np.mean([estimate[g] / baseline[g] for g in groups])))


def run_estimator(estimator, run: Run, x0: np.ndarray, label: str,
                  P0: np.ndarray | None = None) -> EstimateResult:
    """Run ``estimator.run`` over a whole run from ``x0`` (and ``P0``, default: the estimator's
    own) and time it.

    A run with missing outputs (NaN in ``y``) needs an estimator that takes them
    (:func:`~learnest_codegen.estimators.contract.takes_missing_outputs`); otherwise this
    raises :class:`DataError` rather than letting it fail at the first gap.
    """
    missing = int(np.isnan(run.y).sum())
    if missing and not takes_missing_outputs(estimator):
        first = int(np.argwhere(np.isnan(run.y))[0, 0])
        raise DataError(f"{label}: the run has {missing} missing measurement(s) (empty y cells, "
                        f"the first at sample {first}), which {type(estimator).__name__} does not "
                        "take yet; use the Python reference (--backend python)")
    start = time.perf_counter()
    x_hat = estimator.run(run.u, run.y, np.asarray(x0, dtype=float), P0)
    seconds = time.perf_counter() - start
    return EstimateResult(label, np.asarray(x_hat), seconds / len(run),
                          int(getattr(estimator, "rejections", 0)))


def format_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """A plain-text table; ``columns`` holds ``(key, header, format)`` triples."""
    cells = [[h for _, h, _ in columns]]
    cells += [[format(r[k], f) if r.get(k) is not None else "-" for k, _, f in columns] for r in rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(row, widths)))
             for row in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)
