"""A trained model: the residual net, what it was trained for, and its directory on disk.

A trained model is a directory holding the weights (``weights.pt``) and ``model.json`` (system,
network and training settings, hash of the training data, final loss, and under
``system_source`` where the system comes from: see :mod:`.source`) and nothing else.
:func:`make_net` builds the untrained net a system's residual structure asks for; training
(:mod:`.training`) fills it.
"""

from __future__ import annotations

import hashlib
import json
import pickle
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch

from ..errors import LearnestError, ModelMismatchError
from ..systems import System
from .network import NetworkSettings, ResidualNet
from .source import KEY as SOURCE_KEY
from .source import model_meta, system_from_source

WEIGHTS, META = "weights.pt", "model.json"
__all__ = ["META", "WEIGHTS", "TrainedModel", "data_hash", "load_model", "make_net", "residual_structure"]

@dataclass
class TrainedModel:
    """A trained residual network and what it was trained for."""

    system: System
    net: ResidualNet
    meta: dict

    def save(self, directory: str | Path) -> Path:
        """Write the model directory (weights + ``model.json``)."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        torch.save(self.net.state_dict(), directory / WEIGHTS)
        (directory / META).write_text(json.dumps(self.meta, indent=2, sort_keys=True))
        return directory

    @property
    def hash(self) -> str:
        """Content hash of weights and settings: identifies the model in compiled manifests.

        Wall-clock fields (``train_seconds``) are left out so retraining gives the same hash,
        and so is where the system file lives (``system_source``).
        """
        stable = {k: v for k, v in self.meta.items() if k not in ("train_seconds", SOURCE_KEY)}
        h = hashlib.sha256(json.dumps(stable, sort_keys=True).encode())
        for name, tensor in sorted(self.net.state_dict().items()):
            h.update(name.encode() + tensor.detach().numpy().tobytes())
        return h.hexdigest()


def make_net(system: System, settings: NetworkSettings = NetworkSettings()) -> ResidualNet:
    """An untrained residual net for ``system``: it sees ``system.residual_input_names`` (angles
    as sine and cosine) and acts through the inputs ``system.residual_via_names`` when there are
    any, otherwise on the derivatives of :func:`residual_states`."""
    names = system.state_names
    periodic = tuple(names.index(n) for n in system.periodic_states)
    outputs = tuple(names.index(n) for n in residual_states(system))
    signals = [*names, *system.input_names]
    inputs = tuple(signals.index(n) for n in system.residual_input_names)
    via = tuple(system.input_names.index(n) for n in system.residual_via_names)
    prior_features = tuple(names.index(n) for n in system.residual_prior_feature_names)
    return ResidualNet(system.nx, system.nu, settings, periodic, outputs, inputs, via,
                       prior=system.f if via or prior_features else None,
                       prior_features=prior_features, prior_gains=system.residual.prior_gains,
                       prior_terms=partial(_prior_terms, system))


def _prior_terms(system: System, ops, xs: list, us: list) -> list:
    """The prior's derivative as a list of terms (``System.f`` before stacking)."""
    return list(system.dynamics(ops, xs, us, system.params))


def residual_states(system: System) -> list[str]:
    """States whose derivative the residual may change: ``system.residual_state_names``; for a
    system that declares neither ``residual.states`` nor kinematic chains, every state but those
    whose derivative its equations show to be another state (``qdot`` is the derivative of
    ``q``: kinematics, where a free residual would only fit observation noise; see
    :func:`~learnest_codegen.observers.inferred_chains`)."""
    if system.residual.states is not None or system.kinematic_chains:
        return system.residual_state_names
    from ..observers import inferred_chains

    exact = {n for chain in inferred_chains(system) for n in chain.states[:-1]}
    return [n for n in system.state_names if n not in exact]


def residual_structure(system: System) -> dict:
    """What a residual net of ``system`` sees and where it acts (stored with a trained model)."""
    return {"inputs": system.residual_input_names, "via": system.residual_via_names,
            "states": [] if system.residual_via_names else residual_states(system),
            "prior_features": system.residual_prior_feature_names,
            **({"prior_gains": True} if system.residual.prior_gains else {})}


def data_hash(*arrays: np.ndarray) -> str:
    """sha256 of the training arrays (identifies the data a model was trained on)."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()


def load_model(directory: str | Path, system: System | None = None) -> TrainedModel:
    """Load a model directory, checking that it was trained for ``system``.

    ``system`` defaults to the one the model records (``model.json``'s ``system_source``: a
    built-in by name, a system file by path, refused when the file changed since; see
    :mod:`.source`). A model trained with a fitted (grey-box) prior carries the fitted
    parameters in ``model.json`` (``prior_params``); the loaded model's system holds them.
    """
    directory = Path(directory)
    weights_path = directory / WEIGHTS
    meta = model_meta(directory)
    if system is None:
        system = system_from_source(meta.get(SOURCE_KEY), meta.get("system"), f"model {directory}")
    got = (meta.get("system"), meta.get("nx"), meta.get("nu"))
    if got != (system.name, system.nx, system.nu):
        raise ModelMismatchError(f"model {directory} was trained for system {got[0]!r} "
                                 f"(nx={got[1]}, nu={got[2]}), not {system.name!r} "
                                 f"(nx={system.nx}, nu={system.nu})")
    if meta.get("prior_params"):  # a grey-box prior fitted with the net: part of the model
        from .prior_fit import fitted_system

        try:
            system = fitted_system(system, meta["prior_params"])
        except (LearnestError, TypeError, ValueError, AttributeError) as exc:
            raise ModelMismatchError(f"model {directory} has fitted prior parameters "
                                     f"{meta['prior_params']!r} that system {system.name!r} cannot take: "
                                     f"{exc}") from exc
    stored, expected = meta.get("residual"), residual_structure(system)
    if stored is not None and stored != expected:
        raise ModelMismatchError(f"model {directory} has residual structure {stored}, but system "
                                 f"{system.name!r} now defines {expected}; retrain it")
    net = make_net(system, NetworkSettings(**meta["network"]))
    try:
        net.load_state_dict(torch.load(weights_path, weights_only=True))
    except (RuntimeError, EOFError, OSError, ValueError, KeyError, pickle.UnpicklingError) as exc:
        raise ModelMismatchError(f"{weights_path} cannot be read as this model's weights "
                                 f"({str(exc).splitlines()[0]}); retrain or restore it") from exc
    return TrainedModel(system, net, meta)
