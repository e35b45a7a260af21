"""Running estimators on runs, scoring them against truth, and timing them."""

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
