"""Generate the MHE as C: the whole Ipopt nlpsol (CasADi codegen) plus a small C API.

Stages, acados-style: :func:`build_problem` describes the NLP (shared with the Python
reference), CasADi writes ``<prefix>.c/.h`` (the solver and the model ``F`` used for the warm
start), the templates ``templates/mhe_ipopt_api.{h,c}.in`` give ``<prefix>_api.c/.h`` (window
bookkeeping on caller-provided memory, see the header), gcc links them against the casadi
wheel's ``libipopt.so`` into ``lib<prefix>.so``, and ``manifest.json`` records what was built.
An unchanged build is reused (toolchain stamp).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import casadi as cs

from .. import toolchain
from ..estimators.gate import MAX_INFLATION
from ..estimators.mhe_problem import (
    IPOPT_OPTIONS,
    MHESettings,
    ParamLayout,
    build_problem,
    measurement_function,
    mhe_settings,
)
from ..export import DiscreteModel
from ..runtime.manifest import MANIFEST, read_manifest, settings_hash, write_manifest
from ..runtime.status import STATUS_NAMES
from . import templates

API_CFLAGS = (*toolchain.DEFAULT_CFLAGS, "-Wall", "-Wextra")


@dataclass(frozen=True)
class GeneratedMHE:
    """What :func:`generate_mhe` produced.

    Attributes
    ----------
    directory, library, sources (generated solver .c, API .c), header (API .h), manifest.
    build_seconds : compile time of this call (0.0 when the build was reused).
    code_bytes : size of the C sources and headers.
    reused : True when the library was up to date and not recompiled.
    """

    directory: Path
    prefix: str
    library: Path
    sources: tuple[Path, ...]
    header: Path
    manifest: Path
    build_seconds: float
    code_bytes: int
    reused: bool


def generate_mhe(model: DiscreteModel, settings: MHESettings | None, out_dir: Path, *,
                 prefix: str | None = None, model_hash: str = "") -> GeneratedMHE:
    """Generate, compile and describe the MHE of ``model`` in ``out_dir``.

    Parameters
    ----------
    model : the discrete model the estimator uses.
    settings : horizon and default weights (weights stay settable at run time);
        default ``MHESettings.from_system(model.system)``; through
        :func:`~learnest_codegen.estimators.mhe_problem.mhe_settings`, as every MHE.
    out_dir : the folder for this estimator (created).
    prefix : C symbol prefix, default ``"<system>_<kind>_mhe"``; also names the CasADi solver.
    model_hash : hash of the model's weights, recorded in the manifest.
    """
    settings = mhe_settings(model, settings)  # the one door (estimators/mhe_problem.py)
    prefix = prefix or f"{model.system.name}_{model.kind}_mhe"
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*", prefix):
        raise ValueError(f"generate_mhe: prefix {prefix!r} is not a C identifier without "
                         "leading/trailing/double underscores (CasADi's rule for names)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    problem = build_problem(model, settings, prefix)
    solver_c = _generate_solver(problem.solver, (_renamed_F(model, prefix),
                                measurement_function(model, f"{prefix}_meas")), out, prefix)
    api_h, api_c = _write_api(out, prefix, problem.layout, settings)
    include, lib = toolchain.casadi_dirs()
    build = toolchain.build_shared([solver_c, api_c], out / f"lib{prefix}.so",
                                   include_dirs=[out, include], lib_dirs=[lib], libs=["ipopt"],
                                   cflags=API_CFLAGS)
    files = (solver_c, solver_c.with_suffix(".h"), api_c, api_h, out / templates.STATUS_HEADER,
             out / templates.GATE_HEADER)
    code_bytes = sum(f.stat().st_size for f in files)
    manifest = write_manifest(out, {
        "estimator": "mhe", "system": model.system.name, "model_kind": model.kind,
        "system_fingerprint": model.system.fingerprint(),
        "prefix": prefix, "nx": model.nx, "nu": model.nu, "ny": model.ny, "dt": model.dt,
        "horizon": settings.horizon, "settings": settings.to_json(),
        "settings_hash": settings_hash(settings.to_json()), "model_hash": model_hash,
        "code_hash": toolchain.file_hash(*files), "casadi_version": cs.__version__,
        "ipopt_options": dict(IPOPT_OPTIONS), "library": build.library.name,
        "build_seconds": _build_seconds(out, build), "code_bytes": code_bytes,
        "status_codes": {str(k): v for k, v in STATUS_NAMES.items()},
    })
    return GeneratedMHE(out, prefix, build.library, (solver_c, api_c), api_h, manifest,
                        build.seconds, code_bytes, build.reused)


def _renamed_F(model: DiscreteModel, prefix: str) -> cs.Function:
    """``F`` under a prefixed name, so its exported C symbol is unique."""
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    return cs.Function(f"{prefix}_F", [x, u], [model.F(x, u)], ["x", "u"], ["x_next"])


def _generate_solver(solver: cs.Function, helpers: tuple[cs.Function, ...], out: Path,
                     prefix: str) -> Path:
    cg = cs.CodeGenerator(f"{prefix}.c", {"with_header": True})
    cg.add(solver)
    for fn in helpers:
        cg.add(fn)
    cg.generate(f"{out}/")
    return out / f"{prefix}.c"


def _build_seconds(out: Path, build: toolchain.BuildResult) -> float:
    """This build's seconds, or, for a reused library, those recorded when it was built."""
    if build.reused and (out / MANIFEST).is_file():
        return float(read_manifest(out).get("build_seconds", 0.0))
    return round(build.seconds, 3)


def _write_api(out: Path, prefix: str, layout: ParamLayout,
               settings: MHESettings) -> tuple[Path, Path]:
    offsets = layout.offsets()
    values = {"p": prefix, "P": prefix.upper(), "nx": layout.nx, "nu": layout.nu,
              "ny": layout.ny, "horizon": layout.horizon, "np": layout.size,
              "off_xbar": offsets["xbar"], "off_u": offsets["U"], "off_y": offsets["Y"],
              "off_mask": offsets["mask"], "off_g": offsets["G"], "off_q": offsets["Q"],
              "off_r": offsets["R"], "off_pw": offsets["P"], **gate_values(settings, "float64")}
    templates.write_status_header(out)
    templates.write_gate_header(out)
    return (templates.write(out, "mhe_ipopt_api.h.in", f"{prefix}_api.h", values),
            templates.write(out, "mhe_ipopt_api.c.in", f"{prefix}_api.c", values))


def gate_values(settings: MHESettings, precision: str) -> dict[str, str]:
    """The gate defaults as template fields ``gate_threshold``, ... (C literals)."""
    gate = settings.gate
    return {"gate_threshold": repr(gate.c_threshold()), "gate_recover_after": str(gate.recover_after),
            "gate_inflation": repr(gate.inflation), "max_inflation": repr(MAX_INFLATION[precision]),
            "gate_header_sha256": templates.gate_header_digest()}
