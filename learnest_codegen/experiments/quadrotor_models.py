"""What a quadrotor study's KNODE model is (its features) and how it is trained on flights.

Features (:data:`FEATURES`) pick the system: ``state`` (the residual sees velocity and
acceleration: the paper's), ``thrust`` (also the thrust command and the battery voltage),
``linear`` (a grey-box prior ``A x`` whose acceleration rows are fitted to the training flights,
then the net on velocity and acceleration), ``linear_prior`` (that prior alone, no net),
``thrust_prior`` (a grey-box prior of the true model's form, ``adot = c_T vbat T + c_v v + c_a
a`` (+ ``c_0`` on z), one thrust gain for all axes, fitted alone), ``thrust_prior_axes`` (its
vertical gain fitted apart), ``thrust_prior_z`` (the thrust on the vertical only) and
``thrust_linear`` (``thrust_prior`` then the net). The ``bias*`` features are the same models
with the accelerometer's world-frame offset as three more states
(:func:`~learnest_codegen.systems.quadrotor.with_accelerometer_bias`): ``bias`` (the paper's
triple integrator with the offsets, nothing fitted: a control), ``bias_prior``, ``bias_linear``,
``bias_thrust_prior``, ``bias_thrust_prior_axes``; ``bias_lag`` and ``bias_lag_prior`` also read
the accelerometer through a first-order lag whose time constant the tuning chooses.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..errors import UnknownNameError
from ..export import DiscreteModel, prior_model
from ..systems import System
from ..systems.quadrotor import (
    QUADROTOR,
    QUADROTOR_BIAS,
    QUADROTOR_BIAS_LAG,
    QUADROTOR_LINEAR,
    QUADROTOR_LINEAR_BIAS,
    QUADROTOR_LINEAR_BIAS_LAG,
    QUADROTOR_STATE,
    QUADROTOR_THRUST_LINEAR,
    QUADROTOR_THRUST_LINEAR_BIAS,
)
from .quadrotor_cases import Case
from .store import code_hash
from .store import content_hash as _hash

if TYPE_CHECKING:
    from .quadrotor import StudySettings


@dataclass(frozen=True)
class Features:
    """What a study's KNODE model is: the system (its residual's inputs) and the prior
    parameters fitted to the training flights before the net is trained (the grey-box route).
    ``net=False`` and no ``fit_prior``: the system's prior as it is, nothing trained (a
    control, such as the accelerometer offsets alone). ``fit_on``: the system whose prior is
    fitted (the parameters then go into ``system``, which has more states than the observer
    gives: the accelerometer lag); ``choose``: prior parameters chosen with the noise on the
    training flights (``(name, values)``, :func:`~.quadrotor_tuning.tune`; without the tuning
    the registered value)."""

    system: System
    fit_prior: tuple[str, ...] = ()
    start_at_prior: bool = False
    net: bool = True
    fit_on: System | None = None
    choose: tuple[tuple[str, tuple[float, ...]], ...] = ()

    @property
    def observer_system(self) -> System:
        """The system the pre-training observer runs on: the triple integrator, with the
        accelerometer offsets when the model has them (``linear_rts`` needs a linear prior)."""
        fitted = self.fit_on or self.system
        return QUADROTOR_BIAS if fitted.nx == QUADROTOR_BIAS.nx else QUADROTOR

    @property
    def trained(self) -> bool:
        return self.net or bool(self.fit_prior)


_THRUST_SHARED = tuple(n for n in QUADROTOR_THRUST_LINEAR.params if n != "dc_T_z")  # one thrust gain
_THRUST_Z = tuple(n for n in QUADROTOR_THRUST_LINEAR.params if n != "c_T")  # thrust on z only
_LINEAR = tuple(QUADROTOR_LINEAR.params)
#: The accelerometer lags [s] the tuning chooses from (``bias_lag_prior``).
LAG_GRID_S = (0.01, 0.02, 0.04, 0.08, 0.16)
FEATURES: dict[str, Features] = {
    "state": Features(QUADROTOR_STATE), "thrust": Features(QUADROTOR),
    "linear": Features(QUADROTOR_LINEAR, _LINEAR, start_at_prior=True),
    "linear_prior": Features(QUADROTOR_LINEAR, _LINEAR, net=False),
    "thrust_prior": Features(QUADROTOR_THRUST_LINEAR, _THRUST_SHARED, net=False),
    "thrust_prior_axes": Features(QUADROTOR_THRUST_LINEAR, tuple(QUADROTOR_THRUST_LINEAR.params), net=False),
    "thrust_prior_z": Features(QUADROTOR_THRUST_LINEAR, _THRUST_Z, net=False),
    "thrust_linear": Features(QUADROTOR_THRUST_LINEAR, _THRUST_SHARED, start_at_prior=True),
    # with the accelerometer's offset as states (systems/quadrotor.py, with_accelerometer_bias)
    "bias": Features(QUADROTOR_BIAS, net=False),
    "bias_prior": Features(QUADROTOR_LINEAR_BIAS, _LINEAR, net=False),
    "bias_linear": Features(QUADROTOR_LINEAR_BIAS, _LINEAR, start_at_prior=True),
    "bias_thrust_prior": Features(QUADROTOR_THRUST_LINEAR_BIAS, _THRUST_SHARED, net=False),
    "bias_thrust_prior_axes": Features(QUADROTOR_THRUST_LINEAR_BIAS,
                                       tuple(QUADROTOR_THRUST_LINEAR.params), net=False),
    "bias_lag": Features(QUADROTOR_BIAS_LAG, net=False, choose=(("tau_acc", LAG_GRID_S),)),
    "bias_lag_prior": Features(QUADROTOR_LINEAR_BIAS_LAG, _LINEAR, net=False, fit_on=QUADROTOR_LINEAR_BIAS,
                               choose=(("tau_acc", LAG_GRID_S),)),
}
#: The configuration measured best on held-out trajectory types (docs/reports/flights_study.md).
RECOMMENDED_FEATURES = "bias_lag_prior"
def feature_system(features: str) -> System:
    """The quadrotor system whose residual sees the named features (see :data:`FEATURES`)."""
    if features not in FEATURES:
        raise UnknownNameError(f"unknown features {features!r}; choose from {list(FEATURES)}")
    return FEATURES[features].system


def observations(cases: Sequence[Case], out: Path, settings: StudySettings,
                  system: System = QUADROTOR) -> list[np.ndarray]:
    """The pre-training observer's states of each case on ``system``, cached in ``OUT/observations``."""
    from ..observers import observe

    zetas = []
    for case in cases:
        suffix = "" if system is QUADROTOR else f".{system.name}"
        path = out / "observations" / f"{case.name}{suffix}.npz"
        ident = _hash({"observer": settings.observer, "system": system.name, "samples": len(case.run),
                       "y": float(np.nansum(case.run.y)), "u": float(np.sum(case.run.u))})
        if path.is_file():
            with np.load(path) as stored:
                if str(stored["ident"]) == ident:
                    zetas.append(stored["zeta"])
                    continue
        zeta = observe(case.run, system, settings.observer).zeta
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.npz")  # whole or not at all: studies share it
        np.savez(tmp, zeta=zeta, ident=ident)
        os.replace(tmp, path)
        zetas.append(zeta)
    return zetas


def trained_model(train: Sequence[Case], features: str, out: Path, settings: StudySettings,
                  directory: Path, *, progress: bool = True):
    """The KNODE model trained on ``train`` with ``features``: loaded from ``directory`` when a
    model of the same training is there, else trained (on all the flights at once) and saved.
    A feature that trains nothing (``net=False``, no ``fit_prior``) is its system's prior."""
    from ..learning.model import load_model
    from ..learning.runs import train_on_runs

    spec = FEATURES[features]
    system = spec.fit_on or feature_system(features)
    if not spec.trained:
        return prior_model(system)
    ident = _hash({"train": [c.name for c in train], "samples": [len(c.run) for c in train],
                   "features": features, "training": settings.training.to_json(), "code": code_hash(),
                   "observer": settings.observer, "fit_prior": list(spec.fit_prior),
                   "start_at_prior": spec.start_at_prior, "net": spec.net,
                   "observer_system": spec.observer_system.name,
                   **({} if settings.net_must_beat_prior else {"net_must_beat_prior": False})})
    meta = directory / "model.json"
    if meta.is_file() and json.loads(meta.read_text()).get("study_training") == ident:
        return _onto(load_model(directory, system), spec)
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 2x16 net: threads only contend
    try:
        model = train_on_runs([c.run for c in train], system, settings.training,
                              names=[c.name for c in train], observer=settings.observer,
                              observations=observations(train, out, settings, spec.observer_system),
                              fit_prior=spec.fit_prior, start_at_prior=spec.start_at_prior, net=spec.net,
                              net_must_beat_prior=settings.net_must_beat_prior, progress=progress)
    finally:
        torch.set_num_threads(threads)
    model.meta["study_training"] = ident
    model.save(directory)
    return _onto(model, spec)


def _onto(model, spec: Features):
    """``model``, or with ``spec.fit_on`` the prior of ``spec.system`` with its fitted parameters."""
    if spec.fit_on is None:
        return model
    from ..learning.prior_fit import fitted_system

    return prior_model(fitted_system(spec.system, model.meta.get("prior_params") or {}))


def training_record(trained) -> dict:
    """What a result file records of the model: its fitted prior parameters, whether a net was kept."""
    if isinstance(trained, DiscreteModel):
        return {"prior_params": dict(trained.system.params), "net_kept": False, "trained": False}
    return {k: trained.meta.get(k) for k in ("train_seconds", "best_epoch", "final_loss", "prior_loss",
                                             "observer", "prior_params", "net_kept")}
