"""The compile stage: a model (nominal, true or trained KNODE) to compiled estimator directories.

``compile_estimators`` generates and builds each requested estimator into a folder of ``out``
named by its C prefix (:func:`estimator_dir`: ``<system>_<kind>_<estimator>``, with the horizon
``_n<N>`` of an MHE and ``_float32`` of a float32 build; C sources, header, shared library,
``manifest.json``),
each folder whole or not at all: it is written beside its place under a temporary name and
renamed into place when complete. Generation is deterministic and the toolchain reuses a
library whose inputs did not change and which is still the file it built, so compiling the same
model twice costs only the code generation.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, Callable, Mapping

from .errors import ModelMismatchError, SettingsError, UnknownNameError
from .estimators.ekf import EKF, EKFSettings
from .estimators.mhe import MHE
from .estimators.mhe_problem import MHESettings, mhe_settings
from .estimators.precision import PRECISIONS
from .estimators.ukf import FLOAT32_MIN_ALPHA, UKF, UKFSettings
from .export import DiscreteModel, hybrid_model, prior_model, true_model
from .outputs import atomic_dir
from .runtime.ekf import CompiledEKF
from .runtime.manifest import MANIFEST, read_manifest
from .runtime.mhe import CompiledMHE
from .runtime.mhe_gn import CompiledEmbeddedMHE
from .runtime.ukf import CompiledUKF
from .systems import System


@dataclass(frozen=True)
class EstimatorKind:
    """One estimator: every face of the package (the CLI's choices and help, the pipeline, the
    compile stage, the manifest's ``estimator``, the contract tests, the docs' table) reads it
    from :data:`ESTIMATORS`, so adding an estimator is a kit header, a generator, a binding, a
    settings type and one entry there.

    Attributes
    ----------
    name : the estimator's name (``--estimator``, the manifest's ``estimator``, the C prefix).
    summary : one line for the CLI's help and the docs' table.
    settings : its settings type; ``default_settings(model)`` makes the system's.
    generator : ``"<module>:<function>"`` of ``learnest_codegen.codegen`` that writes and builds
        its folder, imported on use: loading a compiled library (the bindings, the pipeline)
        does not load the code generators (tests/test_layout.py).
    python : its Python reference (None: its C defines it).
    compiled : its ctypes binding (``runtime/``).
    kit : the C kit header that holds its algorithm.
    precisions : the C real types it is generated in.
    horizon : whether it has a moving horizon (``horizon`` applies).
    reference : ``(estimator, rtol)``: the compiled library equals that estimator's Python
        reference to ``rtol`` relative (tests/test_estimator_contract.py).
    default : compiled by ``learnest-compile`` when no ``--estimator`` is given.
    float32_defaults : what the default settings become in float32 (None: the same).
    label : its name in tables and plots (``KNODE-`` is put before it for a trained model).
    crazyflie : whether it runs in the Crazyflie app (no Ipopt, no heap); ``--target crazyflie``
        builds the first default estimator that does.
    """

    name: str
    summary: str
    settings: type
    default_settings: Callable[..., Any]
    generator: str
    python: Callable[..., Any] | None
    compiled: Callable[..., Any]
    kit: str
    precisions: tuple[str, ...] = ("float64",)
    horizon: bool = False
    reference: tuple[str, float] | None = None
    default: bool = False
    float32_defaults: Callable[[Any], Any] | None = None
    label: str = ""
    crazyflie: bool = False

    @property
    def own_python(self) -> bool:
        """Whether it has a Python reference of its own (mhe_gn's is the Ipopt MHE's, so no)."""
        return self.python is not None and self.reference is not None and self.reference[0] == self.name

    @property
    def backends(self) -> tuple[str, ...]:
        """``("python", "c")`` with a Python reference of its own, else ``("c",)``."""
        return ("python", "c") if self.own_python else ("c",)

    def generate(self, model: DiscreteModel, settings: Any, directory: Path, **options) -> Any:
        """Write, build and describe the estimator of ``model`` in ``directory`` (the manifest's
        ``estimator`` is :attr:`name`)."""
        module, function = self.generator.split(":")
        return getattr(importlib.import_module(f"learnest_codegen.codegen.{module}"), function)(
            model, settings, directory, name=self.name, **options)


def _mhe_defaults(model: DiscreteModel, **overrides):
    return mhe_settings(model, **overrides)


def _kalman_defaults(settings: type) -> Callable[..., Any]:
    def defaults(model: DiscreteModel, **overrides):
        return settings.from_system(model.system, **overrides)
    return defaults


PRECISION_NAMES = tuple(PRECISIONS)

#: The estimators, by name, in the order the CLI and the docs list them.
ESTIMATORS: dict[str, EstimatorKind] = {kind.name: kind for kind in (
    EstimatorKind("mhe", "the MHE solved by Ipopt (the reference)", MHESettings, _mhe_defaults,
                  "mhe:generate_mhe", MHE, CompiledMHE, "learnest_mhe_ipopt.h", horizon=True,
                  reference=("mhe", 1e-6), default=True, label="MHE"),
    EstimatorKind("ukf", "the unscented Kalman filter", UKFSettings, _kalman_defaults(UKFSettings),
                  "ukf:generate_ukf", UKF, CompiledUKF, "learnest_ukf.h", PRECISION_NAMES,
                  reference=("ukf", 1e-9), default=True,
                  float32_defaults=lambda settings: float32_ukf_settings(settings), label="UKF",
                  crazyflie=True),
    # the converged Gauss-Newton MHE solves the Ipopt MHE's problem to the same minimiser, so
    # that MHE is its Python reference
    EstimatorKind("mhe_gn", "the embedded MHE (Gauss-Newton, no Ipopt, no malloc) iterated to "
                  "convergence, the same estimates as mhe", MHESettings, _mhe_defaults,
                  "mhe_gn:generate_mhe_gn", MHE, CompiledEmbeddedMHE, "learnest_mhe_gn.h",
                  PRECISION_NAMES, horizon=True, reference=("mhe", 1e-6), label="MHE-GN",
                  crazyflie=True),
    # the real-time iteration takes one warm-started Gauss-Newton step per sample (9e-8 from
    # the converged MHE on the contract tests' run)
    EstimatorKind("mhe_rti", "the embedded MHE with one Gauss-Newton iteration per sample "
                  "(real-time iteration, fastest)", MHESettings, _mhe_defaults,
                  "mhe_gn:generate_mhe_rti", None, CompiledEmbeddedMHE, "learnest_mhe_gn.h",
                  PRECISION_NAMES, horizon=True, reference=("mhe", 1e-5), label="MHE-RTI",
                  crazyflie=True),
    EstimatorKind("ekf", "the extended Kalman filter (the model's Jacobians by CasADi's AD)",
                  EKFSettings, _kalman_defaults(EKFSettings), "ekf:generate_ekf", EKF, CompiledEKF,
                  "learnest_ekf.h", PRECISION_NAMES, reference=("ekf", 1e-9), label="EKF"),
)}


class _Names(Sequence):
    """The names of :data:`ESTIMATORS` an entry filter keeps, read at each use (an entry added
    later is in it)."""

    def __init__(self, keep: Callable[[EstimatorKind], bool] = lambda kind: True):
        self._keep = keep

    def __getitem__(self, i):
        return tuple(n for n, kind in ESTIMATORS.items() if self._keep(kind))[i]

    def __len__(self) -> int:
        return sum(1 for kind in ESTIMATORS.values() if self._keep(kind))

    def __repr__(self) -> str:
        return repr(tuple(self))


ESTIMATOR_NAMES: Sequence[str] = _Names()
#: The estimators with a moving horizon (``horizon`` applies to them).
MHE_NAMES: Sequence[str] = _Names(lambda kind: kind.horizon)
#: What ``learnest-compile`` builds when no ``--estimator`` is given.
DEFAULT_ESTIMATORS: Sequence[str] = _Names(lambda kind: kind.default)
#: The estimators generated in float32: those a microcontroller runs (not the Ipopt MHE).
FLOAT32_NAMES: Sequence[str] = _Names(lambda kind: "float32" in kind.precisions)
#: The estimators the Crazyflie app runs (``--target crazyflie``).
CRAZYFLIE_NAMES: Sequence[str] = _Names(lambda kind: kind.crazyflie)


def crazyflie_default() -> str:
    """What ``--target crazyflie`` builds when no ``--estimator`` is given: the first default
    estimator the app runs."""
    return next(name for name in DEFAULT_ESTIMATORS if name in CRAZYFLIE_NAMES)


def check_crazyflie(name: str) -> None:
    """Raise :class:`SettingsError` unless the Crazyflie app runs estimator ``name``."""
    if name not in CRAZYFLIE_NAMES:
        able = list(CRAZYFLIE_NAMES)
        raise SettingsError(f"the crazyflie target runs {able} (no Ipopt, no heap), not {name!r}; "
                            f"give --estimator {', '.join(able[:-1])} or {able[-1]}")


def estimator_kind(name: str) -> EstimatorKind:
    """Look up an estimator by name (one of :data:`ESTIMATOR_NAMES`)."""
    if name not in ESTIMATORS:
        raise UnknownNameError(f"unknown estimator {name!r}; choose from {list(ESTIMATOR_NAMES)}")
    return ESTIMATORS[name]


def estimator_help() -> str:
    """``name: summary; ...`` of every estimator (the CLI's help)."""
    return "; ".join(f"{kind.name}: {kind.summary}" for kind in ESTIMATORS.values())


def estimator_table() -> str:
    """The estimators as a Markdown table (docs/guide/python_api.md shows it)."""
    rows = ["| Estimator | What it is | Settings | Python reference | Binding | C kit | Precisions | "
            "Crazyflie app |",
            "|---|---|---|---|---|---|---|---|"]
    for kind in ESTIMATORS.values():
        python = f"`{kind.python.__name__}`" if kind.python else "none (its C defines it)"
        rows.append(f"| `{kind.name}` | {kind.summary} | `{kind.settings.__name__}` | {python} | "
                    f"`{kind.compiled.__name__}` | `{kind.kit}` | {', '.join(kind.precisions)} | "
                    f"{'yes' if kind.crazyflie else 'no'} |")
    return "\n".join(rows)


#: Whether a KNODE model's net inputs are clamped to their training range when
#: ``clamp_inputs`` is not given (see :func:`knode_model`).
CLAMP_INPUTS = False


def resolve_model(system: System, model: str, clamp_inputs: bool | None = None) -> tuple[DiscreteModel, str]:
    """``"nominal"``, ``"true"`` or a trained-model directory to ``(DiscreteModel, model_hash)``.

    ``clamp_inputs`` applies to a trained model only (see :func:`knode_model`).
    """
    if model in ("nominal", "true"):
        if clamp_inputs:
            raise SettingsError(f"clamp_inputs keeps a trained net's inputs in range; model {model!r} "
                                "has no net")
        return (prior_model(system), "nominal") if model == "nominal" else (true_model(system), "true")
    from .learning.training import load_model  # torch is needed only for trained models

    return knode_model(load_model(model, system), clamp_inputs)


def knode_model(trained, clamp_inputs: bool | None = None) -> tuple[DiscreteModel, str]:
    """A trained model's ``(DiscreteModel, model_hash)``, its net's inputs clamped to their
    training range when ``clamp_inputs`` (default :data:`CLAMP_INPUTS`).

    The clamp is part of the model's CasADi graph, so every estimator and precision gets it; a
    clamped model has its own hash. A model that records no training range (its
    ``model.json`` has no ``training_ranges``) cannot be clamped: :class:`ModelMismatchError`
    when asked explicitly; by default it is not clamped.
    """
    from .learning.ranges import training_box

    clamp = CLAMP_INPUTS if clamp_inputs is None else bool(clamp_inputs)
    box = training_box(trained) if clamp else None
    if clamp and box is None:
        if clamp_inputs is None:
            return hybrid_model(trained.system, trained.net), trained.hash
        raise ModelMismatchError(f"model of system {trained.system.name!r} records no training range "
                                 "(model.json has no training_ranges); retrain it to clamp its inputs")
    if box is None:
        return hybrid_model(trained.system, trained.net), trained.hash
    tag = hashlib.sha256((trained.hash + json.dumps(box.to_json(), sort_keys=True)).encode()).hexdigest()
    return hybrid_model(trained.system, trained.net, box.arrays), tag


def float32_ukf_settings(settings):
    """The float32 UKF's default: ``settings`` with alpha raised to ``FLOAT32_MIN_ALPHA`` (0.5).

    A small alpha makes the sigma-point weights cancel, which single precision cannot afford
    (see ``codegen/ukf.py``); explicit settings with a smaller alpha are refused there.
    """
    return replace(settings, alpha=max(settings.alpha, FLOAT32_MIN_ALPHA))


def precision_problem(estimators: tuple[str, ...], precision: str) -> str | None:
    """Why ``estimators`` cannot be generated in ``precision``, or None when they can."""
    if precision not in PRECISION_NAMES:
        return f"unknown precision {precision!r}; choose from {list(PRECISION_NAMES)}"
    unsupported = [name for name in estimators if precision not in estimator_kind(name).precisions]
    if unsupported:
        able = [n for n in ESTIMATOR_NAMES if precision in estimator_kind(n).precisions]
        return f"estimator(s) {unsupported} cannot be generated in {precision}; it is available for {able}"
    return None


def default_horizon() -> int:
    """The MHE horizon N when none is given (``MHESettings``' default)."""
    return MHESettings.__dataclass_fields__["horizon"].default


def estimator_dir(out: Path, model: DiscreteModel, name: str, precision: str = "float64",
                  horizon: int | None = None) -> Path:
    """Where an estimator of ``model`` is compiled to inside ``out``: the folder named by the
    estimator's C prefix (:func:`~learnest_codegen.codegen.emit.default_prefix`), e.g.
    ``cartpole_knode_ukf``, ``cartpole_knode_mhe_rti_n20``, ``cartpole_knode_mhe_rti_n20_float32``.
    ``horizon`` applies to the MHEs (default :func:`default_horizon`)."""
    from .codegen.emit import default_prefix

    if name in MHE_NAMES:
        horizon = default_horizon() if horizon is None else horizon
    else:
        horizon = None
    return Path(out) / default_prefix(model, name, precision, horizon)


def check_horizon(estimators: tuple[str, ...], horizon: int | None) -> None:
    """Raise :class:`ValueError` when a ``horizon`` is given but no MHE is among ``estimators``."""
    if horizon is not None and not any(name in MHE_NAMES for name in estimators):
        raise SettingsError(f"a horizon applies to the MHEs {list(MHE_NAMES)}, not to {list(estimators)}")


def estimator_settings(name: str, model: DiscreteModel, settings: Any = None, *,
                       precision: str = "float64", gate: Any = None, horizon: int | None = None):
    """The settings estimator ``name`` of ``model`` is built with: the one door for the
    compiled libraries and the Python references alike.

    ``settings`` (default: the system's, as ``learnest-compile``; a float32 UKF gets its alpha
    raised, :func:`float32_ukf_settings`), then ``gate`` replaces the innovation gate and
    ``horizon`` the MHE horizon; an MHE's steady-state arrival covariance is computed for
    ``model`` (:func:`~learnest_codegen.estimators.mhe_problem.mhe_settings`).
    """
    kind = estimator_kind(name)
    if horizon is not None and name not in MHE_NAMES:
        raise SettingsError(f"{name}: a horizon applies to the MHEs {list(MHE_NAMES)} only")
    chosen = settings or kind.default_settings(model)
    if precision == "float32" and settings is None and kind.float32_defaults is not None:
        chosen = kind.float32_defaults(chosen)
    if gate is not None:
        chosen = replace(chosen, gate=gate)
    if kind.horizon:
        chosen = mhe_settings(model, chosen, **({} if horizon is None else {"horizon": horizon}))
    return chosen


def compile_estimators(model: DiscreteModel, out: str | Path, *, model_hash: str,
                       estimators: tuple[str, ...] = DEFAULT_ESTIMATORS,
                       settings: Mapping[str, Any] | None = None,
                       precision: str = "float64", gate: Any = None,
                       horizon: int | None = None) -> dict[str, Any]:
    """Generate and build ``estimators`` for ``model`` under ``out``; returns name -> result.

    ``precision`` (``"float64"`` or ``"float32"``) is the C real type; an estimator that is
    not generated in it raises :class:`ValueError`. ``gate`` (a
    :class:`~learnest_codegen.estimators.gate.GateSettings`) replaces the innovation gate of
    every estimator's settings, ``horizon`` the horizon of every MHE's (see
    :func:`estimator_settings`). Each folder records where the model's system comes from, so
    that :func:`~learnest_codegen.pipeline.load_estimator` finds it.
    """
    problem = precision_problem(estimators, precision)
    if problem:
        raise SettingsError(problem)
    check_horizon(estimators, horizon)
    # loading a compiled folder must not import the learning package (tests/test_layout.py)
    from .learning.source import system_source, write_sidecar

    record = system_source(model.system)
    results = {}
    for name in estimators:
        kind = estimator_kind(name)
        chosen = estimator_settings(name, model, (settings or {}).get(name), precision=precision,
                                    gate=gate, horizon=horizon if name in MHE_NAMES else None)
        directory = estimator_dir(Path(out), model, name, precision, getattr(chosen, "horizon", None))
        extra = {} if precision == "float64" else {"precision": precision}
        with atomic_dir(directory) as tmp:
            _reusable(directory, tmp)
            result = kind.generate(model, chosen, tmp, model_hash=model_hash, **extra)
            write_sidecar(tmp, record)
        results[name] = _moved(result, tmp, directory)
    return results


def _reusable(old: Path, new: Path) -> None:
    """Link the library, its build stamp and a sound manifest of ``old`` into ``new``, so the
    toolchain reuses an unchanged library (it rebuilds one that no longer matches its stamp)."""
    if not old.is_dir():
        return
    for path in [*old.glob("lib*.so"), *old.glob("lib*.so.stamp")]:
        _link(path, new / path.name)
    try:
        read_manifest(old)  # only a manifest that still describes its library
    except (OSError, ValueError):
        return
    shutil.copy2(old / MANIFEST, new / MANIFEST)


def _link(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)  # the toolchain renames a new build over it: the old inode is untouched
    except OSError:
        shutil.copy2(src, dst)


def _moved(value: Any, tmp: Path, final: Path) -> Any:
    """``value`` (a generation result) with every path inside ``tmp`` moved to ``final``."""
    if isinstance(value, Path):
        try:
            return final / value.relative_to(tmp)
        except ValueError:
            return value
    if isinstance(value, tuple):
        return tuple(_moved(v, tmp, final) for v in value)
    if is_dataclass(value) and not isinstance(value, type):
        return replace(value, **{f.name: _moved(getattr(value, f.name), tmp, final) for f in fields(value)
                                 if f.init})
    return value
