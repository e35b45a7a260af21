"""The moving-horizon estimation NLP of the paper's eq. (2), built once for every MHE.

The Python reference (:mod:`.mhe`) and the C code generator (:mod:`..codegen.mhe`) both call
:func:`build_problem`, so the problem they solve is the same object, not two copies to keep
in step.

Formulation. The decision variables are the window states ``X = [x_0 .. x_N]`` (window index
``i`` is sample ``k-N+i``). The noises of eq. (2) are eliminated, ``w_i = x_{i+1} - F(x_i, u)``
and ``v_i = y_i - h(x_i, u)``: the same minimiser as eq. (2) with ``w, v`` as variables and
equality constraints, but an unconstrained NLP with ``nx (N+1)`` variables and no constraint
Jacobian or multipliers to warm-start. Measured on the cartpole (N = 20, 1000 samples, Python
nlpsol), the explicit-``w`` variant with equality constraints also takes 2.0 Ipopt iterations
a step but 1.44 ms instead of 1.32, with 229 KB of solver C instead of 179 KB. The cost is

    s * [ sum_i a_i ||x_i - xbar||^2_P + sum_{i<N} m_i ||w_i||^2_Q + sum_i m_i ||v_i||^2_R ],
    a_i = 1 - m_{i-1} (m_{-1} = 0),   s = 1 / (largest diagonal entry of Q, R, P),

with the 0/1 mask ``m`` marking window stages that hold a real sample (``s`` only rescales,
see ``IPOPT_OPTIONS``). Once the window is full, ``m = 1`` and ``a = e_0``: eq. (2) exactly.
Before it is full (the first ``N`` samples) the leading stages are padding: their measurement
and process terms are masked out, the arrival term sits on the first real stage, and each
padded state is pinned to ``xbar`` by a term that touches no other variable (it keeps the
Hessian non-singular and does not move the real states). So the first ``N`` estimates are the
full-information estimates with prior ``x_0 ~ (xbar, P^-1)``, which for a linear-Gaussian
model are the Kalman filter's (tested).

Parameters (one vector ``p``, laid out by :class:`ParamLayout`): ``xbar``; the inputs ``U``
with ``N+1`` stages, where ``U[i]`` is the input applied since the previous sample (it drives
the transition into stage ``i`` and enters ``h`` at stage ``i``; ``U[0]`` only enters ``h``);
the outputs ``Y`` (``N+1`` stages); the mask; the weights ``Q, R, P`` as full matrices, so
they are set at run time, not baked into the code.

Size of the generated code. One SX stage function is reused over the horizon with
``Function.map`` inside an MX graph. CasADi's own exact Hessian of that graph differentiates
every mapped stage in 12 forward directions (the colouring of the whole block-tridiagonal
Hessian): 0.84 MB of C for the cartpole, 5.3 s to compile (KNODE: 1.25 MB, 10.4 s). The
Hessian is therefore supplied as ``hess_lag``: each stage's exact 8x8 Hessian from SX
``cs.hessian``, mapped and assembled into the block-tridiagonal matrix: 0.19 MB, 1.0 s
(KNODE: 0.43 MB, 2.3 s). ``tests/test_mhe.py`` checks it against CasADi's own Hessian.

Length: the settings (with their checks of the weights, the arrival and the state bounds), the
parameter layout and the NLP with its Hessian are one problem's definition, which the Python
MHE and the generators read together.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING

import casadi as cs
import numpy as np

from ..errors import SettingsError, ShapeError
from ..runtime.limits import check_option
from ..systems.base import check_bounds
from .gate import GateSettings
from .inputs import check_limits, plausible_inputs

#: Where the arrival covariance comes from (:attr:`MHESettings.arrival`).
ARRIVALS = ("steady_state", "arrival_std")

if TYPE_CHECKING:  # for annotations only
    from ..export import DiscreteModel
    from ..systems import System

# Ipopt options, in one place for the reference solver and the generated C (nlpsol embeds them).
# The problem is unconstrained, so Ipopt is a damped Newton method on the cost, which
# build_problem divides by the largest weight: Ipopt's tolerance is an absolute bound on the
# gradient, whose round-off floor is about eps * lambda_max(Hessian) * |x| (1e-8 for the
# cartpole's Q = 1e8 unnormalised; a 1e-10 tolerance then fails with
# Search_Direction_Becomes_Too_Small). Normalised, the floor is ~1e-15 whatever the run-time
# weights, and tol 1e-12 leaves estimates within 4e-9 of a 1e-14 solve on the cartpole, far
# inside the 1e-6 parity tolerance between the reference and the C solver. Warm-started, a
# step takes 1-2 iterations; max_iter only bounds a failing step.
IPOPT_OPTIONS = MappingProxyType({
    "tol": 1e-12,
    "max_iter": 100,
    "hessian_approximation": "exact",
    "print_level": 0,
    "sb": "yes",
})
#: With state bounds: Ipopt does not relax them (by default by 1e-8), and its barrier goes to 0
#: (adaptive, no floor) with a tolerance of 1e-14: with the defaults, a bound that is barely
#: active left the solution 5e-7 inside it and the estimates 5e-6 from the exact bounded
#: minimiser (the projected Gauss-Newton's, to which these settings take Ipopt within 1.4e-8 on
#: the cartpole test of tests/test_bounds.py).
BOUNDED_IPOPT_OPTIONS = MappingProxyType({"bound_relax_factor": 0.0, "honor_original_bounds": "yes",
                                          "mu_strategy": "adaptive", "mu_target": 0.0,
                                          "mu_min": 1e-20, "tol": 1e-14})
# error_on_fail: the generated C then returns Ipopt's unified status (0 ok, 1 failed, 2 maximum
# iterations) instead of 0; the Python solver raises. calc_lam_p: multipliers of p are unused.
NLPSOL_OPTIONS = MappingProxyType({"print_time": False, "error_on_fail": True, "calc_lam_p": False})


@dataclass(frozen=True, kw_only=True)
class MHESettings:
    """Horizon and weights of the MHE; ``Q, R, P = diag(1 / std**2)``.

    Attributes
    ----------
    horizon : N, the number of transitions in the window (N+1 states), 1 to 1000.
    process_std : (nx,) std of the process noise ``w`` (Q = diag(1/process_std**2)).
    measurement_std : (ny,) std of the measurement noise ``v`` (R).
    arrival_std : (nx,) std of the arrival prior ``x_{k-N} - xbar`` (P).
    arrival_covariance : optional full (nx, nx) covariance of the arrival prior; when given it
        replaces ``arrival_std`` (P = its inverse). :func:`steady_state_arrival` fills it with
        the steady-state Kalman covariance, which is what the arrival cost should summarise.
    arrival : where the arrival covariance comes from while ``arrival_covariance`` is not
        given: ``"steady_state"`` (default), the steady-state Kalman prior covariance of the
        model the estimator is built for, filled in by :func:`mhe_settings` (every MHE, Python
        or generated, goes through it, so every door gives the same arrival cost);
        ``"arrival_std"``, ``diag(arrival_std**2)``.
    gate : the innovation gate and lost-track recovery (:mod:`.gate`); a dict is accepted.
    input_limits : ``((lo, hi), ...)`` per input, the plausible range of ``u``
        (:mod:`.inputs`; ``from_system`` takes :func:`~.inputs.plausible_inputs`); ``None``:
        only finiteness is checked.
    arrival_update : ``True``: the arrival covariance follows the data, by the extended
        Kalman filter's covariance recursion along the window's leaving stage (:mod:`.arrival`)
        from the start (the running arrival covariance, or ``P0`` of ``reset``) on, instead of
        the fixed running weight; ``False`` (default): that recursion only carries a first
        prior larger than the running covariance until it has settled below it.
    state_bounds : ``((lo, hi), ...)`` per state, a box every state of the window stays in
        (``-inf``/``inf`` or ``None``: that side unbounded); ``None``: no bounds. Ipopt gets them
        as variable bounds; the embedded MHE takes projected Gauss-Newton steps with the bounds
        whose gradient points out of the box held (an active set), so both solve the same
        bounded problem.
    """

    horizon: int = 20
    process_std: tuple[float, ...]
    measurement_std: tuple[float, ...]
    arrival_std: tuple[float, ...]
    arrival_covariance: tuple[tuple[float, ...], ...] | None = None
    arrival: str = "steady_state"
    gate: GateSettings = GateSettings()
    input_limits: tuple[tuple[float, float], ...] | None = None
    arrival_update: bool = False
    state_bounds: tuple[tuple[float, float], ...] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "gate", GateSettings.coerce(self.gate))
        object.__setattr__(self, "horizon", check_option("horizon", self.horizon, "MHESettings.horizon"))
        if self.state_bounds is not None:
            object.__setattr__(self, "state_bounds",
                               check_bounds(self.state_bounds, "MHESettings.state_bounds"))
        if self.arrival not in ARRIVALS:
            raise SettingsError(f"MHESettings.arrival must be one of {ARRIVALS}, got {self.arrival!r}")
        if self.input_limits is not None:
            limits = check_limits(self.input_limits, len(tuple(self.input_limits)), "MHESettings")
            object.__setattr__(self, "input_limits", limits)
        for name in ("process_std", "measurement_std", "arrival_std"):
            values = tuple(float(v) for v in np.atleast_1d(getattr(self, name)))
            if not values or not all(math.isfinite(v) and v > 0 for v in values):
                raise SettingsError(f"MHESettings.{name} must be finite positive numbers, got {values}")
            object.__setattr__(self, name, tuple(check_option("std", v, f"MHESettings.{name}")
                                                 for v in values))
        if self.arrival_covariance is not None:
            cov = np.asarray(self.arrival_covariance, dtype=float)
            n = len(self.arrival_std)
            if cov.shape != (n, n) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T):
                raise SettingsError(f"MHESettings.arrival_covariance must be a finite symmetric "
                                    f"({n}, {n}) matrix, got shape {cov.shape}")
            if np.linalg.eigvalsh(cov).min() <= 0:
                raise SettingsError("MHESettings.arrival_covariance must be positive definite")
            object.__setattr__(self, "arrival_covariance", tuple(tuple(map(float, r)) for r in cov))

    @classmethod
    def from_system(cls, system: "System", **overrides) -> "MHESettings":
        """Settings from ``system.noise`` (arrival std = ``initial_std``), the system's
        plausible inputs (:func:`~.inputs.plausible_inputs`) and its state bounds (a parameter
        estimated online included), with ``overrides``. The
        steady-state arrival covariance needs the model: it is filled in when an estimator is
        built (:func:`mhe_settings`)."""
        noise = system.noise
        defaults = {"process_std": noise.process_std, "measurement_std": noise.measurement_std,
                    "arrival_std": noise.initial_std, "input_limits": plausible_inputs(system),
                    "state_bounds": system.state_bounds}
        return cls(**{**defaults, **overrides})

    def check(self, nx: int, ny: int, where: str, nu: int | None = None) -> None:
        """Raise :class:`ShapeError` unless the std tuples have ``nx, ny, nx`` entries (and the
        input limits ``nu`` pairs, when ``nu`` is given)."""
        for name, n in (("process_std", nx), ("measurement_std", ny), ("arrival_std", nx)):
            got = len(getattr(self, name))
            if got != n:
                raise ShapeError(f"{where}: MHESettings.{name} needs {n} values, got {got}")
        if nu is not None:
            check_limits(self.input_limits, nu, where)
        if self.state_bounds is not None and len(self.state_bounds) != nx:
            raise ShapeError(f"{where}: MHESettings.state_bounds needs {nx} (lo, hi) pairs, got "
                             f"{len(self.state_bounds)}")

    def bounds(self, nx: int) -> tuple[np.ndarray, np.ndarray]:
        """``(lo (nx,), hi (nx,))`` of :attr:`state_bounds` (``-inf``/``inf``: unbounded)."""
        if self.state_bounds is None:
            return np.full(nx, -np.inf), np.full(nx, np.inf)
        pairs = np.asarray(self.state_bounds, dtype=float)
        return pairs[:, 0].copy(), pairs[:, 1].copy()

    @property
    def resolved(self) -> bool:
        """Whether the arrival covariance is known (False: steady state, not computed yet)."""
        return self.arrival_covariance is not None or self.arrival == "arrival_std"

    def weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(Q (nx, nx), R (ny, ny), P (nx, nx))``, the inverse covariances."""
        if not self.resolved:
            raise SettingsError("MHESettings: the steady-state arrival covariance is computed from "
                             "the model; build the estimator with its model (MHE(model, "
                             "settings), or mhe_settings(model, settings)), or set "
                             "arrival='arrival_std'")
        Q, R, P = (np.diag(1.0 / np.square(getattr(self, name)))
                   for name in ("process_std", "measurement_std", "arrival_std"))
        if self.arrival_covariance is not None:
            P = np.linalg.inv(np.asarray(self.arrival_covariance))
            P = 0.5 * (P + P.T)
        return Q, R, P

    def covariances(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(Q (nx, nx), R (ny, ny), P (nx, nx))``, the covariances the weights invert (what
        the C API takes): ``diag(std**2)``, P the arrival covariance when one is set."""
        Q, R, P = (np.diag(np.square(getattr(self, name)))
                   for name in ("process_std", "measurement_std", "arrival_std"))
        if self.arrival_covariance is not None:
            P = np.asarray(self.arrival_covariance, dtype=float)
        return Q, R, P
    def initial_covariance(self) -> np.ndarray:
        """``diag(arrival_std**2)``: the uncertainty of the first prior ``x0`` (the system's
        ``initial_std``), what a caller passes as ``P0`` to start from a doubtful guess."""
        return np.diag(np.square(self.arrival_std))

    def to_json(self) -> dict:
        skip = (("gate",) + (("input_limits",) if self.input_limits is None else ())
                + (("state_bounds",) if self.state_bounds is None else ())
                + (() if self.arrival_update else ("arrival_update",)))  # older manifests' hash
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in skip}
        if self.state_bounds is not None:  # an open side as null: JSON has no infinity
            data["state_bounds"] = [[v if math.isfinite(v) else None for v in pair]
                                    for pair in self.state_bounds]
        return {**json.loads(json.dumps(data)), "gate": self.gate.to_json()}  # tuples -> lists

    @classmethod
    def from_json(cls, data: dict) -> "MHESettings":
        data = dict(data)
        if "arrival" not in data:  # written before the field: a covariance was given, or not
            data["arrival"] = "arrival_std" if data.get("arrival_covariance") is None else "steady_state"
        return cls(**data)


def mhe_settings(model: "DiscreteModel", settings: MHESettings | None = None,
                 **overrides) -> MHESettings:
    """The settings every MHE of ``model`` uses: the one door to them.

    ``settings`` (default ``MHESettings.from_system(model.system, **overrides)``; with both,
    ``overrides`` replace fields of ``settings``) checked against the model, with the
    steady-state arrival covariance of ``model`` filled in when ``arrival`` asks for it and
    none is given (:func:`steady_state_arrival`). The Python MHE, the code generators, the
    pipeline and the command line all call it, so ``MHE(model)``, ``generate_mhe(model, None)``
    and ``MHESettings.from_system(system, horizon=10)`` given to either build the same
    estimator.
    """
    if settings is None:
        settings = MHESettings.from_system(model.system, **overrides)
    elif overrides:
        settings = dataclasses.replace(settings, **overrides)
    settings.check(model.nx, model.ny, f"MHE for {model.system.name} ({model.kind})", model.nu)
    return settings if settings.resolved else steady_state_arrival(model, settings)


def steady_state_arrival(model: "DiscreteModel", settings: MHESettings,
                         x: np.ndarray | None = None, u: np.ndarray | None = None) -> MHESettings:
    """``settings`` with the arrival covariance set to the steady-state Kalman prior covariance.

    The arrival cost summarises the data that left the window. With a fixed ``arrival_std`` from
    the initial uncertainty it forgets it: on the cartpole (N=20 is 40 ms of data) the MHE with
    the *true* model then scores 8.0e-3 MSE instead of 5.6e-5. The covariance solves the
    discrete algebraic Riccati equation of ``F`` and ``h`` linearised at ``(x, u)`` (default:
    the system's ``x0`` and zero input) with ``Q = diag(process_std**2)``,
    ``R = diag(measurement_std**2)``.
    """
    from scipy.linalg import solve_discrete_are

    system = model.system
    x = np.asarray(system.x0 if x is None else x, dtype=float)
    u = np.zeros(system.nu) if u is None else np.asarray(u, dtype=float)
    xs, us = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    A = cs.Function("A", [xs, us], [cs.jacobian(model.F(xs, us), xs)])(x, u).full()
    C = cs.Function("C", [xs, us], [cs.jacobian(model.h(xs, us), xs)])(x, u).full()
    Q = np.diag(np.square(settings.process_std))
    R = np.diag(np.square(settings.measurement_std))
    try:
        P = solve_discrete_are(A.T, C.T, Q, R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise SettingsError(f"steady-state arrival cost: the Riccati equation of {system.name!r} "
                            f"linearised at x={x.tolist()} has no stabilising solution ({exc}); "
                            "set MHESettings.arrival_std instead") from exc
    return dataclasses.replace(settings, arrival_covariance=0.5 * (P + P.T))


@dataclass(frozen=True)
class ParamLayout:
    """Where each block of the parameter vector ``p`` lives; shared with the generated C.

    Blocks in order: ``xbar (nx)``, ``U (N+1, nu)``, ``Y (N+1, ny)``, ``mask (N+1)``,
    ``G (N+1, ny)`` (the innovation gate's 0/1 per output, :mod:`.gate`), ``Q (nx, nx)``,
    ``R (ny, ny)``, ``P (nx, nx)``. Window blocks are stage-contiguous (stage
    ``i`` at ``offset + i * width``) and matrices column-major, CasADi's order.
    """

    nx: int
    nu: int
    ny: int
    horizon: int

    def sizes(self) -> dict[str, int]:
        n1 = self.horizon + 1
        return {"xbar": self.nx, "U": n1 * self.nu, "Y": n1 * self.ny, "mask": n1,
                "G": n1 * self.ny, "Q": self.nx**2, "R": self.ny**2, "P": self.nx**2}

    def offsets(self) -> dict[str, int]:
        starts = np.cumsum([0, *self.sizes().values()])
        return dict(zip(self.sizes(), map(int, starts)))

    @property
    def size(self) -> int:
        return sum(self.sizes().values())

    def slice(self, name: str) -> slice:
        start = self.offsets()[name]
        return slice(start, start + self.sizes()[name])


@dataclass(frozen=True)
class MHEProblem:
    """The built NLP: ``solver(x0=X0 (nx (N+1)), p=p) -> x`` and the layout of ``p``."""

    name: str
    layout: ParamLayout
    solver: cs.Function
    hessian: cs.Function  # the hess_lag given to nlpsol (tested against CasADi's own)


def build_problem(model: "DiscreteModel", settings: MHESettings, name: str) -> MHEProblem:
    """Build the MHE NLP for ``model`` with horizon ``settings.horizon``.

    ``name`` names the nlpsol Function and so prefixes the symbols of generated C.
    """
    settings.check(model.nx, model.ny, f"MHE for {model.system.name} ({model.kind})")
    layout = ParamLayout(model.nx, model.nu, model.ny, settings.horizon)
    n = layout.horizon
    stage, stage_hess, node, node_hess = _stage_functions(model)
    X = cs.MX.sym("X", model.nx, n + 1)
    p = cs.MX.sym("p", layout.size)
    xbar, U, Y, mask, G, Q, R, P = _split(p, layout)
    mask_prev = cs.horzcat(cs.MX.zeros(1, 1), mask[:, :n])
    args = (X[:, :n], X[:, 1:], U[:, :n], U[:, 1:], Y[:, :n], G[:, :n], mask[:, :n],
            mask_prev[:, :n], xbar, Q, R, P)
    last = (X[:, n], U[:, n], Y[:, n], G[:, n], mask[:, n], mask_prev[:, n], xbar, R, P)
    scale = 1.0 / cs.mmax(cs.vertcat(cs.diag(Q), cs.diag(R), cs.diag(P)))  # see IPOPT_OPTIONS
    cost = scale * (cs.sum2(stage.map(n)(*args)) + node(*last))
    lam_f, lam_g = cs.MX.sym("lam_f"), cs.MX.sym("lam_g", 0)
    blocks = _assemble_hessian(*stage_hess.map(n)(*args), node_hess(*last), n)
    hessian = cs.Function(f"{name}_hess_l", [cs.vec(X), p, lam_f, lam_g],
                          [cs.triu((lam_f * scale) * blocks)], ["x", "p", "lam_f", "lam_g"],
                          ["triu_hess_gamma_x_x"])
    ipopt = dict(IPOPT_OPTIONS)
    if settings.state_bounds is not None:  # the solution inside the box, not 1e-8 beyond it
        ipopt.update(BOUNDED_IPOPT_OPTIONS)
    solver = cs.nlpsol(name, "ipopt", {"x": cs.vec(X), "p": p, "f": cost},
                       {**NLPSOL_OPTIONS, "ipopt": ipopt, "hess_lag": hessian})
    return MHEProblem(name, layout, solver, hessian)


def measurement_function(model: "DiscreteModel", name: str) -> cs.Function:
    """``name(x, u) -> (h (ny), C = dh/dx (ny, nx))``: what the MHEs' innovation gate needs."""
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    h = model.h(x, u)
    return cs.Function(name, [x, u], [h, cs.densify(cs.jacobian(h, x))], ["x", "u"], ["h", "C"])


def _split(p: cs.MX, layout: ParamLayout) -> list[cs.MX]:
    """The blocks of ``p`` as MX of shapes (nx,1), (nu,N+1), (ny,N+1), (1,N+1), (ny,N+1), Q, R, P."""
    n1 = layout.horizon + 1
    shapes = {"xbar": (layout.nx, 1), "U": (layout.nu, n1), "Y": (layout.ny, n1), "mask": (1, n1),
              "G": (layout.ny, n1), "Q": (layout.nx, layout.nx), "R": (layout.ny, layout.ny),
              "P": (layout.nx, layout.nx)}
    return [cs.reshape(p[layout.slice(name)], *shape) for name, shape in shapes.items()]


def _stage_functions(model: "DiscreteModel") -> tuple[cs.Function, ...]:
    """SX cost of one stage ``i < N`` and of the last node, and their exact Hessians.

    Stage: ``node_i + m_i ||x_{i+1} - F(x_i, u_{i+1})||^2_Q``; node:
    ``m_i ||g_i * (y_i - h(x_i, u_i))||^2_R + (1 - m_{i-1}) ||x_i - xbar||^2_P``, with ``g_i``
    the 0/1 gate of each output (0: rejected; for a diagonal ``R`` the output is simply dropped).
    """
    nx, nu, ny = model.nx, model.nu, model.ny
    x, x_next, xbar = cs.SX.sym("x", nx), cs.SX.sym("x_next", nx), cs.SX.sym("xbar", nx)
    u, u_next, y = cs.SX.sym("u", nu), cs.SX.sym("u_next", nu), cs.SX.sym("y", ny)
    m, m_prev, g = cs.SX.sym("m"), cs.SX.sym("m_prev"), cs.SX.sym("g", ny)
    Q, R, P = cs.SX.sym("Q", nx, nx), cs.SX.sym("R", ny, ny), cs.SX.sym("P", nx, nx)
    v, e, w = g * (y - model.h(x, u)), x - xbar, x_next - model.F(x, u_next)
    node_cost = m * cs.bilin(R, v, v) + (1 - m_prev) * cs.bilin(P, e, e)
    stage_cost = node_cost + m * cs.bilin(Q, w, w)
    node_in = [x, u, y, g, m, m_prev, xbar, R, P]
    node_names = ["x", "u", "y", "g", "m", "m_prev", "xbar", "R", "P"]
    stage_in = [x, x_next, u, u_next, y, g, m, m_prev, xbar, Q, R, P]
    stage_names = ["x", "x_next", "u", "u_next", "y", "g", "m", "m_prev", "xbar", "Q", "R", "P"]
    H, _ = cs.hessian(stage_cost, cs.vertcat(x, x_next))
    H_node, _ = cs.hessian(node_cost, x)
    return (
        cs.Function("mhe_stage", stage_in, [stage_cost], stage_names, ["cost"]),
        cs.Function("mhe_stage_hess", stage_in, [H[:nx, :nx], H[:nx, nx:], H[nx:, nx:]],
                    stage_names, ["H_xx", "H_xn", "H_nn"]),
        cs.Function("mhe_node", node_in, [node_cost], node_names, ["cost"]),
        cs.Function("mhe_node_hess", node_in, [H_node], node_names, ["H_xx"]),
    )


def _assemble_hessian(H_xx: cs.MX, H_xn: cs.MX, H_nn: cs.MX, H_last: cs.MX, n: int) -> cs.MX:
    """Block-tridiagonal Hessian of the cost from the mapped stage blocks (each nx x n nx)."""
    nx = H_last.shape[0]
    H_xx, H_xn, H_nn = (cs.horzsplit(h, nx) for h in (H_xx, H_xn, H_nn))
    blocks = [[cs.MX(nx, nx)] * (n + 1) for _ in range(n + 1)]
    for i in range(n + 1):
        own = H_xx[i] if i < n else H_last  # x_i in its own stage (or the last node)
        blocks[i][i] = own + H_nn[i - 1] if i > 0 else own  # ... and as x_next of stage i-1
        if i < n:
            blocks[i][i + 1] = H_xn[i]
            blocks[i + 1][i] = H_xn[i].T
    return cs.blockcat(blocks)
