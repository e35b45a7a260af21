"""The pipeline as calls: simulate, train, compile, load, evaluate.

Every stage of the data flow is reachable from here with one import, and the commands, the demo
and the studies use the same calls, so a model reaches a running estimator by one path only::

    import learnest_codegen as ln

    system = ln.get_system("cartpole")
    train_run, test_run = ln.simulate(system, seed=0), ln.simulate(system, seed=1)
    model = ln.train(train_run, system)                          # ln.DEFAULT_TRAINING
    ukf = ln.make_estimator(model, "ukf", out="generated")      # C library, loaded
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
    estimator_kind,
    estimator_settings,
    knode_model,
    resolve_model,
)
from .data import Run, check_sampling
from .errors import ModelMismatchError, SettingsError
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

    ``system`` is needed for ``"nominal"`` and ``"true"``; a model directory records its own
    (a built-in by name, a system file by path and content hash, see
    :mod:`~learnest_codegen.learning.source`), and a ``system`` given is checked against it.
    ``clamp_inputs`` keeps a trained net's inputs inside their training range (default
    :data:`~learnest_codegen.compilation.CLAMP_INPUTS`; see
    :func:`~learnest_codegen.compilation.knode_model`).
    """
    if isinstance(model, ResolvedModel):
        if clamp_inputs is not None:
            raise SettingsError("resolve: a resolved model is already clamped or not; pass the trained "
                             "model (or its directory) with clamp_inputs instead")
        return model
    if isinstance(model, DiscreteModel):  # nominal and true models are identified by their kind
        if clamp_inputs:
            raise SettingsError("resolve: clamp_inputs needs a trained model (or its directory)")
        if model.kind not in ("nominal", "true"):
            raise SettingsError("resolve: a KNODE DiscreteModel carries no identity; pass the trained "
                                "model (or its directory) instead")
        return ResolvedModel(model, model.kind)
    if isinstance(model, (str, Path)):
        if str(model) in ("nominal", "true"):
            if system is None:
                raise SettingsError(f"resolve: model {str(model)!r} needs a system (system=)")
            return ResolvedModel(*resolve_model(get_system(system), str(model), clamp_inputs))
        from .learning.model import load_model  # torch only for trained models

        trained = load_model(model, None if system is None else get_system(system))
        return ResolvedModel(*knode_model(trained, clamp_inputs))
    return ResolvedModel(*knode_model(model, clamp_inputs))


def train(run: Run, system: System | str, settings: TrainingSettings | None = None, *,
          observer: str | None = None, full_state: bool = False, progress: bool = True) -> TrainedModel:
    """Train the KNODE residual on ``run`` (Alg. 1 phase 1); see :func:`training.train_on_run`.

    ``settings`` defaults to :data:`~learnest_codegen.config.DEFAULT_TRAINING`, the one default
    (``learnest train``'s too); the pre-training observer to :func:`~learnest_codegen.observers.
    choose_observer`'s choice, said on stderr when ``progress``.
    """
    from .config import DEFAULT_TRAINING
    from .learning.training import train_on_run

    return train_on_run(run, get_system(system), settings or DEFAULT_TRAINING, observer=observer,
                        full_state=full_state, progress=progress)


def make_estimator(model: ModelLike, estimator: str = "ukf", *, backend: str = "c",
                   out: str | Path = "generated", system: System | str | None = None,
                   settings: Any = None, precision: str = "float64", gate: Any = None,
                   horizon: int | None = None, clamp_inputs: bool | None = None):
    """One estimator of ``model``, compiled and loaded (``backend="c"``) or the Python reference:
    the one door to an estimator from a model (:func:`load_estimator` loads a compiled folder).

    Both backends take their settings from
    :func:`~learnest_codegen.compilation.estimator_settings`, so the same arguments give the
    same estimator.

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
    horizon : the MHE horizon N (MHEs only; default: the settings').
    clamp_inputs : keep a trained net's inputs inside their training range (see :func:`resolve`).
    """
    resolved = resolve(model, system, clamp_inputs=clamp_inputs)
    kind = estimator_kind(estimator)
    if backend == "python":
        if kind.python is None:
            raise SettingsError(f"{estimator} has no Python reference (its C defines it); use backend 'c'")
        chosen = estimator_settings(estimator, resolved.model, settings, gate=gate, horizon=horizon)
        return _with_system(kind.python(resolved.model, chosen), resolved.model.system)
    if backend != "c":
        raise SettingsError(f"make_estimator: backend must be 'c' or 'python', got {backend!r}")
    built = compile_estimators(resolved.model, out, model_hash=resolved.hash, estimators=(estimator,),
                               settings={estimator: settings} if settings is not None else None,
                               precision=precision, gate=gate, horizon=horizon)
    return _with_system(load_estimator(built[estimator].directory, expect=expected_manifest(resolved)),
                        resolved.model.system)


def _with_system(estimator, system: System):
    """``estimator`` knowing its system (``estimator.system``), for :func:`evaluate`."""
    try:
        estimator.system = system
    except AttributeError:  # a class that forbids it: evaluate then looks the system up
        pass
    return estimator


def expected_manifest(model: ModelLike, system: System | str | None = None) -> dict[str, Any]:
    """What a compiled folder of ``model`` must record: the system's name and fingerprint (its
    equations, parameters and noise, so a different system of the same name is refused), the
    time step and the model's hash."""
    resolved = resolve(model, system)
    sys_ = resolved.model.system
    return {"system": sys_.name, "system_fingerprint": sys_.fingerprint(), "dt": sys_.dt,
            "model_hash": resolved.hash}


def load_estimator(directory: str | Path, *, expect: Mapping[str, Any] | None = None,
                   gate: Any = None):
    """Load a compiled estimator folder, whichever estimator its manifest names.

    ``gate`` (:class:`~learnest_codegen.estimators.gate.GateSettings`) replaces the compiled
    innovation gate; the library applies it at ``reset`` (the gate is a run-time setting).
    """
    kind = estimator_kind(str(read_manifest(Path(directory)).get("estimator")))
    estimator = kind.compiled(directory, expect=expect)
    if gate is not None:
        estimator = kind.compiled(directory, expect=expect, settings=replace(estimator.settings, gate=gate))
    return estimator


def estimator_system(estimator) -> System:
    """The system an estimator was made for: the one :func:`make_estimator` attached, or the
    one its compiled folder records (a built-in by name, a system file by path, checked against
    the file's content and the library's system fingerprint)."""
    system = getattr(estimator, "system", None)
    if isinstance(system, System):
        return system
    model = getattr(estimator, "model", None)
    if isinstance(getattr(model, "system", None), System):
        return model.system
    directory = getattr(estimator, "directory", None)
    if directory is None:
        raise SettingsError(f"{type(estimator).__name__} does not say which system it estimates; "
                            "pass system=")
    from .learning.source import read_sidecar, system_from_source

    manifest = read_manifest(Path(directory))
    system = system_from_source(read_sidecar(directory), manifest.get("system"),
                                f"compiled estimator {directory}")
    if manifest.get("system_fingerprint") not in (None, system.fingerprint()):
        raise ModelMismatchError(f"compiled estimator {directory} was built for another version of "
                                 f"system {system.name!r} (its equations, parameters or noise "
                                 "changed); recompile it")
    return system


def evaluate(estimator, run: Run, x0: np.ndarray | None = None, *, P0: np.ndarray | None = None,
             system: System | str | None = None, label: str = "") -> EstimateResult:
    """Run ``estimator`` over ``run`` from ``x0`` (default: the system's ``x0``) and time it.

    ``P0`` is the covariance of ``x0`` (default: the estimator's own: the UKF's initial
    covariance, the MHE's running arrival covariance); give it when ``x0`` is a doubtful
    guess, e.g. ``initial_covariance(system)``. ``system`` defaults to the estimator's own
    (:func:`estimator_system`). The run must be sampled at the system's ``dt``, the step the
    estimator was built for; its missing outputs (NaN) are left out. The result's
    ``mse(run.x)`` scores it when the truth is known.
    """
    system = get_system(system) if system is not None else estimator_system(estimator)
    check_sampling(run, system.dt, label or "evaluate")
    x0 = np.asarray(system.x0 if x0 is None else x0, dtype=float)
    return run_estimator(estimator, run, x0, label or type(estimator).__name__, P0)


def initial_covariance(system: System | str) -> np.ndarray:
    """``diag(initial_std**2)`` of ``system.noise``: the uncertainty of its ``x0``, the ``P0``
    that goes with a guessed start."""
    return np.diag(np.square(get_system(system).noise.initial_std))


__all__ = ["ESTIMATOR_NAMES", "ResolvedModel", "estimator_system", "evaluate", "expected_manifest",
           "initial_covariance", "load_estimator", "make_estimator", "resolve", "simulate", "train"]
