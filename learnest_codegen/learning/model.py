"""A trained model: the residual net, what it was trained for, and its directory on disk.

A trained model is a directory holding the weights (``weights.pt``) and ``model.json`` (system,
network and training settings, hash of the training data, final loss) and nothing else.
:func:`make_net` builds the untrained net a system's residual structure asks for; training
(:mod:`.training`) fills it.
"""

from __future__ import annotations

import hashlib
import json
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import LearnestError, ModelMismatchError
from ..systems import System
from .network import NetworkSettings, ResidualNet

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

        Wall-clock fields (``train_seconds``) are left out so retraining gives the same hash.
        """
        stable = {k: v for k, v in self.meta.items() if k != "train_seconds"}
        h = hashlib.sha256(json.dumps(stable, sort_keys=True).encode())
        for name, tensor in sorted(self.net.state_dict().items()):
            h.update(name.encode() + tensor.detach().numpy().tobytes())
        return h.hexdigest()


def make_net(system: System, settings: NetworkSettings = NetworkSettings()) -> ResidualNet:
    """An untrained residual net for ``system``: it sees ``system.residual_input_names`` (angles
    as sine and cosine) and acts through the inputs ``system.residual_via_names`` when there are
    any, otherwise on the derivatives of ``system.residual_state_names``."""
    names = system.state_names
    periodic = tuple(names.index(n) for n in system.periodic_states)
    outputs = tuple(names.index(n) for n in system.residual_state_names)
    signals = [*names, *system.input_names]
    inputs = tuple(signals.index(n) for n in system.residual_input_names)
    via = tuple(system.input_names.index(n) for n in system.residual_via_names)
    prior_features = tuple(names.index(n) for n in system.residual_prior_feature_names)
    return ResidualNet(system.nx, system.nu, settings, periodic, outputs, inputs, via,
                       prior=system.f if via or prior_features else None,
                       prior_features=prior_features, prior_gains=system.residual.prior_gains)


def residual_structure(system: System) -> dict:
    """What a residual net of ``system`` sees and where it acts (stored with a trained model)."""
    return {"inputs": system.residual_input_names, "via": system.residual_via_names,
            "states": [] if system.residual_via_names else system.residual_state_names,
            "prior_features": system.residual_prior_feature_names,
            **({"prior_gains": True} if system.residual.prior_gains else {})}


def data_hash(*arrays: np.ndarray) -> str:
    """sha256 of the training arrays (identifies the data a model was trained on)."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()


def load_model(directory: str | Path, system: System) -> TrainedModel:
    """Load a model directory, checking that it was trained for ``system``.

    A model trained with a fitted (grey-box) prior carries the fitted parameters in
    ``model.json`` (``prior_params``); the loaded model's system holds them.
    """
    directory = Path(directory)
    meta_path, weights_path = directory / META, directory / WEIGHTS
    if not meta_path.is_file() or not weights_path.is_file():
        raise FileNotFoundError(f"{directory} is not a model directory (needs {META} and {WEIGHTS})")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelMismatchError(f"{meta_path} is not valid JSON ({exc}); the model directory is "
                                 "damaged: retrain or restore it") from exc
    if not isinstance(meta, dict) or "network" not in meta:
        raise ModelMismatchError(f"{meta_path} holds no model description; retrain or restore it")
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
