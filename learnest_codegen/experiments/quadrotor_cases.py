"""The quadrotor study's cases: real flights or simulated runs, with the states to score against.

A :class:`Case` is a run and its reference states: on NanoBench flights Vicon position with
Savitzky-Golay velocity and acceleration
(:func:`~learnest_codegen.recordings.crazyflie.reference_states`, the paper's) and the
references of :func:`~learnest_codegen.recordings.references.references` (several windows, a
central-difference velocity), in simulation the truth. :func:`scores` is the paper's metric
(MSE over samples and the 9 states) and, per reference, the MSE of each state group.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from ..data import Run
from ..errors import DataError
from ..systems.quadrotor import QUADROTOR

GROUPS = {"p": slice(0, 3), "v": slice(3, 6), "a": slice(6, 9)}
GROUP_INDICES = {g: list(range(s.start, s.stop)) for g, s in GROUPS.items()}
GROUP_NAMES = {"p": "position", "v": "velocity", "a": "acceleration"}
TRUTH = "truth"


@dataclass(frozen=True)
class Case:
    """One run to train or test on.

    Attributes
    ----------
    name : e.g. the flight's name or ``"sim_seed3"``.
    run : the quadrotor run (``y = [p, a]``, ``u = [T, vbat]``).
    reference : (T, 9) states to score against (truth in simulation, the paper's Savitzky-Golay
        reference on flights).
    onboard : (T, 9) the onboard EKF's states, or ``None``.
    references : reference name -> (T, 9) states (NaN: no reference for that state); in
        simulation ``{"truth": reference}``.
    findings : what the recording checks found (:class:`~learnest_codegen.recordings.checks.Finding`).
    """

    name: str
    run: Run
    reference: np.ndarray
    onboard: np.ndarray | None = None
    references: dict = field(default_factory=dict)
    findings: tuple = ()

    def scored_against(self) -> dict[str, np.ndarray]:
        """The references its scores use: ``references``, or ``{"truth": reference}``."""
        return self.references or {TRUTH: self.reference}


def flight_paths(spec: str | Path) -> list[Path]:
    """The flight CSVs a ``spec`` names: a folder (its ``*.csv``, or those of its ``nanobench``
    subfolder), a glob pattern (``logs/B2_*.csv``) or one file; sorted. Metadata files
    (``*_metadata.*``) are never flights."""
    from glob import glob

    from ..recordings.crazyflie import list_flights

    text = str(spec)
    path = Path(text)
    if path.is_dir():
        found = list_flights(path)
    elif any(ch in text for ch in "*?["):
        found = sorted(Path(p) for p in glob(text) if Path(p).is_file() and p.endswith(".csv"))
    elif path.is_file():
        found = [path]
    else:
        raise FileNotFoundError(f"{text}: no such folder, file or matching flight CSV")
    found = [p for p in found if "_metadata" not in p.stem]
    if not found:
        raise FileNotFoundError(f"{text}: no flight CSV (expected *.csv in the folder or matching "
                                "the pattern)")
    return found


def flight_cases(root: str | Path | Sequence[str | Path], *, skipped: dict[str, str] | None = None,
                 findings: list | None = None, echo: bool = True, **read_options) -> list[Case]:
    """Every NanoBench flight under ``root`` (a folder, a glob, a file, or a list of them) as a
    :class:`Case` (see ``read_flight``), each recording counted once.

    A flight that cannot be used (one that never leaves the ground, too little left once its
    faulty spans are cut, another sampling rate) raises :class:`DataError`; with a ``skipped``
    dict it is left out instead and its reason recorded there under the file's name, so one
    bad recording does not stop a study. A recording with the same data as one before it
    (another name for the same flight) is left out and said. What the checks find is appended
    to ``findings`` (:class:`~learnest_codegen.recordings.checks.Finding`) and, with ``echo``,
    printed on stderr.
    """
    from ..recordings.checks import Finding, announce, duplicate_findings
    from ..recordings.crazyflie import read_flight

    specs = list(root) if isinstance(root, (list, tuple)) else [root]
    paths = list(dict.fromkeys(p for spec in specs for p in flight_paths(spec)))
    cases, keys, found = [], {}, []
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
            found.append(Finding(Path(path).stem, "unusable", None, None, str(exc), "left out"))
            continue
        keys[f.name] = f.key
        found += list(f.findings)
        cases.append(Case(f.name, f.run, f.reference, f.onboard, f.references, f.findings))
    copies = duplicate_findings(keys)
    found += copies
    left_out = {c.recording for c in copies}
    cases = [c for c in cases if c.name not in left_out]
    if findings is not None:
        findings += found
    if echo:
        announce(f for f in found if f.check != "unusable" or skipped is None)
    if not cases:
        raise DataError(f"no usable flight in {', '.join(map(str, specs))}: " + "; ".join(
            f"{k}: {v}" for k, v in (skipped or {}).items()))
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


def scores(x_hat: np.ndarray, reference: np.ndarray,
           references: dict[str, np.ndarray] | None = None) -> dict:
    """MSE overall against ``reference`` (the paper's metric: mean over samples and the 9
    states) and per state group (``mse_p``, ``mse_v``, ``mse_a``), and with ``references``,
    ``by_reference``: reference name -> group -> MSE (:func:`~learnest_codegen.evaluation.group_mse`;
    a group the reference has no values for is left out). Estimates of more states (the
    accelerometer offsets) are scored on the first 9."""
    from ..evaluation import group_mse

    x_hat = np.asarray(x_hat)[:, :reference.shape[1]]
    out: dict = {"mse": float(np.mean((x_hat - reference) ** 2))}
    out.update({f"mse_{g}": float(np.mean((x_hat[:, s] - reference[:, s]) ** 2)) for g, s in GROUPS.items()})
    if references:
        out["by_reference"] = {name: group_mse(x_hat, ref, GROUP_INDICES) for name, ref in references.items()}
    return out
