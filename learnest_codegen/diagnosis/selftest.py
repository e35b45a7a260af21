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
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ..errors import UnknownNameError
from ..evaluation import format_table
from ..simulation import simulate
from ..systems import System, get_system
from .core import diagnose
from .effects import corrected_dynamics, library
from .selftest_systems import PENDULUM_FRICTION, PENDULUM_PRIOR, PENDULUM_TRUE, SMALL_FRICTION, SYSTEMS
from .settings import DiagnosisSettings


@dataclass(frozen=True)
class Case:
    """One withheld-effect scenario.

    Attributes
    ----------
    system : built-in system name.
    label : what is injected, for the table.
    inject : ``((effect name, parameter), ...)`` from the system's library.
    outside : optional ``fn(ops, x, u, p) -> list`` added to the true derivative (not in the library).
    expect : ``"effects"``, ``"no gap"`` or ``"unexplained"``.
    true_params : optional changes of the true parameters (e.g. the built-in drag ``C_D``).
    expect_names : when ``true_params`` or ``builtin_truth`` is used, the effects (and their
        first parameters) that should be found.
    builtin_truth : diagnose the built-in system as it is (its own true dynamics).
    source : the state observations (default: the settings' source).
    runs, duration : simulate this many runs (seeds ``seed``, ``seed + 1``, ...) of this length
        [s] (default: the system's); several runs are pooled.
    accept : for ``expect`` other than ``"effects"``, every verdict that passes (default: only
        ``expect``); e.g. ``("unexplained", "no gap")`` for an outside effect near the noise floor.
    """

    system: str
    label: str
    inject: tuple[tuple[str, float], ...] = ()
    outside: Callable | None = None
    expect: str = "effects"
    true_params: tuple[tuple[str, float], ...] = ()
    expect_names: tuple[tuple[str, float], ...] = ()
    accept: tuple[str, ...] = ()
    builtin_truth: bool = False
    source: str | None = None
    runs: int = 1
    duration: float | None = None

    @property
    def accepted(self) -> tuple[str, ...]:
        """The verdicts that pass a case without expected effects."""
        return self.accept or (self.expect,)

    @property
    def expected(self) -> tuple[tuple[str, float], ...]:
        return self.expect_names or self.inject


def _cogging(amplitude: float) -> Callable:
    """Cart cogging / a bumpy track: ``amplitude sin(2 pi p / 0.25 m)`` N on the cart, as true
    dynamics (outside the library: nothing in it depends on the cart's position).

    Strengths: with the truth as source both 0.8 N and 3 N are far above the floor. Through the
    observer (``[p, alpha]`` measured, RTS-smoothed) 0.8 N is below the observer's noise floor on
    ``pdot'`` (verdict "no gap"); 3 N is clearly above it.
    """
    def dynamics(ops, x, u, p):
        from ..systems.cartpole import dynamics as prior

        return prior(ops, x, [u[0] + amplitude * ops.sin(2 * ops.pi * x[0] / 0.25)], p)

    return dynamics


def _wind(ops, x, u, p):
    """A steady wind along a fixed direction: 0.3 m/s^2 cos(psi - 0.5) against the motion."""
    base = get_system("ground_robot").dynamics(ops, x, u, p)  # with the case's prior parameters
    return [base[0], base[1], base[2] - 0.3 * ops.cos(x[3] - 0.5), base[3]]


_K_DRAG = 0.5 * 1.225 * 0.06 * 1.05 / 1.5  # the ground robot's built-in drag, 1/m

def _pendulum_expect(friction: float) -> tuple[tuple[str, float], ...]:
    return (("mass(qdot via J)", PENDULUM_TRUE["J"] - PENDULUM_PRIOR["J"]),
            ("parameter(qdot via mgl)", PENDULUM_TRUE["mgl"] - PENDULUM_PRIOR["mgl"]),
            ("coulomb_friction(qdot via tau)", friction))


CASES: tuple[Case, ...] = (
    Case("cartpole", "exact prior", expect="no gap"),
    Case("cartpole", "cart mass +0.25 kg", (("mass(pdot via m_c)", 0.25),)),
    Case("cartpole", "cart mass +0.5 kg (built-in)", true_params=(("m_c", 1.5),),
         expect_names=(("mass(pdot via m_c)", 0.5),)),
    Case("cartpole", "cart viscous 0.5 N s/m", (("viscous_friction(pdot via F)", 0.5),)),
    Case("cartpole", "cart viscous 2 N s/m", (("viscous_friction(pdot via F)", 2.0),)),
    Case("cartpole", "cart Coulomb 0.3 N", (("coulomb_friction(pdot via F)", 0.3),)),
    Case("cartpole", "cart Coulomb 1 N", (("coulomb_friction(pdot via F)", 1.0),)),
    Case("cartpole", "cart drag 1 N s^2/m^2", (("quadratic_drag(pdot via F)", 1.0),)),
    Case("cartpole", "pole damping 0.2 1/s", (("viscous_friction(alphadot)", 0.2),)),
    Case("cartpole", "force gain -20 %", (("actuator_gain(pdot via F)", -0.2),)),
    Case("cartpole", "force gain +10 %", (("actuator_gain(pdot via F)", 0.1),)),
    Case("cartpole", "force offset 0.3 N", (("actuator_offset(pdot via F)", 0.3),)),
    Case("cartpole", "mass +0.5 kg & viscous 1 N s/m",
         (("mass(pdot via m_c)", 0.5), ("viscous_friction(pdot via F)", 1.0))),
    Case("cartpole", "gain -20 % & Coulomb 0.5 N",
         (("actuator_gain(pdot via F)", -0.2), ("coulomb_friction(pdot via F)", 0.5))),
    Case("cartpole", "cogging 3 N sin(2 pi p/0.25 m) (outside)", outside=_cogging(3.0),
         expect="unexplained"),
    Case("cartpole", "weak cogging 0.8 N sin(2 pi p/0.25 m) (outside)", outside=_cogging(0.8),
         expect="unexplained", accept=("unexplained", "no gap")),
    Case("ground_robot", "exact prior", expect="no gap"),
    Case("ground_robot", "drag C_D 1.05 (built-in)", true_params=(("C_D", 1.05),),
         expect_names=(("quadratic_drag(v)", _K_DRAG),)),
    Case("ground_robot", "drag k 0.01 1/m", (("quadratic_drag(v)", 0.01),)),
    Case("ground_robot", "rolling resistance 0.05 1/s", (("viscous_friction(v)", 0.05),)),
    Case("ground_robot", "rolling resistance 0.2 1/s", (("viscous_friction(v)", 0.2),)),
    Case("ground_robot", "Coulomb 0.1 m/s^2", (("coulomb_friction(v)", 0.1),)),
    Case("ground_robot", "Coulomb 0.3 m/s^2", (("coulomb_friction(v)", 0.3),)),
    Case("ground_robot", "throttle gain -10 %", (("actuator_gain(v via a)", -0.1),)),
    Case("ground_robot", "steering gain -10 %", (("actuator_gain(psi via delta)", -0.1),)),
    Case("ground_robot", "steering offset 0.02 rad", (("actuator_offset(psi via delta)", 0.02),)),
    Case("ground_robot", "yaw-rate bias 0.05 rad/s", (("bias(psi)", 0.05),)),
    Case("ground_robot", "drag 0.02 1/m & Coulomb 0.2 m/s^2",
         (("quadratic_drag(v)", 0.02), ("coulomb_friction(v)", 0.2))),
    Case("ground_robot", "steering gain -10 % & throttle offset 0.2 m/s^2",
         (("actuator_gain(psi via delta)", -0.1), ("actuator_offset(v via a)", 0.2))),
    Case("ground_robot", "wind 0.3 m/s^2 cos(psi - 0.5) (outside)", outside=_wind, expect="unexplained"),
    # The built-in quadrotor truth: motor lag tau 0.05 s, battery-scaled thrust k_T 11.4, rotor
    # drag k_D 0.35 1/s -> thrust_response k_T/tau = 228, plus the gravity term the drag's
    # -k_D a leaves: bias(az) = k_D g = 3.4335 m/s^3 (see effects._quadrotor_effects).
    Case("quadrotor", "motor lag + battery thrust + rotor drag (built-in)", builtin_truth=True,
         expect_names=(("thrust_response(ax,ay,az)", 11.4 / 0.05), ("bias(az)", 0.35 * 9.81))),
    # A physical pendulum as a user's system file declares it (selftest_systems.py), diagnosed from
    # its angle alone: inertia and gravity torque wrong by large factors plus real Coulomb friction.
    Case("pendulum", "J x2, mgl x1.6, Coulomb 0.2 N m (observer)", builtin_truth=True,
         expect_names=_pendulum_expect(PENDULUM_FRICTION), source="observer"),
    Case("pendulum_small_friction", "J x2, mgl x1.6, Coulomb 0.05 N m (observer)", builtin_truth=True,
         expect_names=_pendulum_expect(SMALL_FRICTION), source="observer"),
    Case("pendulum", "J x2, mgl x1.6, Coulomb 0.2 N m, 4 runs of 8 s pooled (observer)", builtin_truth=True,
         expect_names=_pendulum_expect(PENDULUM_FRICTION), source="observer", runs=4, duration=8.0),
    # A dominant effect and a small one, at several ratios: the small one is judged against the
    # gap the dominant one leaves, not against the prior's.
    *(Case("cartpole", f"mass +0.5 kg & Coulomb {c:g} N (observer)",
           (("mass(pdot via m_c)", 0.5), ("coulomb_friction(pdot via F)", c)), source="observer")
      for c in (0.3, 1.0)),
    Case("cartpole", "cart mass +0.5 kg (built-in), 4 runs of 4 s pooled (observer)",
         true_params=(("m_c", 1.5),),
         expect_names=(("mass(pdot via m_c)", 0.5),), source="observer", runs=4, duration=4.0),
)

# The default test suite runs this one: the situation of a real pendulum (two parameters of a
# user's system file wrong by large factors plus a friction, through the observer). The others run
# with the slow tests (``test_full_selftest_passes``) and ``learnest diagnose --selftest``.
QUICK = ("pendulum: J x2, mgl x1.6, Coulomb 0.2 N m (observer)",)


def case_key(case: Case) -> str:
    return f"{case.system}: {case.label}"


def prior_system(case: Case) -> System:
    """The prior a case is diagnosed against: the built-in prior, except that the ground robot's
    single-effect cases use a prior that knows the built-in drag (``C_D = 1.05``), so that the
    injected effect is the only thing missing (the built-in drag case keeps ``C_D = 0``)."""
    system = SYSTEMS[case.system]() if case.system in SYSTEMS else get_system(case.system)
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
    truth = dataclasses.replace(exact, true_dynamics=corrected_dynamics(system, effects,
                                                                        [v for _, v in case.inject]))
    if case.system == "ground_robot":
        truth = dataclasses.replace(truth, excitation=_speed_loop(system, truth, system.excitation))
    return truth


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
    runs = [simulate(truth, seed + i, duration=case.duration) for i in range(case.runs)]
    if case.source:
        settings = dataclasses.replace(settings, source=case.source)
    report = diagnose(truth, runs, settings=settings).report
    effects = report["effects"]
    matched, errors, kinds = [], [], []
    for name, value in case.expected:
        hit = next((e for e in effects if e["name"] == name), None)
        equivalent = next((e for e in effects if name in e.get("equivalent", {})), None)
        alias = next((e for e in effects if name in e["aliases"]), None)
        got = (next(iter(hit["params"].values())) if hit is not None else
               equivalent["equivalent"][name]["value"] if equivalent is not None else None)
        matched.append(got is not None or alias is not None)
        kinds.append("exact" if got is not None else "alias" if alias is not None else "missed")
        if got is not None:
            errors.append(abs(got - value) / abs(value))
    expected_names = {n for n, _ in case.expected}
    extra = [e for e in effects if e["name"] not in expected_names
             and not expected_names & (set(e["aliases"]) | set(e.get("equivalent", {})))
             and e["explained"] > extra_tolerance]
    per_estimator = report.get("estimator_verdicts", {})
    if case.expect == "effects":
        ok = (all(matched) and not extra and report["verdict"] in ("explained", "partly explained")
              and "rejected" not in per_estimator.values())
    else:  # no named effect may explain a noticeable part of the gap
        named = [e for e in effects if e["explained"] > extra_tolerance]
        ok = report["verdict"] in case.accepted and not named
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
            "param_error": max(errors) if errors else None,
            "gap_closed": one.get("closed"), "at_floor": one["after"], "unexplained": report["unexplained"],
            "pass": ok, "seconds": time.perf_counter() - start}


def run_selftest(cases: Sequence[Case] = CASES, *, settings: DiagnosisSettings | None = None,
                 progress: bool = True, seed: int = 1) -> list[dict]:
    """Run ``cases`` (default: all) and return their rows (see :func:`run_case`)."""
    from tqdm.auto import tqdm

    settings = settings or DiagnosisSettings(estimators=())
    bar = tqdm(cases, desc="diagnosis self-test", disable=not progress)
    return [run_case(c, settings, seed) for c in bar]


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
    estimator (a column per estimator that ran, ``-`` where it did not), gap closed."""
    names = sorted({n for r in rows for n in r.get("estimator_verdicts", {})})
    shown = [{**r, "param_error": None if r["param_error"] is None else 100 * r["param_error"],
              "gap_closed": None if r["gap_closed"] is None else 100 * r["gap_closed"],
              "pass": "yes" if r["pass"] else "NO",
              **{f"est:{n}": r.get("estimator_verdicts", {}).get(n) for n in names}} for r in rows]
    cols = [("case", "system: effect injected", "s"), ("truth", "truth", "s"), ("found", "effect found", "s"),
            ("verdict", "verdict", "s"), *((f"est:{n}", n.upper(), "s") for n in names),
            ("expect", "expected", "s"), ("match", "match", "s"), ("param_error", "param err %", ".2f"),
            ("gap_closed", "gap closed %", ".1f"), ("pass", "pass", "s"), ("seconds", "s", ".1f")]
    return format_table(shown, cols)
