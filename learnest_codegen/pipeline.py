"""The pipeline as calls: simulate, train, compile, load, evaluate.

Every stage of the data flow is reachable from here with one import, and the commands, the demo
and the studies use the same calls, so a model reaches a running estimator by one path only::

    import learnest_codegen as ln

    system = ln.get_system("cartpole")
    train_run, test_run = ln.simulate(system, seed=0), ln.simulate(system, seed=1)
    model = ln.train(train_run, system, ln.QUICK_TRAINING)
    ukf = ln.compile_estimator(model, "ukf", out="generated")   # C library, loaded
    result = ln.evaluate(ukf, test_run)                          # estimates, MSE, timing

A *model* is ``"nominal"`` (the prior), ``"true"`` (simulation's truth), a trained model or its
directory. torch is imported only when a trained model is involved.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping, Union

import numpy as np

from .compilation import (
    ESTIMATOR_NAMES,
    compile_estimators,
    estimator_dir,
    estimator_kind,
    knode_model,
    resolve_model,
)
from .data import Run, check_sampling
from .evaluation import EstimateResult, run_estimator
from .export import DiscreteModel
from .runtime.manifest import read_manifest
from .systems import System, get_system

if TYPE_CHECKING:
    from .learning.training import TrainedModel, TrainingSettings

ModelLike = Union[str, Path, "TrainedModel", DiscreteModel, "ResolvedModel"]


def simulate(system: System | str, seed: int = 0, *, duration: float | None = None) -> Run:
    """Simulate the true system (scipy RK45, zero-order-hold inputs) into a :class:`Run` with truth."""
    from .simulation import simulate as sim  # scipy.integrate: loaded only when simulating

    return sim(get_system(system), seed, duration=duration)


@dataclass(frozen=True)
class ResolvedModel:
    """A discrete model and the hash that identifies it in compiled manifests."""

    model: DiscreteModel
    hash: str


def resolve(model: ModelLike, system: System | str | None = None, *,
            clamp_inputs: bool | None = None) -> ResolvedModel:
    """``"nominal"``, ``"true"``, a trained model, its directory, a :class:`DiscreteModel` (nominal
    or true) or an already resolved model.

    ``system`` is needed for the names and for model directories (checked against the model's
    own); a trained model knows its system. ``clamp_inputs`` keeps a trained net's inputs inside
    their training range (default :data:`~learnest_codegen.compilation.CLAMP_INPUTS`; see
    :func:`~learnest_codegen.compilation.knode_model`).
    """
    if isinstance(model, ResolvedModel):
        if clamp_inputs is not None:
            raise ValueError("resolve: a resolved model is already clamped or not; pass the trained "
                             "model (or its directory) with clamp_inputs instead")
        return model
    if isinstance(model, DiscreteModel):  # nominal and true models are identified by their kind
        if clamp_inputs:
            raise ValueError("resolve: clamp_inputs needs a trained model (or its directory)")
        if model.kind not in ("nominal", "true"):
            raise ValueError("resolve: a KNODE DiscreteModel carries no identity; pass the trained "
                             "model (or its directory) instead")
        return ResolvedModel(model, model.kind)
    if isinstance(model, (str, Path)):
        if system is None:
            raise ValueError(f"resolve: model {str(model)!r} needs a system")
        return ResolvedModel(*resolve_model(get_system(system), str(model), clamp_inputs))
    return ResolvedModel(*knode_model(model, clamp_inputs))


def train(run: Run, system: System | str, settings: TrainingSettings | None = None, *,
          observer: str | None = None, full_state: bool = False, progress: bool = True) -> TrainedModel:
    """Train the KNODE residual on ``run`` (Alg. 1 phase 1); see :func:`training.train_on_run`.

    ``settings`` defaults to :data:`~learnest_codegen.config.QUICK_TRAINING`.
    """
    from .config import QUICK_TRAINING
    from .learning.training import train_on_run

    return train_on_run(run, get_system(system), settings or QUICK_TRAINING, observer=observer,
                        full_state=full_state, progress=progress)


def make_estimator(model: ModelLike, estimator: str = "ukf", *, backend: str = "c",
                   out: str | Path = "generated", system: System | str | None = None,
                   settings: Any = None, precision: str = "float64", gate: Any = None,
                   clamp_inputs: bool | None = None):
    """One estimator of ``model``, compiled and loaded (``backend="c"``) or the Python reference.

    Parameters
    ----------
    model : see :func:`resolve`.
    estimator : a name of :data:`~learnest_codegen.compilation.ESTIMATOR_NAMES`.
    backend : ``"c"`` (generated C through ctypes) or ``"python"`` (FilterPy UKF, CasADi
        ``nlpsol`` MHE).
    out : folder of compiled estimators (one subfolder each; unchanged builds are reused).
    settings : the estimator's settings (default: the system's, as ``learnest-compile``).
    precision : the C real type, ``"float64"`` or ``"float32"`` (UKF and embedded MHE).
    gate : a :class:`~learnest_codegen.estimators.gate.GateSettings` replacing the settings'
        innovation gate (default: the settings' own, on by default).
    clamp_inputs : keep a trained net's inputs inside their training range (see :func:`resolve`).
    """
    resolved = resolve(model, system, clamp_inputs=clamp_inputs)
    kind = estimator_kind(estimator)
    if backend == "python":
        if kind.python is None:
            raise ValueError(f"{estimator} has no Python reference (its C defines it); use backend 'c'")
        chosen = settings or kind.default_settings(resolved.model)
        return kind.python(resolved.model, chosen if gate is None else replace(chosen, gate=gate))
    if backend != "c":
        raise ValueError(f"make_estimator: backend must be 'c' or 'python', got {backend!r}")
    compile_estimators(resolved.model, out, model_hash=resolved.hash, estimators=(estimator,),
                       settings={estimator: settings} if settings is not None else None,
                       precision=precision, gate=gate)
    return load_estimator(estimator_dir(Path(out), resolved.model, estimator, precision),
                          expect=expected_manifest(resolved))


def expected_manifest(model: ModelLike, system: System | str | None = None) -> dict[str, Any]:
    """What a compiled folder of ``model`` must record: the system's name and fingerprint (its
    equations, parameters and noise, so a different system of the same name is refused), the
    time step and the model's hash."""
    resolved = resolve(model, system)
    sys_ = resolved.model.system
    return {"system": sys_.name, "system_fingerprint": sys_.fingerprint(), "dt": sys_.dt,
            "model_hash": resolved.hash}


def compile_estimator(model: ModelLike, estimator: str = "ukf", *, out: str | Path = "generated",
                      system: System | str | None = None, settings: Any = None,
                      precision: str = "float64", gate: Any = None, clamp_inputs: bool | None = None):
    """Generate, build and load one estimator of ``model`` (see :func:`make_estimator`)."""
    return make_estimator(model, estimator, backend="c", out=out, system=system, settings=settings,
                          precision=precision, gate=gate, clamp_inputs=clamp_inputs)


def load_estimator(directory: str | Path, *, expect: Mapping[str, Any] | None = None,
                   gate: Any = None):
    """Load a compiled estimator folder, whichever estimator its manifest names.

    ``gate`` (:class:`~learnest_codegen.estimators.gate.GateSettings`) replaces the compiled
    innovation gate; the library applies it at ``reset`` (the gate is a run-time setting).
    """
    kind = estimator_kind(str(read_manifest(Path(directory)).get("estimator")))
    estimator = kind.compiled(directory, expect=expect)
    if gate is None:
        return estimator
    return kind.compiled(directory, expect=expect, settings=replace(estimator.settings, gate=gate))


def reference_estimator(model: ModelLike, estimator: str = "ukf", *, system: System | str | None = None,
                        settings: Any = None):
    """The Python reference (FilterPy UKF, CasADi ``nlpsol`` MHE) of ``model``."""
    return make_estimator(model, estimator, backend="python", system=system, settings=settings)


def evaluate(estimator, run: Run, x0: np.ndarray | None = None, *, system: System | str | None = None,
             label: str = "") -> EstimateResult:
    """Run ``estimator`` over ``run`` from ``x0`` (default: the system's ``x0``) and time it.

    ``system`` defaults to the built-in one the run names. The run must be sampled at the
    system's ``dt``, the step the estimator was built for. The result's ``mse(run.x)`` scores it
    when the truth is known.
    """
    system = get_system(system or run.system)
    check_sampling(run, system.dt, label or "evaluate")
    x0 = np.asarray(system.x0 if x0 is None else x0, dtype=float)
    return run_estimator(estimator, run, x0, label or type(estimator).__name__)


__all__ = ["ESTIMATOR_NAMES", "ResolvedModel", "compile_estimator", "evaluate", "expected_manifest",
           "load_estimator", "make_estimator", "reference_estimator", "resolve", "simulate", "train"]
