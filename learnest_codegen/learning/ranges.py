"""The range of a residual net's inputs over its training data, and how far a run leaves it.

A net is only trustworthy where it was trained. Training records, per net input (the features
the MLP sees before standardisation: the residual's states and inputs, angles as sine and
cosine, prior features), the least and greatest value over the training data in the
``training_ranges`` key of ``model.json``. :func:`extrapolation` reports the share of a run's
samples that leave that box; :func:`training_box` gives the box that the export can clamp the
net's inputs to (``clamp_inputs``, see :func:`learnest_codegen.export.hybrid_model`).

Why the flights need it, and what clamping does there: ``docs/reports/flights.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..errors import ModelMismatchError, ShapeError

RANGES_KEY = "training_ranges"
__all__ = ["RANGES_KEY", "Extrapolation", "InputBox", "extrapolation", "feature_names", "record_ranges",
           "training_box"]


@dataclass(frozen=True)
class InputBox:
    """Per-feature bounds ``low <= feature <= high`` of a net's inputs.

    Attributes
    ----------
    names : feature names, in the net's input order (``sin(theta)`` for an angle, ``f(ax)`` for
        a prior feature).
    low, high : (n,) least and greatest value seen in training.
    """

    names: tuple[str, ...]
    low: tuple[float, ...]
    high: tuple[float, ...]

    def __post_init__(self) -> None:
        if not (len(self.names) == len(self.low) == len(self.high)) or not self.names:
            raise ShapeError(f"InputBox: names, low and high must have one entry per feature, got "
                             f"{len(self.names)}, {len(self.low)}, {len(self.high)}")
        if any(not lo <= hi for lo, hi in zip(self.low, self.high)):
            raise ShapeError(f"InputBox: need low <= high for every feature, got {self.low}, {self.high}")

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low, high)`` as float arrays (what the net's clamp takes)."""
        return np.asarray(self.low, dtype=float), np.asarray(self.high, dtype=float)

    def to_json(self) -> dict[str, Any]:
        return {"names": list(self.names), "low": list(self.low), "high": list(self.high)}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "InputBox":
        try:
            return cls(tuple(data["names"]), tuple(map(float, data["low"])), tuple(map(float, data["high"])))
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelMismatchError(f"{RANGES_KEY} in model.json must hold names, low and high "
                                     f"lists; got {data!r}") from exc


@dataclass(frozen=True)
class Extrapolation:
    """How much of a run lies outside a model's training box.

    Attributes
    ----------
    share : fraction of samples with at least one net input outside the box.
    by_feature : feature name -> fraction of samples with that input outside the box.
    samples : samples checked.
    """

    share: float
    by_feature: dict[str, float]
    samples: int

    def worst(self, n: int = 2) -> list[tuple[str, float]]:
        """The ``n`` features most often outside, with their shares (only those ever outside)."""
        ranked = sorted(self.by_feature.items(), key=lambda kv: -kv[1])
        return [(k, v) for k, v in ranked[:n] if v > 0]

    def describe(self) -> str:
        """One line: ``"12.3 % of 3400 samples outside the training range (vbat 11.0 %, ...)"``."""
        where = ", ".join(f"{k} {100 * v:.1f} %" for k, v in self.worst(3))
        return (f"{100 * self.share:.1f} % of {self.samples} samples outside the training range"
                + (f" ({where})" if where else ""))

    def to_json(self) -> dict[str, Any]:
        return {"share": self.share, "by_feature": dict(self.by_feature), "samples": self.samples}


def feature_names(net, state_names: list[str], input_names: list[str]) -> tuple[str, ...]:
    """Names of ``net``'s input features in its order (see ``ResidualNet._features``)."""
    signals = [*state_names, *input_names]
    keep = [signals[i] for i in net.inputs if i not in net.periodic]
    angles = [f"{f}({signals[i]})" for i in net.periodic if i in net.inputs for f in ("sin", "cos")]
    return tuple(keep + angles + [f"f({state_names[i]})" for i in net.prior_features])


def record_ranges(net, system, zeta: np.ndarray, u: np.ndarray) -> dict[str, Any]:
    """The box of ``net``'s inputs over training states ``zeta (M, nx)`` and inputs ``u (M, nu)``,
    as the JSON stored under :data:`RANGES_KEY`."""
    feats = net.features_numpy(zeta, u)
    box = InputBox(feature_names(net, system.state_names, system.input_names),
                   tuple(float(v) for v in feats.min(axis=0)), tuple(float(v) for v in feats.max(axis=0)))
    return box.to_json()


def training_box(model) -> InputBox | None:
    """The trained model's input box, or ``None`` for a model trained before boxes were recorded."""
    data = model.meta.get(RANGES_KEY)
    if data is None:
        return None
    box = InputBox.from_json(data)
    expected = feature_names(model.net, model.system.state_names, model.system.input_names)
    if box.names != expected:
        raise ModelMismatchError(f"{RANGES_KEY} in model.json names features {list(box.names)}, but the "
                                 f"net of system {model.system.name!r} has {list(expected)}; retrain it")
    return box


def extrapolation(model, x: np.ndarray, u: np.ndarray) -> Extrapolation | None:
    """Share of the samples ``x (T, nx)``, ``u (T, nu)`` whose net inputs leave ``model``'s
    training box (``None`` when the model records no box).

    ``x`` is what the net sees at run time: an estimator's estimates, or reference states.
    """
    box = training_box(model)
    if box is None:
        return None
    x, u = np.atleast_2d(np.asarray(x, float)), np.atleast_2d(np.asarray(u, float))
    if x.shape[0] != u.shape[0] or x.shape[1] != model.system.nx or u.shape[1] != model.system.nu:
        raise ShapeError(f"extrapolation: expected x (T, {model.system.nx}) and u (T, {model.system.nu}), "
                         f"got {x.shape}, {u.shape}")
    low, high = box.arrays
    feats = model.net.features_numpy(x, u)
    outside = (feats < low) | (feats > high)
    return Extrapolation(float(np.mean(outside.any(axis=1))),
                         {n: float(s) for n, s in zip(box.names, outside.mean(axis=0))}, int(len(x)))
