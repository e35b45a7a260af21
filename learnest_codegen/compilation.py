"""The compile stage: a model (nominal, true or trained KNODE) to compiled estimator directories.

``compile_estimators`` generates and builds each requested estimator into
``out/<system>_<kind>_<estimator>/`` (C sources, header, shared library, ``manifest.json``).
Generation is deterministic and the toolchain reuses a library whose inputs did not change, so
compiling the same model twice costs only the code generation.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from .errors import UnknownNameError
from .export import DiscreteModel, hybrid_model, prior_model, true_model
from .systems import System


@dataclass(frozen=True)
class EstimatorKind:
    """How to make settings for, generate, and load one kind of estimator."""

    default_settings: Callable[[DiscreteModel], Any]
    generate: Callable[..., Any]
    python: Callable[..., Any]
    compiled: Callable[..., Any]


def _registry() -> dict[str, EstimatorKind]:
    from .codegen.mhe import generate_mhe
    from .codegen.ukf import generate_ukf
    from .estimators.mhe import MHE
    from .estimators.mhe_problem import MHESettings, steady_state_arrival
    from .estimators.ukf import UKF, UKFSettings
    from .runtime.mhe import CompiledMHE
    from .runtime.ukf import CompiledUKF

    def mhe_defaults(model: DiscreteModel) -> MHESettings:
        return steady_state_arrival(model, MHESettings.from_system(model.system))

    return {
        "mhe": EstimatorKind(mhe_defaults, generate_mhe, MHE, CompiledMHE),
        "ukf": EstimatorKind(lambda model: UKFSettings.from_system(model.system), generate_ukf, UKF,
                             CompiledUKF),
    }


ESTIMATOR_NAMES = ("mhe", "ukf")


def estimator_kind(name: str) -> EstimatorKind:
    """Look up an estimator by name (``"mhe"`` or ``"ukf"``)."""
    if name not in ESTIMATOR_NAMES:
        raise UnknownNameError(f"unknown estimator {name!r}; choose from {list(ESTIMATOR_NAMES)}")
    return _registry()[name]


def resolve_model(system: System, model: str) -> tuple[DiscreteModel, str]:
    """``"nominal"``, ``"true"`` or a trained-model directory to ``(DiscreteModel, model_hash)``."""
    if model == "nominal":
        return prior_model(system), "nominal"
    if model == "true":
        return true_model(system), "true"
    from .training import load_model  # torch is needed only for trained models

    trained = load_model(model, system)
    return hybrid_model(system, trained.net), trained.hash


def estimator_dir(out: Path, model: DiscreteModel, name: str) -> Path:
    """Where an estimator of ``model`` is compiled to inside ``out``."""
    return Path(out) / f"{model.system.name}_{model.kind}_{name}"


def compile_estimators(model: DiscreteModel, out: str | Path, *, model_hash: str,
                       estimators: tuple[str, ...] = ESTIMATOR_NAMES,
                       settings: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Generate and build ``estimators`` for ``model`` under ``out``; returns name -> result."""
    results = {}
    for name in estimators:
        kind = estimator_kind(name)
        chosen = (settings or {}).get(name) or kind.default_settings(model)
        directory = estimator_dir(Path(out), model, name)
        directory.mkdir(parents=True, exist_ok=True)
        results[name] = kind.generate(model, chosen, directory, model_hash=model_hash)
    return results
