"""The withheld-effect cases of the self-test (see :mod:`~learnest_codegen.diagnosis.selftest`).

Each :class:`Case` names a system, what its truth adds to the prior (effects of the library by
name, changed true parameters, a term outside the library, or the system's own truth) and what a
right diagnosis says. Outside-library truths are written out here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..systems import get_system
from .selftest_systems import (
    CART_FRICTION,
    PENDULUM_FRICTION,
    PENDULUM_PRIOR,
    PENDULUM_TRUE,
    RIG_FRICTION,
    RIG_TRUE,
    SMALL_FRICTION,
    SWINGUP_FRICTION,
    SWINGUP_TRUE,
    WHEEL_BEARING,
    WHEEL_GAIN,
    WHEEL_PIVOT,
    WHEEL_PRIOR,
)


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
    tolerance : the largest relative parameter error that passes (default: any, when found by name).
    expect_derived : per expected effect, the key of its ``params`` or ``derived`` entry that the
        expected value is compared with (``""``: its first parameter), e.g. a saturation's level in
        N, or a prior parameter's value rather than its change.
    only : nothing but the expected effects may be selected (default: others may explain up to
        the self-test's ``extra_tolerance`` of the in-sample gap).
    input_delay : the truth applies every command this late [s], within the sample (the system's
        builder takes it as ``delay``; the runs are integrated with
        :func:`~learnest_codegen.diagnosis.selftest_systems.late_step`).
    absolute : per expected effect, an absolute tolerance that passes it instead of ``tolerance``
        (``None``: the relative one), e.g. a delay within 1 ms.
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
    tolerance: float | None = None
    only: bool = False
    expect_derived: tuple[str, ...] = ()
    input_delay: float = 0.0
    absolute: tuple[float | None, ...] = ()

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


def _saturated(level: float) -> Callable:
    """The cart's force clipped at ``+-level`` N (a drive that saturates), as true dynamics."""
    def dynamics(ops, x, u, p):
        from ..systems.cartpole import dynamics as prior

        return prior(ops, x, [0.5 * (ops.abs(u[0] + level) - ops.abs(u[0] - level))], p)

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


# Cases that each inject one library effect: system, label, effect name, value.
_ALONE = """
cartpole | cart viscous 0.5 N s/m | viscous_friction(pdot via F) | 0.5
cartpole | cart viscous 2 N s/m | viscous_friction(pdot via F) | 2.0
cartpole | cart Coulomb 0.3 N | coulomb_friction(pdot via F) | 0.3
cartpole | cart Coulomb 1 N | coulomb_friction(pdot via F) | 1.0
cartpole | cart drag 1 N s^2/m^2 | quadratic_drag(pdot via F) | 1.0
cartpole | pole damping 0.2 1/s | viscous_friction(alphadot) | 0.2
cartpole | force gain -20 % | actuator_gain(pdot via F) | -0.2
cartpole | force gain +10 % | actuator_gain(pdot via F) | 0.1
cartpole | force offset 0.3 N | actuator_offset(pdot via F) | 0.3
ground_robot | drag k 0.01 1/m | quadratic_drag(v) | 0.01
ground_robot | rolling resistance 0.05 1/s | viscous_friction(v) | 0.05
ground_robot | rolling resistance 0.2 1/s | viscous_friction(v) | 0.2
ground_robot | Coulomb 0.1 m/s^2 | coulomb_friction(v) | 0.1
ground_robot | Coulomb 0.3 m/s^2 | coulomb_friction(v) | 0.3
ground_robot | throttle gain -10 % | actuator_gain(v via a) | -0.1
ground_robot | steering gain -10 % | actuator_gain(psi via delta) | -0.1
ground_robot | steering offset 0.02 rad | actuator_offset(psi via delta) | 0.02
ground_robot | yaw-rate bias 0.05 rad/s | bias(psi) | 0.05
"""


def _alone(system: str) -> tuple[Case, ...]:
    """The cases of ``system`` in :data:`_ALONE`."""
    rows = [line.split(" | ") for line in _ALONE.strip().splitlines()]
    return tuple(Case(s, label, ((name, float(value)),)) for s, label, name, value in rows if s == system)


CASES: tuple[Case, ...] = (
    Case("cartpole", "exact prior", expect="no gap"),
    Case("cartpole", "cart mass +0.25 kg", (("mass(pdot via m_c)", 0.25),)),
    Case("cartpole", "cart mass +0.5 kg (built-in)", true_params=(("m_c", 1.5),),
         expect_names=(("mass(pdot via m_c)", 0.5),)),
    *_alone("cartpole"),
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
    *_alone("ground_robot"),
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
    # Actuator dynamics, each alone. A delay and a lag are equal to first order, so they are
    # injected on the DART car's 10 Hz held commands, whose steps tell them apart; the car's prior
    # carries a known rolling drag so that it cruises (rc_car_damped in selftest_systems).
    Case("rc_car_damped", "throttle delay 3 samples (0.03 s)", (("input_delay(v via throttle)", 0.03),)),
    Case("rc_car_damped", "steering delay 2.5 samples (0.025 s)",
         (("input_delay(psi via steering)", 0.025),)),
    Case("rc_car_damped", "throttle lag 0.08 s", (("actuator_lag(v via throttle)", 0.08),)),
    Case("rc_car_damped", "back-EMF 0.19 s/m", (("back_emf(v via throttle)", 0.19),)),
    Case("cartpole", "force dead zone 1 N", (("dead_zone(pdot via F)", 1.0),)),
    Case("cartpole", "force saturated at 7 N", outside=_saturated(7.0),
         expect_names=(("saturation(pdot via F)", 7.0),), expect_derived=("level",)),
    Case("rc_car_damped", "steering lag 0.05 s & throttle dead zone 0.1 (observer)",
         (("actuator_lag(psi via steering)", 0.05), ("dead_zone(v via throttle)", 0.1)), source="observer"),
    # A cart with sharp Coulomb friction on its true states: the friction within 10 % and nothing
    # else (no viscous term or drag fitting the smoothing's mismatch, none with a wrong sign).
    Case("cart", "Coulomb 1 N (sharp), 3 runs pooled", builtin_truth=True,
         expect_names=(("coulomb_friction(pdot via F)", CART_FRICTION),), runs=3, tolerance=0.1, only=True),
    # The real pendulum's situation: J and mgl about 3x too small, Coulomb friction, swung up by a
    # torque-limited motor (torque correlated with sign(qdot)), a folder of three runs, the angle
    # alone measured. Each parameter within 20 %, no gain, no viscous term.
    Case("pendulum_swingup", "J x2.9, mgl x3.2, Coulomb 0.2 N m, 3 swing-ups (observer)", builtin_truth=True,
         expect_names=(("mass(qdot via J)", SWINGUP_TRUE["J"]),
                       ("parameter(qdot via mgl)", SWINGUP_TRUE["mgl"]),
                       ("coulomb_friction(qdot via tau)", SWINGUP_FRICTION)), expect_derived=("J", "mgl", ""),
         source="observer", runs=3, tolerance=0.2, only=True),
)

# The twin of a torque-limited lab pendulum (selftest_systems.pendulum_rig): a user's prior with J
# and mgl 3.6-3.7x too small in nearly the same ratio (an actuator gain aliases both), Coulomb
# friction, the torque at its limit through most of a swing-up, sampled every 6 ms, the angle
# alone measured, the torque applied 0, 2, 3 or 5 ms late; one run (the default with a single
# recording), and two and three runs pooled. Right is J and mgl and the friction within 20 %, the
# delay within 1 ms from 2 ms on, and nothing else.
def _rig(delay_ms: float, runs: int) -> Case:
    expected = (("mass(qdot via J)", RIG_TRUE["J"]), ("parameter(qdot via mgl)", RIG_TRUE["mgl"]),
                ("coulomb_friction(qdot via tau)", RIG_FRICTION))
    late = (("input_delay(qdot via tau)", delay_ms * 1e-3),) if delay_ms else ()
    return Case("pendulum_rig", f"J x3.7, mgl x3.6, Coulomb 0.195 N m, torque {delay_ms:g} ms late, "
                f"{runs} swing-up{'s' if runs > 1 else ''} (observer)", builtin_truth=True,
                expect_names=expected + late, expect_derived=("J", "mgl", "", ""), source="observer",
                runs=runs, tolerance=0.2, only=True, input_delay=delay_ms * 1e-3,
                absolute=(None, None, None, 1e-3))


CASES += tuple(_rig(d, n) for d in (0.0, 2.0, 3.0, 5.0) for n in (1, 2, 3))

# An inertia-wheel pendulum as a new user writes it (selftest_systems.inertia_wheel), through the
# observer: the motor 20 % weaker, Coulomb friction in the wheel's bearing (a torque where the
# motor's acts: 4 mN m = 0.08 V at 0.05 N m/V) and viscous damping at the pivot (0.002 N m s on
# J_p 0.02 kg m^2: 0.1 1/s on qdot'). All three within 20 %, nothing else.
CASES += (Case("inertia_wheel", "motor -20 %, bearing Coulomb 4 mN m, pivot damping (observer)",
               builtin_truth=True, source="observer", tolerance=0.2, only=True,
               expect_names=(("actuator_gain(qdot via V)", WHEEL_GAIN),
                             ("coulomb_friction(w via V)", WHEEL_BEARING / WHEEL_PRIOR["k_m"]),
                             ("viscous_friction(qdot)", WHEEL_PIVOT / WHEEL_PRIOR["J_p"]))),)

# The default test suite runs this one: the situation of a real pendulum (two parameters of a
# user's system file wrong by large factors plus a friction, through the observer). The others run
# with the slow tests (``test_full_selftest_passes``) and ``learnest diagnose --selftest``.
QUICK = ("pendulum: J x2, mgl x1.6, Coulomb 0.2 N m (observer)",)

