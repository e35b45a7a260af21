"""Generate the MHE as C: the Ipopt nlpsol of eq. (2) (CasADi codegen) in the C kit's MHE.

Stages, acados-style: :func:`build_problem` describes the NLP (shared with the Python
reference), CasADi writes the solver and the model functions the window needs (``F`` for the
warm start, ``h`` and its Jacobian for the gate) into ``<prefix>_model.c``, and the C kit's
``learnest_mhe_ipopt.h`` holds the estimator around them (window, gate, restart, API), its
problem struct being the solver's parameter vector (checked at compile time against
``ParamLayout``). gcc links them against the casadi wheel's ``libipopt.so``
(``codegen/emit.py``). The same window and gate serve the embedded MHE (:mod:`.mhe_gn`).
"""

from __future__ import annotations

import math
from pathlib import Path

import casadi as cs
import numpy as np

from .. import toolchain
from ..estimators.mhe_problem import (
    IPOPT_OPTIONS,
    MHESettings,
    build_problem,
    measurement_function,
    mhe_settings,
)
from ..export import DiscreteModel
from ..runtime.manifest import GeneratedEstimator
from .emit import Design, comment, emit, resolve_prefix


def generate_mhe(model: DiscreteModel, settings: MHESettings | None, out_dir: Path, *,
                 prefix: str | None = None, model_hash: str = "",
                 force: bool = False, name: str = "mhe") -> GeneratedEstimator:
    """Generate, compile and describe the Ipopt MHE of ``model`` in ``out_dir``.

    Parameters
    ----------
    model : the discrete model the estimator uses.
    settings : horizon and default weights (weights stay settable at run time);
        default ``MHESettings.from_system(model.system)``; through
        :func:`~learnest_codegen.estimators.mhe_problem.mhe_settings`, as every MHE.
    out_dir : the folder for this estimator (created).
    prefix : C symbol prefix, default ``"<system>_<kind>_mhe_n<N>"`` (N the horizon).
    model_hash : hash of the model's weights, recorded in the manifest and the fingerprint.
    force : rebuild the library even when nothing changed.
    name : the estimator's name (its entry in ``compilation.ESTIMATORS``): the manifest's
        ``estimator`` and the default prefix's.
    """
    settings = mhe_settings(model, settings)  # the one door (estimators/mhe_problem.py)
    prefix = resolve_prefix(prefix, model, name, "float64", settings.horizon)
    problem = build_problem(model, settings, f"{prefix}_model_nlp")
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    F = cs.Function(f"{prefix}_model_F", [x, u], [model.F(x, u)], ["x", "u"], ["x_next"])
    stage = cs.Function(f"{prefix}_model_stage", [x, u],  # the carried arrival covariance's A
                        [model.F(x, u), cs.densify(cs.jacobian(model.F(x, u), x))], ["x", "u"],
                        ["F", "A"])
    functions = (problem.solver, F, measurement_function(model, f"{prefix}_model_node"), stage)
    offsets = problem.layout.offsets()
    include, lib = toolchain.casadi_dirs()
    design = Design(
        estimator=name, title="Moving horizon estimator (Ipopt)", kit="learnest_mhe_ipopt.h",
        functions=functions,
        hooks={"LEARNEST_MODEL_SOLVER": problem.solver.name(),
               "LEARNEST_MODEL_SOLVER_CHECKOUT": f"{problem.solver.name()}_checkout",
               "LEARNEST_MODEL_SOLVER_RELEASE": f"{problem.solver.name()}_release",
               "LEARNEST_MODEL_F": F.name(), "LEARNEST_MODEL_NODE": functions[2].name(),
               "LEARNEST_MODEL_STAGE": stage.name()},
        defaults=mhe_defaults(model, settings), gate=settings.gate, precision="float64",
        settings=settings.to_json(), solver=None, horizon=settings.horizon,
        doc=header_doc(settings, "Ipopt"), declarations=("mhe.h.in",),
        workspace=mhe_workspace(model.nx, model.nu, model.ny, settings.horizon, solution=True),
        glue_defines={"LEARNEST_NP": str(problem.layout.size),
                      **{f"LEARNEST_OFF_{key.upper()}": str(off) for key, off in offsets.items()},
                      **bounds_defines(settings), **arrival_defines(settings)},
        link={"include_dirs": (include,), "lib_dirs": (lib,), "libs": ("ipopt",)},
        extra={"ipopt_options": dict(IPOPT_OPTIONS)})
    return emit(model, design, Path(out_dir), prefix=prefix, model_hash=model_hash, force=force)


def mhe_defaults(model: DiscreteModel, settings: MHESettings) -> dict[str, np.ndarray]:
    """``x0`` (the system's) and the covariances ``P0`` (arrival), ``Q``, ``R`` of ``settings``."""
    Q, R, P = settings.covariances()
    return {"x0": np.asarray(model.system.x0, dtype=float), "P0": P, "Q": Q, "R": R}


def mhe_workspace(nx: int, nu: int, ny: int, horizon: int, *, solution: bool) -> dict[str, int]:
    """What the MHEs' handles hold besides CasADi's work arrays (``codegen/emit.py``): the
    common part (with the input check's), two problems, two windows of states, the running
    arrival covariance and weight, Q and R covariances, two carried arrival covariances."""
    n1, nw = horizon + 1, (horizon + 1) * nx
    problem = nx + n1 * (nu + 2 * ny + 1) + 2 * nx * nx + ny * ny
    reals = 4 + nu + 2 * problem + 2 * nw + 5 * nx * nx + ny * ny + (nw if solution else 0)
    return {"reals": reals, "ints": 9 + ny + nu, "members": 34}


def bounds_defines(settings: MHESettings, precision: str = "float64") -> dict[str, str]:
    """The kit's ``LEARNEST_STATE_LO/_HI`` (learnest_bounds.h) of the settings' state bounds
    (``HUGE_VAL``: an open side); nothing without bounds. In float32 each bound is the nearest
    float inside the box (-0.85's nearest float is below it)."""
    if settings.state_bounds is None:
        return {}

    def inside(v: float, toward: float) -> float:
        if precision != "float32" or not math.isfinite(v):
            return v
        f = np.float32(v)
        ok = float(f) >= v if toward > 0 else float(f) <= v  # compared in double
        return float(f if ok else np.nextafter(f, np.float32(toward)))

    def side(i: int) -> str:
        values = [inside(pair[i], math.inf if i == 0 else -math.inf) for pair in settings.state_bounds]
        return "{" + ", ".join(repr(v) if math.isfinite(v) else ("HUGE_VAL" if v > 0 else "-HUGE_VAL")
                               for v in values) + "}"

    return {"LEARNEST_STATE_LO": side(0), "LEARNEST_STATE_HI": side(1)}


def arrival_defines(settings: MHESettings) -> dict[str, str]:
    """The kit's ``LEARNEST_ARRIVAL_UPDATE`` (learnest_mhe.h) when the arrival cost follows the
    data (``MHESettings.arrival_update``); nothing otherwise."""
    return {"LEARNEST_ARRIVAL_UPDATE": "1"} if settings.arrival_update else {}


def header_doc(settings: MHESettings, solver: str) -> dict[str, str]:
    """The MHEs' paragraphs of their header (``solver``: ``"Ipopt"`` or ``"Gauss-Newton"``)."""
    how = ("the Ipopt solver CasADi generated (<prefix>_model.c); Ipopt allocates and frees its "
           "problem on every step, so this estimator is the reference, not allocation-free "
           "(mhe_gn / mhe_rti are)" if solver == "Ipopt" else
           "a structured Gauss-Newton method (the C kit's learnest_gn.h: block-tridiagonal "
           "normal equations by a block Cholesky recursion, Armijo line search) on the model "
           "and Jacobians CasADi generated (<prefix>_model.c), without Ipopt and without malloc")
    return {
        "description": comment(
            f"The estimator solves, at every sample, the moving-horizon problem of eq. (2) "
            f"(learnest_codegen/estimators/mhe_problem.py) over the last N+1 = "
            f"{settings.horizon + 1} samples with {how}. The window (the C kit's "
            "learnest_window.h, mirrored by estimators/mhe_window.py) moves by one stage per "
            "sample; the arrival prior becomes the previous solution's estimate of the new "
            "first state once the window is full; the solve is warm-started from the previous "
            "solution shifted by one stage, its new last state predicted by F. Each output "
            "of each stage carries a weight G (1: in the cost; 0: missing, rejected, or folded "
            "into a restart), so a missing output leaves the rest of its stage in the cost."),
        "arrival_note": ", set_arrival",
        "reset_keeps": "" if solver == "Ipopt" else " and the solver options",
        "init_options": "" if solver == "Ipopt" else " and the solver options",
        "threads": ("\n *   The Ipopt MHE: use one library from one thread at a time (each solve "
                    "checks a\n *   memory out of CasADi's static pool)." if solver == "Ipopt" else ""),
        "covariance_rule": "each must be symmetric positive definite (the cost weighs by their "
                           "inverses), else LEARNEST_NOT_POSITIVE_DEFINITE,\n * with every "
                           "variance in the precision's range (LEARNEST_VARIANCE_MIN/_MAX), else "
                           "LEARNEST_BAD_ARGUMENT. P0 is the\n * "
                           "covariance of the first prior x0: larger than the running arrival "
                           "covariance\n * (the build's default, set_arrival), it is carried "
                           "forward with the window until it\n * is no larger (after a recovery "
                           "restart, the restart prior's covariance too).",
        "set_noise_keeps": "the window, its solution and the gate",
        "gate_doc": "before a sample enters the window, each valid output's innovation\n"
                    " *   against h(xpred, u) at the warm start's last state xpred is normalised "
                    "by\n *   S_jj = rho (C P0 C^T)_jj + R_jj (C = dh/dx at xpred, P0 the arrival "
                    "covariance in force).",
        "recovery_doc": "rho is multiplied by it; the first step that then\n"
                        " *   accepts its outputs restarts the window (emptied, its prior the "
                        "Kalman update of\n *   xpred by the sample from the variances "
                        "min(rho P0_ii, ceiling_i), the ceiling being\n *   "
                        "the cap times the running arrival covariance's), and rho shrinks "
                        "again per clean step.\n *   A step that fails makes the next step "
                        "restart the window the same way.",
        "reseed_doc": "the window restarts from the Kalman update of xpred by every\n"
                      " *   valid output with the ceiling's variances.",
    }
