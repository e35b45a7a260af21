"""Generate the embedded MHE as C: a structured Gauss-Newton SQP with no Ipopt and no malloc.

CasADi writes the RK4 model ``F`` and the measurement ``h`` with their state Jacobians (from
CasADi's AD) into ``<prefix>_model.c``; the C kit's ``learnest_mhe_gn.h`` holds the estimator
(the Gauss-Newton core ``learnest_gn.h``, the window and gate the Ipopt MHE shares, the API),
and ``codegen/emit.py`` writes and builds the folder (docs/reports/embedded_mhe.md).
"""

from __future__ import annotations

from pathlib import Path

import casadi as cs

from ..estimators.mhe_gn import GaussNewtonSettings
from ..estimators.mhe_problem import MHESettings, mhe_settings
from ..export import DiscreteModel
from ..integrators import rk4_step_jacobian
from ..runtime.manifest import GeneratedEstimator
from .emit import Design, emit, resolve_prefix
from .mhe import arrival_defines, bounds_defines, header_doc, mhe_defaults, mhe_workspace


def generate_embedded_mhe(model: DiscreteModel, settings: MHESettings | None, out_dir: Path, *,
                          solver: GaussNewtonSettings | None = None, prefix: str | None = None,
                          model_hash: str = "", force: bool = False,
                          name: str | None = None) -> GeneratedEstimator:
    """Generate, compile and describe the embedded (Gauss-Newton) MHE of ``model``.

    The arguments are :func:`~.mhe.generate_mhe`'s, and ``solver``: the mode, iteration limit,
    tolerance and precision (default converged, float64). The default prefix is
    ``"<system>_<kind>_<mhe_gn|mhe_rti>_n<N>"`` (N the horizon; ``_float32`` appended in
    float32); ``name`` replaces the estimator's name (``mhe_gn`` or ``mhe_rti`` by the mode) in
    the manifest and the prefix. The settings go through
    :func:`~learnest_codegen.estimators.mhe_problem.mhe_settings`, as every MHE's.
    """
    settings = mhe_settings(model, settings)  # the one door (estimators/mhe_problem.py)
    solver = solver or GaussNewtonSettings()
    settings.check(model.nx, model.ny, f"embedded MHE for {model.system.name} ({model.kind})")
    name = name or solver.estimator
    prefix = resolve_prefix(prefix, model, name, solver.precision, settings.horizon)
    functions = model_functions(model, f"{prefix}_model")
    nx, ny, n = model.nx, model.ny, settings.horizon
    groups = state_groups(functions[0], functions[1], nx, ny)
    counts = gn_workspace(nx, model.nu, ny, n, bounded=settings.state_bounds is not None)
    P = prefix.upper()
    design = Design(
        estimator=name,
        title=f"Embedded moving horizon estimator ({'RTI' if solver.mode == 'rti' else 'converged'} "
              "Gauss-Newton)", kit="learnest_mhe_gn.h", functions=functions,
        hooks={"LEARNEST_MODEL_STAGE": functions[0].name(), "LEARNEST_MODEL_NODE": functions[1].name(),
               "LEARNEST_MODEL_F": functions[2].name()},
        defaults=mhe_defaults(model, settings), gate=settings.gate, precision=solver.precision,
        settings=settings.to_json(), solver=solver.to_json(), horizon=n,
        doc=header_doc(settings, "Gauss-Newton"), declarations=("mhe.h.in", "mhe_gn.h.in"),
        workspace=counts,
        options={"MODE": f"{int(solver.mode == 'rti')}  /* {P}_MODE_{solver.mode.upper()} */",
                 "MAX_ITER": str(solver.max_iterations), "TOL": repr(solver.tolerance)},
        glue_defines={**{f"LEARNEST_DEFAULT_{k}": f"{P}_DEFAULT_{k}" for k in ("MODE", "MAX_ITER", "TOL")},
                      **group_defines(groups), **pattern_defines(functions[0], functions[1], nx),
                      **bounds_defines(settings, solver.precision),
                      **arrival_defines(settings)},
        extra={"model_instructions": model_instructions(model),
               "state_groups": [list(states) for states, _ in groups]},
        batch=(functions[0].name(),))  # the stages as batches where the code allows (learnest_simd.h)
    return emit(model, design, Path(out_dir), prefix=prefix, model_hash=model_hash, force=force)


def _in_mode(mode: str, estimator: str):
    """The generator of the embedded MHE in ``mode`` (``compilation.ESTIMATORS``' entry
    ``estimator``): :func:`generate_embedded_mhe` with that solver, default prefix."""

    def generate(model: DiscreteModel, settings: MHESettings | None, out_dir: Path, *,
                 model_hash: str = "", precision: str = "float64",
                 name: str = estimator) -> GeneratedEstimator:
        return generate_embedded_mhe(model, settings, out_dir, model_hash=model_hash, name=name,
                                     solver=GaussNewtonSettings(mode=mode, precision=precision))

    generate.__doc__ = f"The embedded MHE in {mode} mode (``{estimator}``) of ``model`` in ``precision``."
    return generate


generate_mhe_gn = _in_mode("converged", "mhe_gn")
generate_mhe_rti = _in_mode("rti", "mhe_rti")


def model_functions(model: DiscreteModel, name: str) -> tuple[cs.Function, ...]:
    """``<name>_stage(x, u) -> (F, A)``, ``<name>_node(x, u) -> (h, C)``, ``<name>_F``.

    ``A = dF/dx`` by the chain rule through the RK4 stages (``F`` is one RK4 step of
    ``f_continuous``: :func:`learnest_codegen.export.discretise`) and ``C = dh/dx`` by CasADi's
    AD, dense (the kit indexes them column-major).
    """
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    xdot = model.f_continuous(x, u)
    f_jac = cs.Function("f_jac", [x, u], [xdot, cs.jacobian(xdot, x)])
    F, A = rk4_step_jacobian(f_jac, x, u, model.dt, cs.SX.eye(model.nx))
    both = cs.cse(cs.vertcat(F, cs.vec(cs.densify(A))))
    n = model.nx
    return (
        cs.Function(f"{name}_stage", [x, u], [both[:n], cs.reshape(both[n:], n, n)], ["x", "u"],
                    ["F", "A"]),
        _with_jacobian(f"{name}_node", model.h(x, u), x, u, ("h", "C")),
        cs.Function(f"{name}_F", [x, u], [model.F(x, u)], ["x", "u"], ["x_next"]),
    )


def gn_workspace(nx: int, nu: int, ny: int, n: int, bounded: bool = False) -> dict[str, int]:
    """What the embedded MHE's handle holds at horizon ``n`` besides CasADi's work arrays (which
    do not depend on ``n``): :func:`~.mhe.mhe_workspace` and the Gauss-Newton's normal equations,
    factors and steps; ``bounded``: also its bounded quadratic program's (a copy of the normal
    equations, two window vectors and the working set, a byte a variable)."""
    gn = (2 * (n * nx + n * nx * nx + (n + 1) * ny * (1 + nx)) + 4 * (n + 1) * nx
          + (2 * n + 1) * nx * nx + 3 * nx * nx + ny * ny + nx + ny + 2)
    counts = mhe_workspace(nx, nu, ny, n, solution=False)
    out = {**counts, "reals": counts["reals"] + gn, "ints": counts["ints"] + 6,
           "members": counts["members"] + 17}
    if bounded:
        out["reals"] += (2 * n + 1) * nx * nx + 2 * (n + 1) * nx
        out["ints"] += -(-(n + 1) * nx // 4)
        out["members"] += 5
    return out


def _with_jacobian(name: str, value: cs.SX, x: cs.SX, u: cs.SX, names: tuple[str, str]) -> cs.Function:
    """``name(x, u) -> (value, d value / dx)``; value and Jacobian share their common
    subexpressions (``cs.cse`` over both: 16 % fewer operations for the KNODE cartpole)."""
    n = value.numel()
    both = cs.cse(cs.vertcat(value, cs.vec(cs.densify(cs.jacobian(value, x)))))
    return cs.Function(name, [x, u], [both[:n], cs.reshape(both[n:], n, x.numel())], ["x", "u"],
                       list(names))


def model_instructions(model: DiscreteModel) -> dict[str, int]:
    """Elementary operations of one evaluation of each model function (flop counts)."""
    stage, node, F = model_functions(model, "m")
    return {name: max(0, int(fn.n_instructions() - fn.nnz_in() - fn.nnz_out()))
            for name, fn in (("dyn", stage), ("meas", node), ("F", F))}


def state_groups(stage: cs.Function, node: cs.Function, nx: int, ny: int
                 ) -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    """The groups of states that no entry of the stage Jacobian ``A`` or the measurement
    Jacobian ``C`` couples (structural nonzeros, so never too few couplings), each with the
    outputs that read it: ``((states, outputs), ...)`` ordered by their first state. An output
    that reads no state goes with the first group. One group: nothing to split."""
    parent = list(range(nx))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def join(i: int, j: int) -> None:
        parent[root(i)] = root(j)

    x, u = cs.SX.sym("x", nx), cs.SX.sym("u", stage.size1_in(1))
    for r, c in _jacobian_pattern(stage, x, u):
        join(r, c)
    reads = [[c for r, c in _jacobian_pattern(node, x, u) if r == k] for k in range(ny)]
    for cols in reads:
        for c in cols[1:]:
            join(cols[0], c)
    roots = sorted({root(i) for i in range(nx)}, key=lambda r: min(i for i in range(nx) if root(i) == r))
    groups = []
    for g, r in enumerate(roots):
        states = tuple(i for i in range(nx) if root(i) == r)
        outputs = tuple(k for k in range(ny) if (reads[k] and root(reads[k][0]) == r)
                        or (not reads[k] and g == 0))
        groups.append((states, outputs))
    return tuple(groups)


def _jacobian_pattern(fn: cs.Function, x: cs.SX, u: cs.SX) -> list[tuple[int, int]]:
    """The structurally nonzero entries ``(row, column)`` of the function's second output, a
    Jacobian stored dense: evaluated symbolically, its structural zeros dropped."""
    jac = cs.SX(fn(x, u)[1])
    return [(r, c) for c in range(jac.size2()) for r in range(jac.size1()) if not jac[r, c].is_zero()]


def pattern_defines(stage: cs.Function, node: cs.Function, nx: int) -> dict[str, str]:
    """The kit's ``LEARNEST_A_PATTERN`` and ``LEARNEST_C_PATTERN`` (learnest_gn.h): the structural
    nonzeros of the Jacobians ``A`` and ``C``, column-major, 1 a nonzero, which the assembly of
    the normal equations skips. A dense Jacobian gets no table (nothing to skip)."""
    x, u = cs.SX.sym("x", nx), cs.SX.sym("u", stage.size1_in(1))
    out = {}
    for key, fn in (("LEARNEST_A_PATTERN", stage), ("LEARNEST_C_PATTERN", node)):
        rows = fn.size1_out(1)
        nz = set(_jacobian_pattern(fn, x, u))
        if len(nz) < rows * nx:
            out[key] = "{" + ", ".join("1" if (r, c) in nz else "0"
                                       for c in range(nx) for r in range(rows)) + "}"
    return out


def group_defines(groups) -> dict[str, str]:
    """The kit's ``LEARNEST_NCOMP`` and group tables (learnest_gn_groups.h) when there is more than
    one group; nothing otherwise."""
    if len(groups) < 2:
        return {}
    nx = sum(len(s) for s, _ in groups)
    ny = sum(len(o) for _, o in groups)
    of_x, of_y = [0] * nx, [0] * ny
    for g, (states, outputs) in enumerate(groups):
        for i in states:
            of_x[i] = g
        for k in outputs:
            of_y[k] = g

    def table(values) -> str:
        return "{" + ", ".join(map(str, values)) + "}"

    return {"LEARNEST_NCOMP": str(len(groups)),
            "LEARNEST_COMP_X": table(i for s, _ in groups for i in s),
            "LEARNEST_COMP_NX": table(len(s) for s, _ in groups),
            "LEARNEST_COMP_Y": table(k for _, o in groups for k in o),
            "LEARNEST_COMP_NY": table(len(o) for _, o in groups),
            "LEARNEST_COMP_OF_X": table(of_x), "LEARNEST_COMP_OF_Y": table(of_y),
            **({"LEARNEST_COMP_SIZE": str(len(groups[0][0])), "LEARNEST_COMP_YSIZE": str(len(groups[0][1]))}
               if len({(len(s), len(o)) for s, o in groups}) == 1 else {})}
