"""Self-test of the diagnosis on withheld effects: inject, diagnose blind, compare.

Each :class:`Case` simulates a built-in system whose *true* dynamics contain effects that the
prior leaves out (one at a time at several strengths, in pairs, or one outside the library, or
none at all), runs :func:`~learnest_codegen.diagnosis.diagnose` without telling it the answer,
and scores the outcome:

* **found** - every injected effect is among the selected ones, by name (``match`` "exact"), or
  as an alias that the diagnosis itself lists as indistinguishable on these data (``match``
  "alias": e.g. on the ground robot's narrow speed range, 0.85-3.5 m/s, drag plus Coulomb
  friction is within 1 % a viscous friction), and nothing else explains more than
  ``extra_tolerance`` of the gap;
* **parameter error** - relative error of each fitted parameter against the injected one;
* **gap closed** - the held-out one-step gap closed by the corrected prior;
* the exact prior must give "no gap"; an outside-library effect must give "unexplained" and
  name no effect that explains more than ``extra_tolerance`` of the gap. A *weak* outside effect
  (:attr:`Case.accept`) may also be "no gap": under the observer (``--source observer``) it can
  lie below the noise floor, and saying "no gap" then is honest, while naming a library effect
  never is. The table's "expect" column shows the accepted verdicts.

Injected library effects go through :func:`~learnest_codegen.effects.corrected_dynamics` (the
same physical forms the library offers: a cart friction is a force on the cart, entering where
the motor force does). Outside-library effects are written out below.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import numpy as np

from ..errors import UnknownNameError
from ..evaluation import format_table
from ..simulation import simulate
from ..systems import System, get_system
from .core import diagnose
from .effects import corrected_dynamics, filter_inputs, library
from .selftest_cases import CASES, Case
from .selftest_systems import SYSTEMS
from .settings import DiagnosisSettings


def case_key(case: Case) -> str:
    return f"{case.system}: {case.label}"


def prior_system(case: Case) -> System:
    """The prior a case is diagnosed against: the built-in prior, except that the ground robot's
    single-effect cases use a prior that knows the built-in drag (``C_D = 1.05``), so that the
    injected effect is the only thing missing (the built-in drag case keeps ``C_D = 0``)."""
    if case.system in SYSTEMS:
        system = SYSTEMS[case.system](**({"delay": case.input_delay} if case.input_delay else {}))
    else:
        system = get_system(case.system)
    if case.system == "ground_robot" and not case.true_params:
        return dataclasses.replace(system, params={**system.params, "C_D": 1.05})
    return system


def _speed_loop(system: System, truth: System, base: Callable) -> Callable:
    """The ground robot's excitation with its speed loop also feeding the injected effect forward.

    The built-in excitation commands ``a = v_ref' + k v_ref^2``, the feed-forward of a speed loop
    that knows the robot's drag. An injected effect on ``v'`` (a Coulomb friction of 0.3 m/s^2)
    would otherwise decelerate the robot until it reverses, which no planar observer represents
    (its speed is a norm). So the reference speed is recovered from the commands
    (``v_ref' = a - k v_ref^2``, RK4) and ``a`` is corrected by the effect at ``v_ref``: the truth
    then flies the same tour as the built-in system, as the real robot's loop would make it.
    """
    from ..systems.ground_robot import X0

    iv = system.state_names.index("v")
    k = 0.5 * system.params["rho"] * system.params["S"] * system.params["C_D"] / system.params["m"]

    def excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        u = np.array(base(t, rng), dtype=float)
        dt, v = np.diff(t, prepend=t[0]), np.empty(len(t))
        v[0] = X0[iv]
        for i in range(len(t) - 1):
            f = lambda s, a=u[i, 0]: a - k * s * abs(s)  # noqa: E731
            k1 = f(v[i])
            k2 = f(v[i] + 0.5 * dt[i + 1] * k1)
            k3 = f(v[i] + 0.5 * dt[i + 1] * k2)
            v[i + 1] = v[i] + dt[i + 1] / 6 * (k1 + 2 * k2 + 2 * k3 + f(v[i] + dt[i + 1] * k3))
        x = np.zeros((len(t), system.nx))
        x[:, iv] = v
        extra = truth.f(x, u, variant="true")[:, iv] - system.f(x, u)[:, iv]
        u[:, 0] -= extra
        return u

    return excitation


def true_system(case: Case) -> System:
    """The case's prior (:func:`prior_system`) whose true dynamics carry the withheld effects."""
    system = prior_system(case)
    if case.builtin_truth:
        return system
    exact = dataclasses.replace(system, true_params=system.params, true_dynamics=system.dynamics)
    if case.true_params:
        return dataclasses.replace(exact, true_params={**system.params, **dict(case.true_params)})
    if case.outside is not None:
        return dataclasses.replace(exact, true_dynamics=case.outside)
    if not case.inject:
        return exact
    lib = {e.name: e for e in library(system)}
    unknown = [n for n, _ in case.inject if n not in lib]
    if unknown:
        raise UnknownNameError(f"case {case.label!r}: effects {unknown} are not in the library of "
                               f"{system.name!r}")
    effects = [lib[n] for n, _ in case.inject]
    values = [v for _, v in case.inject]
    truth = dataclasses.replace(exact, true_dynamics=corrected_dynamics(system, effects, values))
    if case.system == "ground_robot":
        truth = dataclasses.replace(truth, excitation=_speed_loop(system, truth, system.excitation))
    return truth


def _filters(case: Case) -> list:
    """The library effects a case injects, in order."""
    if not case.inject:
        return []
    lib = {e.name: e for e in library(prior_system(case))}
    return [lib[n] for n, _ in case.inject]


def simulate_case(case: Case, truth: System, seed: int):
    """:func:`~learnest_codegen.simulation.simulate`, except that injected ``filter:<u>`` effects (a
    delay, a lag) act on the commands the truth is integrated with; the run records the commands."""
    filters = [(e, v) for e, (_, v) in zip(_filters(case), case.inject) if e.is_filter]
    if case.input_delay:
        return _late_run(truth, seed, case.duration, case.input_delay)
    if not filters:
        return simulate(truth, seed, duration=case.duration)
    from ..data import Run
    from ..simulation import integrate_interval

    rng = np.random.default_rng(seed)
    T = int(round((case.duration or truth.duration) / truth.dt))
    t = np.arange(T) * truth.dt
    u = truth.excitation(t, rng)
    seen = filter_inputs(truth, [e for e, _ in filters], [v for _, v in filters], u, truth.dt)
    x = np.empty((T, truth.nx))
    x[0] = truth.x0
    for k in range(T - 1):
        x[k + 1] = integrate_interval(truth, "true", x[k], seen[k], truth.dt, t[k])
    y_clean = truth.h(x, u)
    y = y_clean + rng.normal(size=y_clean.shape) * np.asarray(truth.noise.measurement_std)
    return Run(t, u, y, x, truth.name)


def _late_run(truth: System, seed: int, duration: float | None, delay: float):
    """:func:`~learnest_codegen.simulation.simulate` with every command taking effect ``delay`` [s]
    late within its sample (:func:`~.selftest_systems.late_step`); the run records the commands."""
    from ..data import Run
    from .selftest_systems import late_step

    rng = np.random.default_rng(seed)
    T = int(round((duration or truth.duration) / truth.dt))
    t = np.arange(T) * truth.dt
    u = truth.excitation(t, rng)
    x = np.empty((T, truth.nx))
    x[0] = truth.x0
    for k in range(T - 1):
        x[k + 1] = late_step(truth, x[k], u[max(k - 1, 0)], u[k], truth.dt, delay, t[k])
    y_clean = truth.h(x, u)
    y = y_clean + rng.normal(size=y_clean.shape) * np.asarray(truth.noise.measurement_std)
    return Run(t, u, y, x, truth.name)


def run_case(case: Case, settings: DiagnosisSettings, seed: int = 1, extra_tolerance: float = 0.1) -> dict:
    """Simulate, diagnose blind, score; returns a table row.

    The diagnosed system is the built-in one with the case's true dynamics: its prior (all the
    diagnosis fits against) is the plain built-in prior; the true dynamics only serve as the
    "true" reference of the shrink step, as in any simulation. An expected effect is found by
    name, or as an exact equivalent the diagnosis reports with its value (a friction on ``qdot'``
    directly, reported also as the torque through ``tau``), or as an alias (no parameter error is
    claimed for an alias: its parameter has another meaning).
    """
    start = time.perf_counter()
    truth = true_system(case)  # the built-in prior, with the case's true dynamics
    runs = [simulate_case(case, truth, seed + i) for i in range(case.runs)]
    if case.source:
        settings = dataclasses.replace(settings, source=case.source)
    diagnosed = truth
    if case.input_delay or any(e.is_filter for e in _filters(case)):  # not an f(x, u): no "true" model
        diagnosed = dataclasses.replace(truth, true_dynamics=None, true_params=truth.params)
    report = diagnose(diagnosed, runs, settings=settings).report
    effects = report["effects"]
    matched, errors, kinds, within = [], [], [], []
    for i, (name, value) in enumerate(case.expected):
        hit = next((e for e in effects if e["name"] == name), None)
        equivalent = next((e for e in effects if name in e.get("equivalent", {})), None)
        alias = next((e for e in effects if name in e["aliases"]), None)
        key = case.expect_derived[i] if i < len(case.expect_derived) else ""
        got = ({**hit["params"], **hit.get("derived", {})}.get(key) if hit is not None and key else
               next(iter(hit["params"].values())) if hit is not None else
               equivalent["equivalent"][name]["value"] if equivalent is not None else None)
        matched.append(got is not None or alias is not None)
        kinds.append("exact" if got is not None else "alias" if alias is not None else "missed")
        if got is not None:
            errors.append(abs(got - value) / abs(value))
            limit = case.absolute[i] if i < len(case.absolute) else None
            within.append(case.tolerance is None or (abs(got - value) <= limit if limit is not None
                                                     else errors[-1] <= case.tolerance))
    expected_names = {n for n, _ in case.expected}
    extra = [e for e in effects if e["name"] not in expected_names
             and not expected_names & (set(e["aliases"]) | set(e.get("equivalent", {})))
             and (case.only or e["in_sample_share"] > extra_tolerance)]
    per_estimator = report.get("estimator_verdicts", {})
    physical = all(e["physical"] for e in effects + report.get("rejected_effects", []))
    if case.expect == "effects":
        ok = (all(matched) and not extra and report["verdict"] in ("explained", "partly explained")
              and "rejected" not in per_estimator.values()
              and (case.tolerance is None or (len(within) == len(case.expected) and all(within))))
    else:  # no named effect may explain a noticeable part of the gap
        named = [e for e in effects if e["in_sample_share"] > extra_tolerance]
        ok = report["verdict"] in case.accepted and not named
    ok = ok and physical
    one = report["shrink"]["one_step"]
    return {"case": case_key(case), "injected": case.label,
            "expect": "effects" if case.expect == "effects" else " or ".join(case.accepted),
            "truth": ", ".join(f"{n} {v:.4g}" for n, v in case.expected) or "-",
            "found": ", ".join(f"{e['name']} {next(iter(e['params'].values())):.4g}"
                               + "".join(f" (= {n} {q['value']:.4g})"
                                         for n, q in e.get("equivalent", {}).items())
                               for e in effects) or "-",
            "match": ("exact" if all(k == "exact" for k in kinds) else
                      "alias" if all(k != "missed" for k in kinds) else "missed") if kinds else "-",
            "verdict": report["verdict"],
            "estimators": ", ".join(f"{n}: {v}" for n, v in per_estimator.items()) or "-",
            "estimator_verdicts": dict(per_estimator),
            "estimator_errors": {n: {k: report["shrink"][n].get(k) for k in
                                     ("before", "after", "supported", "above_supported", "supported_by")}
                                 for n in per_estimator if n in report["shrink"]},
            "found_params": [{"name": e["name"], "params": e["params"], "derived": e.get("derived", {}),
                              "equivalent": {n: q["value"] for n, q in e.get("equivalent", {}).items()}}
                             for e in effects],
            "verdict_reason": report["verdict_reason"],
            "param_error": max(errors) if errors else None,
            "gap_closed": one.get("closed"), "at_floor": one["after"],
            "explained_in_sample": report["explained_in_sample"], "physical": physical,
            "pass": ok, "seconds": time.perf_counter() - start}


def run_selftest(cases: Sequence[Case] = CASES, *, settings: DiagnosisSettings | None = None,
                 progress: bool = True, seed: int = 1) -> list[dict]:
    """Run ``cases`` (default: all) and return their rows (see :func:`run_case`). With
    ``progress``: a bar on a terminal, else one line per case on stderr."""
    import sys

    from tqdm.auto import tqdm

    settings = settings or DiagnosisSettings(estimators=())
    cases = list(cases)
    if not progress or sys.stderr.isatty():
        return [run_case(c, settings, seed) for c in tqdm(cases, desc="diagnosis self-test",
                                                           disable=None if progress else True)]
    rows = []
    for i, c in enumerate(cases):
        rows.append(run_case(c, settings, seed))
        print(f"diagnosis self-test {i + 1}/{len(cases)}: {case_key(c)}: {rows[-1]['verdict']}, "
              f"{'right' if rows[-1]['pass'] else 'WRONG'} ({rows[-1]['seconds']:.0f} s)",
              file=sys.stderr, flush=True)
    return rows


def select_cases(names: Sequence[str] | None = None, systems: Sequence[str] | None = None) -> list[Case]:
    """Cases by key (``"cartpole: exact prior"``) and/or system."""
    cases = [c for c in CASES if not systems or c.system in systems]
    if names:
        keys = {case_key(c): c for c in cases}
        unknown = [n for n in names if n not in keys]
        if unknown:
            raise UnknownNameError(f"unknown self-test cases {unknown}; choose from {sorted(keys)}")
        cases = [keys[n] for n in names]
    return cases


def table(rows: Sequence[dict]) -> str:
    """The self-test table: effect injected, effect found, parameter error, verdict overall and per
    estimator (a column per estimator that ran, ``-`` where it did not, with its corrected held-out
    MSE relative to the level the data support), gap closed."""
    names = sorted({n for r in rows for n in r.get("estimator_verdicts", {})})
    shown = [{**r, "param_error": None if r["param_error"] is None else 100 * r["param_error"],
              "gap_closed": None if r["gap_closed"] is None else 100 * r["gap_closed"],
              "pass": "yes" if r["pass"] else "NO",
              **{f"est:{n}": _against_supported(r, n) for n in names}} for r in rows]
    cols = [("case", "system: effect injected", "s"), ("truth", "truth", "s"), ("found", "effect found", "s"),
            ("verdict", "verdict", "s"), *((f"est:{n}", n.upper(), "s") for n in names),
            ("expect", "expected", "s"), ("match", "match", "s"), ("param_error", "param err %", ".2f"),
            ("gap_closed", "gap closed %", ".1f"), ("pass", "pass", "s"), ("seconds", "s", ".1f")]
    return format_table(shown, cols)


def _against_supported(row: dict, name: str) -> str | None:
    """An estimator's verdict, with its corrected held-out MSE against the level the data support."""
    verdict = row.get("estimator_verdicts", {}).get(name)
    above = row.get("estimator_errors", {}).get(name, {}).get("above_supported")
    return verdict if verdict is None or above is None else f"{verdict} ({above:+.0%})"
