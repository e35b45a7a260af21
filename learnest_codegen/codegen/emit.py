"""One estimator folder, whatever the estimator: the steps every generator shares.

A generator (``ukf.py``, ``mhe.py``, ``mhe_gn.py``) describes its estimator as a
:class:`Design`: the CasADi functions of its model, the kit file that holds its algorithm,
the hooks that name the model for the kit, its tuned defaults and its settings. :func:`emit`
then writes the folder (docs/guide/c_kit.md):

- ``learnest_*.h``: the C kit, copied, and ``learnest_status.h``;
- ``<prefix>_model.c/.h``: CasADi's code of the model (``casadi_c.py``);
- ``<prefix>.h``: the API, with the sizes and the tuned defaults (``templates/estimator.h.in``);
- ``<prefix>.c``: the glue naming the model and the build for the kit, with the fingerprint
  (``templates/estimator.c.in``);
- ``<prefix>.mk`` and ``CMakeLists.txt``: build fragments for a firmware;
- ``lib<prefix>.so`` (``toolchain.build_shared``, reused when nothing changed) and
  ``manifest.json``: the :class:`~..runtime.manifest.GeneratedEstimator` it returns.
"""

from __future__ import annotations

import hashlib
import math
import re
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import casadi as cs
import numpy as np

from .. import toolchain
from ..errors import SettingsError
from ..estimators.gate import GateSettings, max_inflation
from ..estimators.precision import PRECISIONS, check_precision
from ..export import DiscreteModel
from ..runtime.manifest import MANIFEST, GeneratedEstimator, read_manifest, settings_hash
from . import templates
from .casadi_c import write_casadi_c

# The one prefix rule (CasADi's for names): a C identifier without leading, trailing or double
# underscores. It names every exported symbol and every file of the folder.
PREFIX = re.compile(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*")
FIELDS = ("arg", "res", "iw", "w")
ALIGN = 16


@dataclass(frozen=True)
class Design:
    """What a generator hands to :func:`emit` (see the module docstring).

    ``hooks`` maps the kit's model macros (``LEARNEST_MODEL_STAGE``, ...) to CasADi function
    names (``functions`` are written to ``<prefix>_model.c``); ``defaults`` holds ``x0, P0, Q,
    R`` (covariances); ``doc`` the header's estimator-specific text; ``declarations`` the
    templates of the header's estimator-specific functions; ``options`` the header's extra
    defaults (``<PREFIX>_DEFAULT_<name>``) and ``glue_defines`` the glue's extra macros;
    ``workspace`` counts what the handle holds (:func:`workspace_bytes`); ``link`` the
    include and library folders and libraries of the build; ``extra`` manifest entries;
    ``batch`` the functions that also get a lane-parallel copy where their code allows
    (``casadi_c.write_casadi_c``; the hook ``<hook>_BATCH`` then names it).
    """

    estimator: str
    title: str
    kit: str
    functions: tuple[cs.Function, ...]
    hooks: Mapping[str, str]
    defaults: Mapping[str, np.ndarray]
    gate: GateSettings
    precision: str
    settings: dict
    solver: dict | None
    horizon: int | None
    doc: Mapping[str, str]
    declarations: tuple[str, ...]
    workspace: Mapping[str, int]
    options: Mapping[str, str] = field(default_factory=dict)
    glue_defines: Mapping[str, str] = field(default_factory=dict)
    link: Mapping[str, Sequence] = field(default_factory=dict)
    extra: Mapping[str, object] = field(default_factory=dict)
    batch: tuple[str, ...] = ()


def default_prefix(model: DiscreteModel, estimator: str, precision: str = "float64",
                   horizon: int | None = None) -> str:
    """``<system>_<kind>_<estimator>``, then ``_n<N>`` for an MHE of horizon ``N`` and
    ``_float32`` for a float32 build: every exported symbol's prefix and the folder's name. The
    horizon and the precision are in it so that MHEs of several horizons and both precisions of
    one estimator link into one image."""
    name = f"{model.system.name}_{model.kind}_{estimator}"
    if horizon is not None:
        name += f"_n{int(horizon)}"
    if precision != "float64":
        name += f"_{precision}"
    return re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9]", "_", name)).strip("_")


def check_prefix(prefix: str, where: str) -> str:
    if not PREFIX.fullmatch(prefix or ""):
        raise SettingsError(f"{where}: prefix {prefix!r} is not a C identifier of letters and digits "
                         "in words joined by single underscores (e.g. cartpole_knode_ukf)")
    return prefix


def casadi_work(model_header: Path, functions: Sequence[cs.Function]) -> dict[str, int]:
    """The largest work sizes (arg, res, iw, w) of ``functions`` as CasADi's generated header
    declares them (``<name>_SZ_W``: the SX code keeps its temporaries on the stack, so it is
    smaller than ``Function.sz_w()``)."""
    text = model_header.read_text()
    sizes = {}
    for k in FIELDS:
        values = [re.search(rf"#define {f.name()}_SZ_{k.upper()} (\d+)", text) for f in functions]
        if not all(values):
            raise SettingsError(f"{model_header} does not define {k.upper()} sizes of every function")
        sizes[k] = max(int(v.group(1)) for v in values)
    return sizes


def workspace_bytes(counts: Mapping[str, int], precision: str) -> int:
    """An upper bound of the handle's size on any target (LP64 the largest): ``counts`` of
    reals, ints, pointers and casadi_ints, each member padded to 8 bytes, plus the alignment.
    The glue checks it at compile time (``learnest_api.h``), so a bound too small cannot build."""
    real = 4 if precision == "float32" else 8
    raw = (real * counts.get("reals", 0) + 4 * counts.get("ints", 0)
           + 8 * (counts.get("pointers", 0) + counts.get("casadi_ints", 0)))
    return int(raw + 8 * counts.get("members", 0) + 2 * ALIGN)


def comment(text: str) -> str:
    """``text`` as the lines of a C block comment (`` * ``-prefixed, 92 columns)."""
    return "\n".join(" * " + line for line in textwrap.wrap(text, 89))


def c_list(values) -> str:
    """``{v0, v1, ...}``: an initialiser with exact (round-trip) decimal literals."""
    values = np.asarray(values, dtype=float).ravel()
    if not np.all(np.isfinite(values)):
        raise SettingsError(f"a C initialiser needs finite values, got {values.tolist()}")
    return "{" + ", ".join(repr(float(v)) for v in values) + "}"


def resolve_prefix(prefix: str | None, model: DiscreteModel, estimator: str,
                   precision: str, horizon: int | None = None) -> str:
    """``prefix``, or the default one (:func:`default_prefix`; ``horizon`` for an MHE), checked
    against the prefix rule."""
    check_precision(precision, f"generate {estimator}")
    return check_prefix(prefix or default_prefix(model, estimator, precision, horizon),
                        f"generate {estimator}")


def emit(model: DiscreteModel, design: Design, out: Path, *, prefix: str, model_hash: str,
         force: bool = False) -> GeneratedEstimator:
    """Write, build and describe the folder of ``design`` in ``out`` (see the module docstring);
    ``prefix`` from :func:`resolve_prefix` (the design's CasADi functions carry it)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    kit = templates.write_kit(out)
    model_c, model_h = write_casadi_c(design.functions, out, f"{prefix}_model", design.precision,
                                      batch=design.batch)
    values = _values(model, design, prefix, model_h)
    header = templates.write(out, "estimator.h.in", f"{prefix}.h", values)
    glue = out / f"{prefix}.c"
    glue_text = lambda fingerprint: templates.render("estimator.c.in", {**values, "fingerprint": fingerprint})  # noqa: E731
    source_hash = hashlib.sha256(glue_text("").encode())
    for path in (model_c, model_h, header, *kit):
        source_hash.update(path.read_bytes())
    tuning_hash = settings_hash({"settings": design.settings, "solver": design.solver})
    fingerprint = (f"learnest {design.estimator} {design.precision} prefix={prefix} "
                   f"system={model.system.name}:{model.system.fingerprint()[:16]} "
                   f"model={model.kind}:{model_hash[:16]} settings={tuning_hash[:16]} "
                   f"source={source_hash.hexdigest()[:16]}")
    glue.write_text(glue_text(fingerprint))
    fragments = _write_fragments(out, prefix, design)
    generate_seconds = time.perf_counter() - start
    sources = (glue, model_c)
    build = toolchain.build_shared(
        sources, out / library_name(prefix, fingerprint),
        include_dirs=[out, *design.link.get("include_dirs", ())],
        lib_dirs=design.link.get("lib_dirs", ()), libs=design.link.get("libs", ()), force=force)
    _remove_other_libraries(out, prefix, build.library)
    files = (*sources, header, model_h, *kit)
    result = GeneratedEstimator(
        directory=out, estimator=design.estimator, prefix=prefix, system=model.system.name,
        model_kind=model.kind, system_fingerprint=model.system.fingerprint(),
        model_hash=model_hash, nx=model.nx, nu=model.nu, ny=model.ny, dt=float(model.dt),
        horizon=design.horizon, precision=design.precision, settings=design.settings,
        settings_hash=settings_hash(design.settings), solver=design.solver,
        fingerprint=fingerprint, source_hash=source_hash.hexdigest(),
        code_hash=toolchain.file_hash(*files, *fragments),
        sources=tuple(p.name for p in sources), headers=tuple(p.name for p in (header, model_h, *kit)),
        library=build.library.name, casadi_version=cs.__version__,
        generate_seconds=round(generate_seconds, 3), build_seconds=_build_seconds(out, build),
        build_reused=build.reused, code_bytes=sum(p.stat().st_size for p in files),
        extra=dict(design.extra))
    return result.write()


def library_name(prefix: str, fingerprint: str) -> str:
    """``lib<prefix>-<12 hex>.so``, named by the build's fingerprint: a build of other inputs is
    another file, so a process that loaded one build and rebuilt the folder loads the new one
    (``dlopen`` hands back a library already loaded from the same path)."""
    return f"lib{prefix}-{hashlib.sha256(fingerprint.encode()).hexdigest()[:12]}.so"


def _remove_other_libraries(out: Path, prefix: str, keep: Path) -> None:
    """Delete the folder's libraries of other builds (a process that mapped one keeps it)."""
    for old in (*out.glob(f"lib{prefix}-*.so"), *out.glob(f"lib{prefix}.so")):
        if old.name != keep.name:
            old.unlink()
            old.with_suffix(old.suffix + ".stamp").unlink(missing_ok=True)


def _values(model: DiscreteModel, design: Design, prefix: str, model_header: Path) -> dict:
    """The template fields of the header and the glue."""
    P = prefix.upper()
    system = model.system
    work = casadi_work(model_header, design.functions)
    names = [f.name() for f in design.functions]
    sizes = "\n".join(f"#define LEARNEST_CASADI_SZ_{k.upper()} "
                      + _max_of([f"{n}_SZ_{k.upper()}" for n in names]) for k in FIELDS)
    batched = model_header.read_text()
    model_lines = "\n".join(
        f"#define {hook} {name}" + (f"\n#define {hook}_BATCH {name}_batch\n#define {hook}_LANES "
                                    f"{name}_BATCH_LANES" if f"{name}_BATCH_LANES" in batched else "")
        for hook, name in design.hooks.items())
    glue_defines = "".join(f"#define {k} {v}\n" for k, v in design.glue_defines.items())
    identity = f"{prefix} {design.estimator} {design.precision}".encode()
    magic = int(hashlib.sha256(identity).hexdigest()[:8], 16) | 1
    gate = design.gate
    counts = dict(design.workspace)
    counts["pointers"] = counts.get("pointers", 0) + work["arg"] + work["res"] + 2
    counts["casadi_ints"] = counts.get("casadi_ints", 0) + work["iw"] + 1
    counts["reals"] = counts.get("reals", 0) + work["w"] + 1
    d = design.defaults
    horizon = ("" if design.horizon is None
               else f"#define {P}_HORIZON {design.horizon}  /* N: the window holds N+1 samples */\n")
    glue_horizon = "" if design.horizon is None else f"#define LEARNEST_N {P}_HORIZON\n"
    return {
        "p": prefix, "P": P, "title": design.title, "system": system.name, "model_kind": model.kind,
        "precision": design.precision, "real": PRECISIONS[design.precision], "kit": design.kit,
        "nx": model.nx, "nu": model.nu, "ny": model.ny, "dt": repr(float(model.dt)),
        "state_names": ", ".join(system.state_names), "input_names": ", ".join(system.input_names),
        "output_names": ", ".join(system.output_names),
        "horizon": horizon, "glue_horizon": glue_horizon,
        "workspace_bytes": workspace_bytes(counts, design.precision),
        "x0": c_list(d["x0"]), "P0": c_list(d["P0"]), "Q": c_list(d["Q"]), "R": c_list(d["R"]),
        "gate_threshold": repr(float(gate.threshold)) if gate.enabled else "0.0",
        "gate_recover_after": gate.recover_after,
        "gate_inflation": repr(float(gate.inflation)),
        "max_inflation": repr(max_inflation(design.estimator, design.precision)),
        "magic": f"0x{magic:08X}", "model": f"{model_lines}\n{sizes}",
        "options": glue_defines,
        "default_options": "".join(f"#define {P}_DEFAULT_{k} {v}\n" for k, v in design.options.items()),
        "declarations": "".join(templates.render(name, {"p": prefix, "P": P})
                                for name in design.declarations),
        **_input_limits(P, design.settings.get("input_limits")),
        **design.doc,
    }


def _input_limits(P: str, limits) -> dict[str, str]:
    """The header's ``<PREFIX>_INPUT_LO/_HI`` and the glue's ``LEARNEST_INPUT_LO/_HI`` from the
    settings' ``input_limits`` (the system file's): the C API's input check (learnest_api.h).
    Without limits only finiteness is checked."""
    if not limits:
        return {"input_limits": "/* No input limits: the step checks only that u is finite. */\n",
                "glue_input": "", "input_rule": ""}

    def bound(v: float) -> str:
        return repr(float(v)) if math.isfinite(v) else ("HUGE_VAL" if v > 0 else "-HUGE_VAL")

    lo, hi = ("{" + ", ".join(bound(pair[i]) for pair in limits) + "}" for i in (0, 1))
    return {"input_limits": (f"/* Plausible inputs (the system's input_limits), per component of u; "
                             f"HUGE_VAL is <math.h>'s. */\n#define {P}_INPUT_LO {lo}\n"
                             f"#define {P}_INPUT_HI {hi}\n"),
            "glue_input": f"#define LEARNEST_INPUT_LO {P}_INPUT_LO\n#define LEARNEST_INPUT_HI {P}_INPUT_HI\n",
            "input_rule": f" or is outside [{P}_INPUT_LO, {P}_INPUT_HI]"}


def _max_of(names: list[str]) -> str:
    expr = names[-1]
    for name in reversed(names[:-1]):
        expr = f"LEARNEST_MAX({name}, {expr})"
    return expr


def _write_fragments(out: Path, prefix: str, design: Design) -> tuple[Path, ...]:
    """``<prefix>.mk`` (a Makefile include) and ``CMakeLists.txt`` (a CMake target)."""
    link = design.link
    values = {"p": prefix, "P": prefix.upper(), "cflags": " ".join(toolchain.CFLAGS),
              "sources": f"{prefix}.c {prefix}_model.c",
              "mk_include": "".join(f" -I{d}" for d in link.get("include_dirs", ())),
              "mk_libs": "".join(f" -L{d} -Wl,-rpath,{d}" for d in link.get("lib_dirs", ()))
              + "".join(f" -l{lib}" for lib in link.get("libs", ())),
              "cmake_include": "".join(f" {d}" for d in link.get("include_dirs", ())),
              "cmake_libs": "".join(f" -L{d} -Wl,-rpath,{d}" for d in link.get("lib_dirs", ()))
              + "".join(f" {lib}" for lib in link.get("libs", ()))}
    return (templates.write(out, "estimator.mk.in", f"{prefix}.mk", values),
            templates.write(out, "CMakeLists.txt.in", "CMakeLists.txt", values))


def _build_seconds(out: Path, build: toolchain.BuildResult) -> float:
    """This build's seconds, or, for a reused library, those recorded when it was built."""
    if build.reused and (out / MANIFEST).is_file():
        try:
            return float(read_manifest(out).get("build_seconds", 0.0))
        except (ValueError, OSError):  # a manifest of an older format: the build is still reused
            return 0.0
    return round(build.seconds, 3)

