"""Training settings, the one default training and the paper's recipes: the one source of
training defaults.

This module imports neither torch nor CasADi, so the command line reads its option defaults
from here without slowing ``learnest --help``. :class:`TrainingSettings` and
:class:`NetworkSettings` are re-exported by :mod:`~learnest_codegen.learning.training` and
:mod:`~learnest_codegen.learning.network`.

* :data:`DEFAULT_TRAINING` - the one default: ``ln.train``, ``train_on_run``, ``learnest train``
  and ``learnest demo`` train with it (chosen by measurement, see ``docs/reports/training.md``).
* Recipes of the paper's experiments (``TRAINING_RECIPES``): ``paper``
  (:data:`PAPER_TRAINING` = ``TrainingSettings()``, the paper's Adam at 1e-2 for 250 epochs,
  full batch, nothing added) and ``table1_cartpole`` (:data:`TABLE1_CARTPOLE_TRAINING`, the
  cartpole Table I task's).

The measured effect of every setting is in :mod:`~learnest_codegen.learning.training`'s
docstring and the project's ``docs/reports/training.md``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from .errors import SettingsError, UnknownNameError


def _need(ok: bool, where: str, what: str, got) -> None:
    """Raise :class:`SettingsError` "``where`` must be ``what``, got ``got``" unless ``ok``."""
    if not ok:
        raise SettingsError(f"{where} must be {what}, got {got!r}")

ACTIVATIONS = ("Tanh", "Sigmoid", "ReLU", "LeakyReLU")
#: The default ``batch_size``: every training set of up to a million pairs is one batch (full
#: batch: one optimiser step per epoch).
FULL_BATCH = 1_000_000
#: The floating-point types training can run in (``TrainingSettings.precision``).
PRECISIONS = ("float32", "float64")


@dataclass(frozen=True)
class NetworkSettings:
    """Architecture of the residual MLP.

    ``layers`` counts linear layers (the paper's "2 layers, 8 hidden" is ``layers=2,
    hidden=8``: input->8->output).
    """

    layers: int = 2
    hidden: int = 8
    activation: str = "Tanh"

    def __post_init__(self) -> None:
        _need(self.layers >= 2, "NetworkSettings.layers", ">= 2 (input and output layer)", self.layers)
        _need(self.hidden >= 1, "NetworkSettings.hidden", ">= 1", self.hidden)
        if self.activation not in ACTIVATIONS:
            raise UnknownNameError(f"unknown activation {self.activation!r}; choose from {ACTIVATIONS}")

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class WarmRefinement:
    """How the refinement rounds after the first train when they start from the previous
    round's net instead of from scratch (``TrainingSettings.warm_refinement``).

    Each such round trains one net (no restarts: the first round chose the basin), started from
    the kept weights of the round before, with these settings; everything else (weight decay,
    validation, early stopping) as in the first round.

    Attributes
    ----------
    epochs : passes over the training pairs per round.
    batch_size : pairs per step (default full batch).
    learning_rate : Adam's (AdamW's) rate.
    weight_average : decay per step of the moving average of the weights; 0: off.
    """

    epochs: int = 250
    batch_size: int = FULL_BATCH
    learning_rate: float = 1e-2
    weight_average: float = 0.0

    def __post_init__(self) -> None:
        _check_optimiser(self, "WarmRefinement")


def _check_optimiser(settings, name: str) -> None:
    _need(settings.epochs >= 1, f"{name}.epochs", ">= 1", settings.epochs)
    _need(settings.batch_size >= 1, f"{name}.batch_size", ">= 1", settings.batch_size)
    _need(settings.learning_rate > 0, f"{name}.learning_rate", "> 0", settings.learning_rate)
    _need(0.0 <= settings.weight_average < 1.0, f"{name}.weight_average", "in [0, 1)",
          settings.weight_average)


@dataclass(frozen=True)
class TrainingSettings:
    """Optimisation settings; the field defaults are the paper's cartpole settings (250 epochs,
    Adam at 1e-2), full batch, nothing added (:data:`PAPER_TRAINING`). The package trains with
    :data:`DEFAULT_TRAINING` unless told otherwise: start from it, e.g.
    ``dataclasses.replace(DEFAULT_TRAINING, epochs=500)``.

    Attributes
    ----------
    epochs : passes over the training pairs.
    learning_rate : Adam's (AdamW's) rate.
    batch_size : pairs per optimiser step; at least the number of training pairs is full batch
        (the default, :data:`FULL_BATCH`). The paper's 256 (32 steps per epoch on the demo data)
        costs about 8 times as much per epoch and reaches the same loss; the Table I recipe
        trains in batches of 1024 (see ``docs/reports/training.md``).
    seed : network initialisation, mini-batch order and (full-state training) the state noise.
    network : the residual MLP's architecture.
    validation_fraction : final segment of the run held out for early stopping; 0 disables.
    refine : rounds of model-based smoothing and retraining.
    restarts : initialisations trained per round (together, as one stacked model).
    weight_decay : decoupled (AdamW) decay of every weight per step, times the rate.
    final_learning_rate : cosine annealing to this rate; ``None``: constant rate.
    weight_average : decay per optimiser step of the moving average of the weights that is
        validated and kept; 0: the weights themselves. Under full batch a step is an epoch.
    patience : stop when no restart's validation loss has improved for this many epochs;
        ``None``: run every epoch. The kept weights are the best epoch's either way, so the
        result changes only when a later epoch would have beaten it.
    refine_restarts : initialisations trained in each refinement round; ``None``: ``restarts``.
        With fewer than ``restarts``, a refinement round trains the initialisations from the
        seed that won the first round on (its basin, the measurements' choice).
    warm_refinement : the refinement rounds after the first start from the previous round's
        net with these settings (:class:`WarmRefinement`); ``None``: every round trains
        ``restarts`` nets from scratch with the settings above.
    precision : the floating-point type the net is trained in, one of :data:`PRECISIONS`;
        float32 for every recipe (the same Table I cells and demo gap closure as float64 at
        less cost, measured in ``docs/reports/training.md``). The data, the observers and the trained
        model stay float64 (the weights are cast back); only the optimisation runs in this type.
    """

    epochs: int = 250
    learning_rate: float = 1e-2
    batch_size: int = FULL_BATCH
    seed: int = 0
    network: NetworkSettings = field(default_factory=NetworkSettings)
    validation_fraction: float = 0.2
    refine: int = 0
    restarts: int = 1
    weight_decay: float = 0.0
    final_learning_rate: float | None = None
    weight_average: float = 0.0
    patience: int | None = None
    warm_refinement: WarmRefinement | None = None
    refine_restarts: int | None = None
    precision: str = "float32"

    def __post_init__(self) -> None:
        _check_optimiser(self, "TrainingSettings")
        if self.precision not in PRECISIONS:
            raise UnknownNameError(f"TrainingSettings.precision: unknown precision {self.precision!r}; "
                                   f"choose from {PRECISIONS}")
        _need(self.patience is None or self.patience >= 1, "TrainingSettings.patience", ">= 1 (or None)",
              self.patience)
        _need(0 <= self.validation_fraction < 0.9, "TrainingSettings.validation_fraction", "in [0, 0.9)",
              self.validation_fraction)
        _need(self.refine >= 0, "TrainingSettings.refine", ">= 0", self.refine)
        _need(self.restarts >= 1, "TrainingSettings.restarts", ">= 1", self.restarts)
        _need(self.refine_restarts is None or self.refine_restarts >= 1, "TrainingSettings.refine_restarts",
              ">= 1 (or None)", self.refine_restarts)
        _need(0.0 <= self.weight_decay < 1.0 / self.learning_rate, "TrainingSettings.weight_decay",
              f"in [0, 1 / learning_rate = {1.0 / self.learning_rate:g})", self.weight_decay)
        _need(self.final_learning_rate is None or 0 < self.final_learning_rate <= self.learning_rate,
              "TrainingSettings.final_learning_rate",
              f"in (0, learning_rate = {self.learning_rate:g}] or None", self.final_learning_rate)

    def to_json(self) -> dict:
        """The settings as a dict. ``weight_decay``, ``final_learning_rate``,
        ``weight_average``, ``patience``, ``warm_refinement`` and ``refine_restarts`` are left
        out when off and ``precision`` when float64, so the identities of models and sweep jobs
        trained before they existed are unchanged."""
        out = asdict(self)
        for key in ("weight_decay", "final_learning_rate", "weight_average", "patience",
                    "warm_refinement", "refine_restarts"):
            if not out[key]:
                del out[key]
        if out["precision"] == "float64":
            del out["precision"]
        return out


#: The paper's settings (Adam at 1e-2 for 250 epochs, full batch), nothing added: the field
#: defaults of :class:`TrainingSettings`.
PAPER_TRAINING = TrainingSettings()
#: The one default training: the paper's Adam at 1e-2 with the additions of
#: :mod:`~learnest_codegen.learning.training`: two refinement rounds of three initialisations each
#: (chosen by the measurement likelihood), batches of 1024 pairs with the weight average
#: 0.9606 = 0.99 ** 4 per step, weight decay 0.1, and a round stopped once no initialisation's
#: validation loss has improved for 50 epochs (the kept weights are the best epoch's either way),
#: in float32. Chosen on the floor suite (``scripts/bench_floors.py``: the cartpole demo's runs,
#: the ground robot, the README's pendulum and a DC-motor inertia-wheel pendulum, three held-out
#: cases each): every system's KNODE MHE and UKF at or within the floor (the reference default
#: that ``scripts/bench_floors.py`` names: the same recipe without patience, in float64) at less
#: than half its CPU. The full batch of one
#: initialisation costs less on the cartpole but loses 29-180 % of the MSE on three of the four
#: systems. The ablation is in ``docs/reports/training.md``.
DEFAULT_TRAINING = TrainingSettings(batch_size=1024, refine=2, restarts=3, weight_decay=0.1,
                                    weight_average=0.9606, patience=50)
#: The training of the cartpole Table I task: the paper's Adam at 1e-2 for 250 epochs with the
#: additions of :mod:`~learnest_codegen.learning.training` (each one's measured effect is
#: described there): five refinement rounds of three initialisations each, chosen by the
#: measurement likelihood, batches of 1024 pairs with the weight average 0.9606 = 0.99 ** 4 per
#: step, weight decay 0.1. Training the first round's choice alone in the later rounds
#: (``refine_restarts=1``) costs the hardest seeds 0.1-0.2 point: see ``docs/reports/training.md``.
TABLE1_CARTPOLE_TRAINING = TrainingSettings(epochs=250, batch_size=1024, refine=5, restarts=3,
                                            weight_decay=0.1, weight_average=0.9606)

TRAINING_RECIPES: dict[str, TrainingSettings] = {
    "default": DEFAULT_TRAINING, "paper": PAPER_TRAINING, "table1_cartpole": TABLE1_CARTPOLE_TRAINING,
}


def recipe(name: str) -> TrainingSettings:
    """The named training recipe (see ``TRAINING_RECIPES``)."""
    if name not in TRAINING_RECIPES:
        raise UnknownNameError(f"unknown training recipe {name!r}; choose from {sorted(TRAINING_RECIPES)}")
    return TRAINING_RECIPES[name]
