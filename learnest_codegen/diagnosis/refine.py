"""Damped, bounded refinement of effect parameters on the nonlinear one-step residual.

The selection fits parameters to first order; a parameter that enters nonlinearly (an inertia
``J`` in ``tau / J``) then needs a few iterations on the full residual. Plain Gauss-Newton can
run away there: with a residual that an inertia explains only partly, its step can send ``J``
through zero (the derivative blows up) and on to 1e52. So the refinement is Levenberg-Marquardt
with two safeguards, and it never raises:

* **step limits in the parameter's own units**: a change of a prior parameter ``p`` is limited
  per step to ``max_step`` times the current value ``|p + theta|``, and in total to the range
  ``[p / bound, p * bound]`` (a parameter never changes sign); any other effect's step is
  limited to ``max_step`` times the larger of its value and its *scale*, the change that makes
  its term as large as the whole residual; every parameter stays in its physical range
  (``Effect.lower``, ``Effect.upper``: a friction never turns negative);
* **damping**: a step is kept only if it lowers the weighted sum of squares, else the damping
  grows tenfold; non-finite residuals count as "not lower".

A failure (a residual that cannot be computed, or is not finite, at the start) is returned as
``status`` with the starting parameters; the diagnosis turns it into a verdict. When no damped
step lowers the sum of squares any more, the parameters are a (local) minimum: "converged".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..systems import System
from .effects import Effect


@dataclass(frozen=True)
class Refined:
    """Result of :func:`refine`: parameters, weighted sum of squares, iterations and status
    (``"converged"``, ``"iteration limit"`` or ``"failed: ..."``)."""

    theta: np.ndarray
    sse: float
    iterations: int
    status: str

    @property
    def ok(self) -> bool:
        return not self.status.startswith("failed")


def bounds(system: System, effects: Sequence[Effect], bound: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper limits of each effect's parameter: its physical range (``Effect.lower``,
    ``Effect.upper``), and for a prior parameter ``p`` also ``[p / bound, p * bound]``."""
    lo = np.array([e.lower for e in effects], float)
    hi = np.array([e.upper for e in effects], float)
    for k, e in enumerate(effects):
        how, target = e.channel.split(":", 1)
        if how == "param" and system.params[target] != 0:
            p = float(system.params[target])
            a, b = sorted((p / bound - p, p * bound - p))
            lo[k], hi[k] = max(lo[k], a), min(hi[k], b)
    return lo, hi


def refine(evaluate: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], theta: np.ndarray,
           lo: np.ndarray, hi: np.ndarray, current: Callable[[np.ndarray], np.ndarray], *,
           iterations: int = 20, max_step: float = 0.5, tol: float = 1e-7,
           max_damping: float = 1e4) -> Refined:
    """Levenberg-Marquardt on ``evaluate(theta) -> (R (n,), Phi (n, m))`` with step limits.

    ``R(theta + d) ~ R(theta) - Phi d`` (the residual's convention in
    :mod:`~learnest_codegen.diagnosis.fit`). ``current(theta)`` gives each parameter's size
    for the relative step limit (``|p + theta|`` for a prior parameter, ``|theta|`` otherwise).
    Stops when a step is below ``tol`` of the parameter's size, when the sum of squares no longer
    falls, or when no step is accepted with damping up to ``max_damping`` (each trial costs one
    residual evaluation).
    """
    theta = np.clip(np.asarray(theta, float).copy(), lo, hi)
    try:
        R, P = evaluate(theta)
    except Exception as exc:  # noqa: BLE001 - a CasADi or numpy failure is a verdict here
        return Refined(theta, float("inf"), 0, f"failed: residual not computable ({exc})")
    if not (np.isfinite(R).all() and np.isfinite(P).all()):
        return Refined(theta, float("inf"), 0, "failed: residual not finite at the start")
    sse, lam, status, it = float(R @ R), 1e-3, "iteration limit", 0
    for it in range(1, iterations + 1):  # noqa: B007 - the count is returned
        G, g = P.T @ P, P.T @ R
        diag = np.maximum(np.diag(G), 1e-300)
        scale = np.sqrt(max(sse, 1e-300) / diag)  # the change making a term as large as R
        limit = max_step * np.maximum(np.abs(current(theta)), scale)
        accepted = False
        while lam <= max_damping:  # each trial costs a residual evaluation: a few only
            try:
                step = np.linalg.solve(G + lam * np.diag(diag), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            over = np.abs(step) > limit  # shrink the whole step until every part is within its limit
            shrink = float(np.min(limit[over] / np.abs(step[over]))) if over.any() else 1.0
            step = np.clip(step * shrink, lo - theta, hi - theta)
            trial = theta + step
            try:
                R2, P2 = evaluate(trial)
            except Exception:  # noqa: BLE001
                R2 = P2 = None
            if R2 is not None and np.isfinite(R2).all() and np.isfinite(P2).all() and R2 @ R2 <= sse:
                accepted = True
                break
            lam *= 10
        if not accepted:  # no damped step lowers the sum of squares: a (local) minimum
            status = "converged"
            break
        small = np.all(np.abs(step) <= tol * (np.abs(theta) + scale)) or float(R2 @ R2) >= sse * (1 - 1e-12)
        theta, R, P, sse = trial, R2, P2, float(R2 @ R2)
        lam = max(lam / 10, 1e-9)
        if small:
            status = "converged"
            break
    return Refined(theta, sse, it, status)
