"""The description of a dynamical system, written once and evaluated in any backend.

A :class:`System` names its states, inputs and outputs (with units), holds the parameters of the
prior model and of the true system used for simulation, and gives the continuous dynamics and the
measurement as backend-generic functions ``fn(ops, x, u, p) -> list`` where ``x`` and ``u`` are
lists of scalar components and ``p`` a parameter mapping. See ``systems/cartpole.py`` for a
complete example and the README for writing one in your own file.

Length: over 400 lines because a :class:`System` is one definition that states, validates and
evaluates itself (names, sizes, the residual structure and its documentation, every backend);
the cross-backend check run when a system is loaded lives apart, in :mod:`.check`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable, Mapping, Sequence

import casadi as cs
import numpy as np

from ..errors import SettingsError, ShapeError
from .backends import ops_for

DynamicsFn = Callable[..., Sequence]  # fn(ops, x: list, u: list, p: Mapping) -> list of n terms


#: Signal names: they become CSV columns (``y_<name>``) and identifiers, so a letter followed
#: by letters, digits and underscores (a comma or a newline wrote CSVs that could not be read).
NAME_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
#: System names: they start the C symbol prefix ``<system>_<kind>_<estimator>``.
SYSTEM_NAME_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*")


def check_input_limits(limits, nu: int, where: str) -> tuple[tuple[float, float], ...] | None:
    """``limits`` as ``((lo, hi), ...)`` with ``nu`` pairs and ``lo < hi`` (``None`` passes).

    An infinite bound is one-sided (``(0.0, inf)``); NaN is refused.
    """
    if limits is None:
        return None
    try:
        pairs = tuple((float(lo), float(hi)) for lo, hi in limits)
    except (TypeError, ValueError) as exc:
        raise SettingsError(f"{where}: input_limits must be (lo, hi) pairs, one per input, got "
                         f"{limits!r}") from exc
    if len(pairs) != nu:
        raise ShapeError(f"{where}: input_limits needs {nu} (lo, hi) pairs, got {len(pairs)}")
    for j, (lo, hi) in enumerate(pairs):
        if math.isnan(lo) or math.isnan(hi) or not lo < hi:
            raise SettingsError(f"{where}: input_limits[{j}] must have lo < hi, got ({lo}, {hi})")
    return pairs


def check_bounds(pairs, where: str) -> tuple[tuple[float, float], ...]:
    """``((lo, hi), ...)`` as floats (``None``: that side open, ``-inf``/``inf``), each with
    ``lo < hi`` and no NaN; else :class:`SettingsError`."""
    out = []
    for pair in pairs:
        if len(tuple(pair)) != 2:
            raise SettingsError(f"{where}: each bound is a (lo, hi) pair, got {pair!r}")
        lo, hi = pair
        lo = -math.inf if lo is None else float(lo)
        hi = math.inf if hi is None else float(hi)
        if math.isnan(lo) or math.isnan(hi) or not lo < hi:
            raise SettingsError(f"{where}: need lo < hi in every (lo, hi) pair, got {pair!r}")
        out.append((lo, hi))
    return tuple(out)


@dataclass(frozen=True)
class Signal:
    """A named scalar signal with its unit, e.g. ``Signal("p", "m", "cart position")``.

    ``name`` is a letter followed by letters, digits and underscores (:data:`NAME_PATTERN`);
    ``unit`` and ``description`` are one line of text.
    """

    name: str
    unit: str
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not NAME_PATTERN.fullmatch(self.name):
            raise SettingsError(f"signal name {self.name!r} must be a letter followed by letters, digits "
                             "and underscores (it names CSV columns such as y_<name>)")
        for what in ("unit", "description"):
            text = getattr(self, what)
            if not isinstance(text, str) or not text.isprintable():
                raise SettingsError(f"signal {self.name!r}: {what} {text!r} must be one line of "
                                    "printable text")


@dataclass(frozen=True)
class NoiseModel:
    """Noise standard deviations used to simulate data and to tune the estimators.

    Attributes
    ----------
    measurement_std : per-output measurement noise std (units of each output).
    state_std : per-state noise std on full-state observations (the "full state" training data).
    process_std : per-state std of the process-noise model the estimators assume (Q = diag**2).
        It is a tuning choice, not noise that the simulator injects.
    initial_std : per-state std of the estimators' initial uncertainty (P0 = diag**2).
    """

    measurement_std: tuple[float, ...]
    state_std: tuple[float, ...]
    process_std: tuple[float, ...]
    initial_std: tuple[float, ...]


@dataclass(frozen=True)
class KinematicChain:
    """A measured output that is a state, followed by that state's time derivatives.

    ``KinematicChain("p", ("p", "pdot"))`` says output ``p`` measures state ``p`` whose derivative
    is state ``pdot``. The kinematic pre-training observer runs one constant-acceleration Kalman
    filter per chain, which needs no dynamics model at all.
    """

    output: str
    states: tuple[str, ...]


@dataclass(frozen=True)
class ResidualStructure:
    """Where the learned residual enters the dynamics and what it may depend on.

    Every field is optional; the defaults give a residual on every state derivative that is not
    a kinematic identity, depending on all states and inputs. The resolved names are
    :attr:`System.residual_state_names` and its siblings, which document each field's effect.

    Attributes
    ----------
    states : states whose derivative the residual may change.
    inputs : states and inputs the residual depends on (leave out what the physics is invariant to).
    via : inputs through which the residual acts as a generalised force (exclusive with ``states``).
    prior_features : states whose prior derivative the residual also sees.
    prior_gains : the residual also multiplies those prior derivatives by learned gains.
    reflection : states and inputs that change sign under the system's mirror symmetry.
    """

    states: tuple[str, ...] | None = None
    inputs: tuple[str, ...] | None = None
    via: tuple[str, ...] | None = None
    prior_features: tuple[str, ...] = ()
    prior_gains: bool = False
    reflection: tuple[str, ...] | None = None


@dataclass(frozen=True)
class DiagnosisHints:
    """What ``learnest diagnose`` cannot infer from the names of a system (all optional).

    Attributes
    ----------
    velocity_states : states that are velocities (default: the last state of each kinematic
        chain, then names such as ``*dot`` / ``v*``); velocity-dependent effects act on them.
    mass_params : parameters that are masses or inertias (default: names such as ``m*``, ``J*``).
    effects : ``fn(system, context) -> list[Effect]``, the system's own candidate effects added
        to the library (see :mod:`learnest_codegen.diagnosis.effects`).
    """

    velocity_states: tuple[str, ...] | None = None
    mass_params: tuple[str, ...] | None = None
    effects: Callable | None = None


@dataclass(frozen=True)
class System:
    """A dynamical system ``xdot = f(x, u, p)``, ``y = h(x, u, p)``.

    ``dynamics`` is the prior model; ``true_dynamics`` (default: ``dynamics``) evaluated with
    ``true_params`` is the system that generates simulated data. Both are written once against
    an ``ops`` backend and evaluate on numpy arrays ``(..., n)``, torch tensors ``(..., n)`` and
    CasADi columns ``(n, 1)``.

    ``residual`` says where a learned residual enters (learning's view of the system),
    ``planar_pose`` names the pose states of a planar vehicle (the ``ukf_rts`` observer) and
    ``diagnosis`` gives ``learnest diagnose`` what it cannot infer from names.
    ``input_limits`` (optional, one ``(lo, hi)`` per input, in the inputs' units) is the
    plausible range of ``u``: the estimators replace an input outside it by the last plausible
    one (``estimators/inputs.py``). ``state_bounds`` (optional, one ``(lo, hi)`` per state,
    ``None`` an open side) is a box the MHEs keep every state of their window in (the default
    of ``MHESettings.state_bounds``); a parameter estimated online declares its own
    (``systems/params.py``).
    """

    name: str
    states: tuple[Signal, ...]
    inputs: tuple[Signal, ...]
    outputs: tuple[Signal, ...]
    params: Mapping[str, float]
    true_params: Mapping[str, float]
    dynamics: DynamicsFn
    measurement: DynamicsFn
    noise: NoiseModel
    dt: float
    duration: float
    x0: tuple[float, ...]
    excitation: Callable[[np.ndarray, np.random.Generator], np.ndarray]
    true_dynamics: DynamicsFn | None = None
    kinematic_chains: tuple[KinematicChain, ...] = ()
    periodic_states: tuple[str, ...] = ()  # angles: learned models see their sin and cos
    default_observer: str = "rts"  # pre-training observer used when none is named
    planar_pose: tuple[str, str, str, str] | None = None  # states (x, y, v, psi) of a planar vehicle
    residual: ResidualStructure = field(default_factory=ResidualStructure)
    diagnosis: DiagnosisHints = field(default_factory=DiagnosisHints)
    description: str = ""
    input_limits: tuple[tuple[float, float], ...] | None = None
    state_bounds: tuple[tuple[float, float], ...] | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not SYSTEM_NAME_PATTERN.fullmatch(self.name):
            raise SettingsError(f"system name {self.name!r} must be letters and digits in words joined by "
                             "single underscores (it starts the C symbol prefix), e.g. 'my_pendulum'")
        for group in ("states", "inputs", "outputs"):
            names = [s.name for s in getattr(self, group)]
            twice = sorted({n for n in names if names.count(n) > 1})
            if twice:
                raise SettingsError(f"system {self.name!r}: {group} {twice} are named twice")
        object.__setattr__(self, "params", MappingProxyType(dict(self.params)))
        object.__setattr__(self, "true_params", MappingProxyType(dict(self.true_params)))
        noise = self.noise
        for what, values, n in (
            ("noise.measurement_std", noise.measurement_std, self.ny),
            ("noise.state_std", noise.state_std, self.nx),
            ("noise.process_std", noise.process_std, self.nx),
            ("noise.initial_std", noise.initial_std, self.nx),
            ("x0", self.x0, self.nx),
        ):
            if len(values) != n:
                raise ShapeError(f"system {self.name!r}: {what} needs {n} values, got {len(values)}")
        if self.input_limits is not None:
            object.__setattr__(self, "input_limits",
                               check_input_limits(self.input_limits, self.nu, f"system {self.name!r}"))
        if self.state_bounds is not None:
            bounds = check_bounds(self.state_bounds, f"system {self.name!r}: state_bounds")
            if len(bounds) != self.nx:
                raise ShapeError(f"system {self.name!r}: state_bounds needs {self.nx} (lo, hi) pairs, "
                                 f"got {len(bounds)}")
            object.__setattr__(self, "state_bounds", bounds)
        if not self.dt > 0 or not self.duration > self.dt:
            raise SettingsError(f"system {self.name!r}: need 0 < dt < duration, got {self.dt}, "
                                f"{self.duration}")
        unknown = [n for n in (*self.periodic_states, *(self.residual.states or ()),
                               *self.residual.prior_features) if n not in self.state_names]
        if unknown:
            raise SettingsError(f"system {self.name!r}: periodic_states/residual.states/"
                                f"residual.prior_features {unknown} are not states")
        signals = {*self.state_names, *self.input_names}
        unknown = [n for n in (self.residual.reflection or ()) if n not in signals]
        if unknown or self.residual.reflection == ():
            raise SettingsError(f"system {self.name!r}: residual.reflection {unknown or '()'} must name "
                                f"states or inputs ({sorted(signals)})")
        unknown = [n for n in (self.residual.inputs or ()) if n not in signals]
        if unknown or self.residual.inputs == ():
            raise SettingsError(f"system {self.name!r}: residual.inputs {unknown or '()'} must name "
                                f"states or inputs ({sorted(signals)})")
        unknown = [n for n in (self.residual.via or ()) if n not in self.input_names]
        if unknown or self.residual.via == ():
            raise SettingsError(f"system {self.name!r}: residual.via {unknown or '()'} must name "
                                f"inputs ({self.input_names})")
        if self.residual.prior_gains and not self.residual.prior_features:
            raise SettingsError(f"system {self.name!r}: residual.prior_gains multiplies the prior "
                                "features by learned gains; name them in residual.prior_features")
        if self.residual.via is not None and self.residual.states is not None:
            raise SettingsError(f"system {self.name!r}: give residual.states or residual.via, not both "
                                "(a residual through inputs changes whichever states those inputs drive)")
        if self.planar_pose is not None and (len(self.planar_pose) != 4 or any(
                n not in self.state_names for n in self.planar_pose)):
            raise SettingsError(f"system {self.name!r}: planar_pose {self.planar_pose} must name four "
                                f"states (x, y, v, psi) of {self.state_names}")
        for chain in self.kinematic_chains:
            unknown = [n for n in chain.states if n not in self.state_names]
            if chain.output not in self.output_names or unknown:
                raise SettingsError(f"system {self.name!r}: kinematic chain {chain} names unknown "
                                    f"signals (outputs {self.output_names}, states {self.state_names})")

    # -- sizes and names ------------------------------------------------------------------
    @property
    def nx(self) -> int:
        return len(self.states)

    @property
    def nu(self) -> int:
        return len(self.inputs)

    @property
    def ny(self) -> int:
        return len(self.outputs)

    @property
    def state_names(self) -> list[str]:
        return [s.name for s in self.states]

    @property
    def residual_state_names(self) -> list[str]:
        """States whose derivative a learned residual may change.

        ``residual.states`` when given; otherwise every state except those whose derivative is
        by definition the next state of a kinematic chain (``pdot`` is the derivative of ``p``).
        """
        if self.residual.states is not None:
            return list(self.residual.states)
        exact = {n for chain in self.kinematic_chains for n in chain.states[:-1]}
        return [n for n in self.state_names if n not in exact]

    @property
    def residual_input_names(self) -> list[str]:
        """States and inputs a learned residual may depend on (default: all of them, in order).

        A system leaves out the coordinates its physics is invariant to, e.g. a ground robot's
        position and heading (no force depends on where the robot is or which way it points).
        """
        if self.residual.inputs is not None:
            return list(self.residual.inputs)
        return [*self.state_names, *self.input_names]

    @property
    def residual_via_names(self) -> list[str]:
        """Inputs through which a learned residual acts; empty: it acts on state derivatives.

        With ``residual.via`` the hybrid model is ``f_prior(x, u + G Delta(x, u))``, ``G``
        selecting these inputs: the net learns a generalised force where the actuators act, and
        the prior's own input map carries it to every state it drives. A heavier cart is exactly
        such a force (``-Delta m_c * pdd``); so are friction and drag on a driven axis and an
        actuator's gain or offset. An effect elsewhere (friction in an unactuated joint) is out
        of reach of such a residual: leave ``residual.via`` unset for those.
        """
        return list(self.residual.via or ())

    @property
    def residual_prior_feature_names(self) -> list[str]:
        """States whose prior derivative ``f_prior(x, u)`` the learned residual also sees.

        A parameter error in the prior (a wrong mass, a wrong gain) makes the true acceleration
        close to a multiple of the prior's: given the prior's accelerations, the residual is
        nearly linear, and extrapolates to states the training run never reached. On the
        cartpole this lifts the gap closure of a net trained on the exact states from 97.4 % to
        99.8 % on an unseen run.

        With ``residual.prior_gains`` the features also enter multiplied: each residual channel
        is ``a(x, u) + sum_k g_k(x, u) * f_prior_k(x, u)``, the additive term and the gains all
        outputs of the one MLP. A mass or inertia error is then a gain that hardly varies (for
        the cart, ``-Delta m_c / (1 + Delta m_c dpdd/dF)``, a function of the pole angle only),
        instead of a product the tanh units must approximate. On the cartpole, trained through
        the observer with two refinement rounds, this lifts the UKF gap closure of seeds 0-7
        from 98.2 % to 98.6 %, and the worst seed from 95.8 % to 96.5 %.
        """
        return list(self.residual.prior_features)

    def reflection_signs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Signs ``(s_x, s_u)`` of the system's mirror symmetry, or ``None`` if it declares none.

        ``residual.reflection`` names the states and inputs that change sign when the system is seen in
        a mirror; the physics then obeys ``f(s_x x, s_u u) = s_x f(x, u)``. A cartpole on a level
        rail does: pushed the other way, it does the mirror image, whatever its masses, friction
        or drag. A slope along the rail or an actuator offset would break it; a system with such
        effects declares no reflection. Training adds the mirror image of every training pair,
        so the net sees both directions of every motion the run made (see
        :func:`learnest_codegen.learning.training.train`).
        """
        if self.residual.reflection is None:
            return None
        flip = lambda names: np.array([-1.0 if n in self.residual.reflection else 1.0 for n in names])  # noqa: E731
        return flip(self.state_names), flip(self.input_names)

    @property
    def input_names(self) -> list[str]:
        return [s.name for s in self.inputs]

    @property
    def output_names(self) -> list[str]:
        return [s.name for s in self.outputs]

    # -- evaluation in any backend ------------------------------------------------------------
    def f(self, x, u, *, variant: str = "prior", params: Mapping[str, float] | None = None):
        """Continuous dynamics ``xdot``; ``variant`` is ``"prior"`` or ``"true"``."""
        ops = ops_for(x)
        fn, p = self._variant(variant)
        xs, us = ops.unpack(x, self.nx), ops.unpack(u, self.nu)
        return ops.stack(self._values(fn(ops, xs, us, {**p, **(params or {})}), self.label(variant)))

    def h(self, x, u):
        """Measurement ``y = h(x, u)`` (noise-free)."""
        ops = ops_for(x)
        xs, us = ops.unpack(x, self.nx), ops.unpack(u, self.nu)
        return ops.stack(self._values(self.measurement(ops, xs, us, self.params), "measurement"))

    def label(self, variant: str) -> str:
        """How messages name a function: ``"dynamics"``, ``"true_dynamics"``, ``"measurement"``."""
        if variant == "h":
            return "measurement"
        if variant == "true":
            return "true_dynamics" if self.true_dynamics is not None else "dynamics (with true_params)"
        return "dynamics"

    def _values(self, values, label: str):
        """``values`` if it holds one value per state (per output for the measurement)."""
        names = self.output_names if label == "measurement" else self.state_names
        try:
            count = len(values)
        except TypeError:  # a single array or symbol: ops.stack and the shapes downstream judge it
            return values
        if count != len(names):
            kind = "outputs" if label == "measurement" else "states"
            raise ShapeError(f"system {self.name!r}: {label} returned {count} value"
                             f"{'' if count == 1 else 's'}, the system has {len(names)} {kind} {names}")
        return values

    def _variant(self, variant: str):
        if variant == "prior":
            return self.dynamics, self.params
        if variant == "true":
            return self.true_dynamics or self.dynamics, self.true_params
        raise SettingsError(f"variant must be 'prior' or 'true', got {variant!r}")

    def casadi_f(self, variant: str = "prior") -> cs.Function:
        """The continuous dynamics as a named CasADi Function ``f(x, u) -> xdot``."""
        x, u = cs.SX.sym("x", self.nx), cs.SX.sym("u", self.nu)
        return cs.Function(f"{self.name}_f_{variant}", [x, u], [self.f(x, u, variant=variant)],
                           ["x", "u"], ["xdot"])

    def casadi_h(self) -> cs.Function:
        """The measurement as a named CasADi Function ``h(x, u) -> y``."""
        x, u = cs.SX.sym("x", self.nx), cs.SX.sym("u", self.nu)
        return cs.Function(f"{self.name}_h", [x, u], [self.h(x, u)], ["x", "u"], ["y"])

    @property
    def n_samples(self) -> int:
        return int(round(self.duration / self.dt))

    def with_true_params(self, **changes: float) -> "System":
        """A copy whose true system uses changed parameters (for experiments)."""
        return dataclasses.replace(self, true_params={**self.true_params, **changes})

    def with_residual(self, **changes) -> "System":
        """A copy whose :class:`ResidualStructure` has these fields changed (validated again)."""
        return dataclasses.replace(self, residual=dataclasses.replace(self.residual, **changes))

    def fingerprint(self) -> str:
        """Hash of what the system computes: its description, true parameters, noise, residual
        structure, and ``f`` (both variants) and ``h`` at fixed random points, so an edit to the
        equations changes it even when no setting changed."""
        rng = np.random.default_rng(12345)
        x, u = rng.normal(size=(8, self.nx)), rng.normal(size=(8, self.nu))
        h = hashlib.sha256(json.dumps({**self.describe(), "true_params": dict(self.true_params),
                                       "noise": dataclasses.asdict(self.noise), "x0": list(self.x0),
                                       "duration": self.duration,
                                       "residual": [self.residual_input_names, self.residual_via_names,
                                                    self.residual_state_names,
                                                    self.residual_prior_feature_names,
                                                    *(["prior_gains"] if self.residual.prior_gains else []),
                                                    *([["reflection", *self.residual.reflection]]
                                                      if self.residual.reflection else [])]},
                                      sort_keys=True, default=str).encode())
        with np.errstate(all="ignore"):
            excitation = self.excitation(np.arange(16) * self.dt * 25, np.random.default_rng(0))
            for values in (self.f(x, u), self.f(x, u, variant="true"), self.h(x, u), excitation):
                h.update(np.round(np.asarray(values, dtype=np.float64), 9).tobytes())
        return h.hexdigest()[:16]

    def describe(self) -> dict:
        """A JSON-serialisable summary, used in manifests and model directories."""
        return {
            "name": self.name,
            "states": [dataclasses.asdict(s) for s in self.states],
            "inputs": [dataclasses.asdict(s) for s in self.inputs],
            "outputs": [dataclasses.asdict(s) for s in self.outputs],
            "params": dict(self.params),
            "dt": self.dt,
        }
