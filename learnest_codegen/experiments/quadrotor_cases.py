"""The quadrotor study's cases: real flights or simulated runs, with the states to score against.

A :class:`Case` is a run and its reference states: on NanoBench flights Vicon position with
Savitzky-Golay velocity and acceleration
(:func:`~learnest_codegen.recordings.crazyflie.reference_states`), in simulation the truth.
:func:`scores` is the paper's metric (MSE over samples and the 9 states) and its parts.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from ..data import Run
from ..errors import DataError
from ..systems.quadrotor import QUADROTOR

GROUPS = {"p": slice(0, 3), "v": slice(3, 6), "a": slice(6, 9)}


@dataclass(frozen=True)
class Case:
    """One run to train or test on.

    Attributes
    ----------
    name : e.g. the flight's name or ``"sim_seed3"``.
    run : the quadrotor run (``y = [p, a]``, ``u = [T, vbat]``).
    reference : (T, 9) states to score against (truth in simulation, Savitzky-Golay on flights).
    onboard : (T, 9) the onboard EKF's states, or ``None``.
    """

    name: str
    run: Run
    reference: np.ndarray
    onboard: np.ndarray | None = None




def flight_cases(root: str | Path, *, skipped: dict[str, str] | None = None,
                 **read_options) -> list[Case]:
    """Every NanoBench flight under ``root`` as a :class:`Case` (see ``read_flight``).

    A flight that cannot be used (one that never leaves the ground, a gap, another sampling
    rate) raises :class:`DataError`; with a ``skipped`` dict it is left out instead and its
    reason recorded there under the file's name, so one bad recording does not stop a study.
    """
    from ..recordings.crazyflie import list_flights, read_flight

    paths = list_flights(root)
    if not paths:
        raise FileNotFoundError(f"no flight CSVs under {root}")
    cases = []
    for path in paths:
        try:
            f = read_flight(path, **read_options)
            if abs(f.timing.dt - QUADROTOR.dt) > 1e-3 * QUADROTOR.dt:
                raise DataError(f"flight {f.name}: sampled every {f.timing.dt} s, but the quadrotor "
                                f"estimators step {QUADROTOR.dt} s")
        except DataError as exc:
            if skipped is None:
                raise
            skipped[Path(path).stem] = str(exc)
            continue
        cases.append(Case(f.name, f.run, f.reference, f.onboard))
    if not cases:
        raise DataError(f"no usable flight under {root}: " + "; ".join(f"{k}: {v}" for k, v in
                                                                     (skipped or {}).items()))
    return cases


def simulated_cases(seeds: Iterable[int], duration: float | None = None) -> list[Case]:
    """Simulated quadrotor runs (seeded reference shape, speed and battery) with their truth."""
    from ..simulation import simulate

    cases = []
    for seed in seeds:
        run = simulate(QUADROTOR, seed, duration=duration)
        cases.append(Case(f"sim_seed{seed}", run, run.x))
    return cases


def initial_state(run: Run, fit_samples: int = 11) -> np.ndarray:
    """(9,) start state from the first measurements: position and acceleration as measured,
    velocity the slope of a line fitted to the first ``fit_samples`` positions."""
    n = min(fit_samples, len(run))
    velocity = np.polyfit(run.t[:n] - run.t[0], run.y[:n, :3], 1)[0]
    return np.concatenate([run.y[0, :3], velocity, run.y[0, 3:6]])


def scores(x_hat: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """MSE overall (the paper's metric: mean over samples and the 9 states) and per group."""
    out = {"mse": float(np.mean((x_hat - reference) ** 2))}
    out.update({f"mse_{g}": float(np.mean((x_hat[:, s] - reference[:, s]) ** 2)) for g, s in GROUPS.items()})
    return out
