"""KNODE training (Alg. 1, phase 1).

The loss is the paper's eq. (11): the mean over consecutive pairs of
``||zeta_{i+1} - RK4_step(f_prior + Delta_theta)(zeta_i, u_i)||^2``, minimised with Adam in
the settings' ``precision`` (float32 or float64), written as the RK4 step's increment against
the observed increment ``zeta_{i+1} - zeta_i`` (taken in float64), so that float32 rounds
increments rather than states. The trained model and its directory are :mod:`.model`'s: its
weights are float64 whatever the training's precision.

Two additions to the paper's procedure, both measured on the cartpole with a free residual and
the printed eq. (13) (relative error of the learned residual against ``f_true - f_prior`` on an
unseen run):

* Early stopping on a held-out final segment of the run (``validation_fraction``). The
  observer's errors are correlated in time and with the state, and after a few dozen epochs the
  net starts fitting them instead of the physics; the held-out segment sees different errors.
  0.84 -> 0.39.
* ``refine`` rounds of model-based smoothing: the observations are recomputed by an EKF-RTS
  smoother through the current hybrid model and the net is trained again. 0.39 -> 0.30 after
  two rounds. The rounds converge slowly: the smoother only recovers part of the model's error
  (its process noise, chosen by likelihood, shrinks as the model improves), so each round
  removes part of what is left. On the cartpole Table I jobs 13 and 14 (Python UKF, unseen
  runs), rounds 0-5 closed 98.76 / 99.40 / 99.62 / 99.67 / 99.76 / 99.81 % and
  97.63 / 99.09 / 99.47 / 99.67 / 99.75 / 99.80 % of the gap, and the RMSE of the training
  states' velocities fell from 0.017-0.028 to 0.004-0.005 in steps of 10-20 %.

A system's declared mirror symmetry doubles the data: every pair is also used mirrored
(``System.residual.reflection``). On the cartpole this took the worst Table I job from 90.5 % to 99.8 %
of the UKF gap closed: its training run had swung one way harder than the other.

And an optional decoupled weight decay (``weight_decay``, AdamW): on the cartpole it takes the
net trained on noisy full states from 99.3-99.9 % of the UKF gap closed to 99.9-100 % on
unseen runs. Ten seconds of data leave many nets that fit the training run equally well; the
decay picks the smallest, which is also the smoothest and extrapolates least.

How it runs (speed, not results): the ``restarts`` initialisations of a round train together as
one stacked model (:class:`~learnest_codegen.learning.network.StackedMLP`, one batched matrix product per
layer), each on its own mini-batch order, so each follows exactly the path it would follow
alone (in float32 to its rounding: the batched products round differently); the hybrid model
shares the prior's evaluation between the derivative, the net's features and its input
correction (:meth:`~learnest_codegen.learning.network.ResidualNet.hybrid`); the
recorded training loss of an epoch (``loss_history``) is the mean of its steps' losses, which
come free with the steps. The first RK4 stage's prior and features at the data are computed
once per training (:meth:`~learnest_codegen.learning.network.ResidualNet.start_t`), and a full
batch carries the validation pairs in its forward pass: the weights an epoch ends with are
those the next step starts from, so that pass gives the previous epoch's validation loss (the
last epoch's is a pass of its own). Both give the same numbers up to rounding; see
``docs/reports/training.md``.

Two optional ways to quiet the last iterates of Adam at a constant rate 1e-2: on the 15
cartpole Table I jobs the last epoch's validation loss sat 0-140 % (median 34 %) above the best
epoch's.

* ``weight_average``: the net validated and kept is the exponential moving average of the
  weights (decay per step). With 0.99 the cartpole's UKF gap closure moved by +0.32, +0.05,
  +0.11, -0.09, -0.04 and +0.13 point on seeds 14, 12, 11, 13, 0 and 10 (Table I jobs, Python
  UKF). The cartpole Table I task uses it.
* ``final_learning_rate``: cosine annealing of the rate. To 1e-4 on seeds 14, 12, 11 and 13:
  +0.38, +0.05, -0.06 and -0.03 point; with the average as well it added nothing. Not used.

Two ways to spend fewer epochs:

* ``patience``: stop once no restart's validation loss has improved for that many epochs. The
  weights kept are the best epoch's either way. The default uses 50: in batches of 1024 with
  the weight average the cartpole demo's first round peaks at epoch 16 of 250, and stopping
  50 epochs after the peak leaves the demo's model as it was at a third of the epochs. The
  ground-robot Table I task uses 500 of its 10000 epochs: its partial-measurement nets peak
  after 45-1033 epochs.
* ``warm_refinement``: the refinement rounds after the first train one net from the previous
  round's (its weights and input scaling) instead of ``restarts`` nets from scratch. It is
  2-3x cheaper per job, but on cartpole Table I job 13 it closed 98.6 % (full batch, rate
  1e-2), 99.60 % (full batch, 3e-3, 100 epochs) and 99.64 % (batches of 1024, 2e-3, 100
  epochs) of the UKF gap, against 99.85 % from scratch: a restarted Adam pushes the net out of
  the previous round's optimum, and a gentle one hardly moves it. Not used.

Length: the training loop and the settings it carries (restarts, mini-batches, validation,
weight average, rate schedule, patience, warm start) are one procedure; split up, each part
would need the loop's state passed back and forth.
"""

from __future__ import annotations

import copy
import math
import sys
import time
from dataclasses import replace
from typing import Callable, Sequence

import numpy as np
import torch
from tqdm.auto import tqdm

from ..config import DEFAULT_TRAINING, TrainingSettings
from ..data import Run, check_sampling
from ..errors import DataError, SettingsError, ShapeError
from ..integrators import rk4_increment, rk4_step
from ..systems import System
from .model import META, WEIGHTS, TrainedModel, data_hash, load_model, make_net, residual_structure
from .network import ResidualNet, StackedMLP, StartT
from .pairs import segment_pairs
from .ranges import RANGES_KEY, record_ranges
from .source import KEY as SOURCE_KEY
from .source import system_source

__all__ = ["DEFAULT_TRAINING", "META", "WEIGHTS", "TrainingSettings", "TrainedModel",
           "data_hash", "load_model", "make_net", "one_step_loss", "residual_structure", "train",
           "train_on_run"]


def one_step_loss(system: System, net: ResidualNet, zeta: torch.Tensor, u: torch.Tensor,
                  zeta_next: torch.Tensor, dt: float) -> torch.Tensor:
    """Eq. (11): mean squared one-step RK4 prediction error of the hybrid model."""
    hybrid = lambda x, v: system.f(x, v) + net(x, v)  # noqa: E731
    pred = rk4_step(hybrid, zeta, u, dt)
    return ((pred - zeta_next) ** 2).sum(dim=-1).mean()


def train(system: System, zeta: np.ndarray, u: np.ndarray, dt: float,
          settings: TrainingSettings = DEFAULT_TRAINING, *, observer: str = "",
          progress: bool = True, score: Callable[[TrainedModel], float] | None = None,
          init: TrainedModel | None = None, breaks: Sequence[int] = ()) -> TrainedModel:
    """Train ``Delta_theta`` on state observations ``zeta (M, nx)`` and inputs ``u (M, nu)``.

    ``init`` starts the training from that model's net (its weights and input scaling) instead
    of a fresh initialisation; it needs ``settings.restarts == 1``.

    ``breaks`` (sample indices) mark where ``zeta`` and ``u`` join one recording to the next:
    no pair spans a break, and each recording holds out its own final segment for validation
    (:func:`~learnest_codegen.learning.pairs.segment_pairs`;
    :func:`~learnest_codegen.learning.runs.train_on_runs` trains on several recordings this
    way). ``model.json`` records the range of the net's inputs over ``zeta`` and ``u``
    (:mod:`.ranges`).

    With ``settings.restarts > 1`` the net is trained from that many initialisations (seeds
    ``seed, seed + 1, ...``) and the one with the lowest validation loss is kept; ``model.json``
    lists every restart's validation loss. A bad local optimum shows there: on the cartpole one
    of five initialisations closed 80 % of the gap instead of 95-98 %, at a validation loss
    six times the others'. The initialisations train together, as one stacked model
    (:class:`~learnest_codegen.learning.network.StackedMLP`); each follows exactly the path it would
    follow alone (its own initialisation and mini-batch order; in float32 to its rounding).

    A system that declares a mirror symmetry (:meth:`~learnest_codegen.systems.System.reflection_signs`)
    is trained on every pair and its mirror image, the validation segment split off first.

    ``score(model)`` (higher is better) replaces the validation loss as the criterion; its
    values are stored as ``restart_score``. The validation loss cannot tell initialisations
    apart when ``zeta`` is noisy: on one cartpole run the kinematic observer's states gave
    validation losses within 4 % of each other for nets closing 53 %, 90 % and 96 % of the gap.
    """
    zeta, u = np.asarray(zeta, float), np.asarray(u, float)
    if zeta.ndim != 2 or zeta.shape[1] != system.nx or u.shape != (zeta.shape[0], system.nu):
        raise ShapeError(f"train: expected zeta (M, {system.nx}) and u (M, {system.nu}), "
                         f"got {zeta.shape}, {u.shape}")
    if not (np.isfinite(zeta).all() and np.isfinite(u).all()):
        raise DataError("train: zeta and u must be finite (a state observation or an input is NaN or "
                        "infinite)")
    if init is not None and settings.restarts != 1:
        raise SettingsError(f"train: a warm start (init) trains one net; got restarts={settings.restarts}")
    start = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny operations: a second thread only spins (37x slower under load)
    try:
        models = _train_stacked(system, zeta, u, dt, settings, observer, progress, init, tuple(breaks))
    finally:
        torch.set_num_threads(threads)
    valid = [min(m.meta["validation_history"]) for m in models]
    scores = [float(score(m)) for m in models] if score is not None and len(models) > 1 else None
    best = models[int(np.argmax(scores)) if scores else int(np.argmin(valid))]
    best.meta.update(training=settings.to_json(), restart_seed=best.meta["training"]["seed"],
                     restart_validation=valid, train_seconds=time.perf_counter() - start)
    best.meta[SOURCE_KEY] = system_source(system)  # a separate key: where the system comes from
    best.meta[RANGES_KEY] = record_ranges(best.net, system, zeta, u)
    if scores:
        best.meta["restart_score"] = scores
    return best


def _pair_sets(system: System, zeta: np.ndarray, u: np.ndarray, settings: TrainingSettings,
               breaks: tuple[int, ...] = ()):
    """All pairs, and the training and validation pairs (each with its mirror image when the
    system declares a symmetry; the validation segment is split off first: no leak)."""
    if breaks:
        pairs, train_set, valid_set = segment_pairs(zeta, u, breaks, settings.validation_fraction)
    else:
        pairs = [torch.as_tensor(a) for a in (zeta[:-1], u[:-1], zeta[1:])]
        n_train = len(zeta) - 1 - int(settings.validation_fraction * (len(zeta) - 1))
        train_set = [a[:n_train] for a in pairs]
        valid_set = [a[n_train:] for a in pairs] if n_train < len(zeta) - 1 else train_set
    signs = system.reflection_signs()
    if signs is not None:
        sx, su = (torch.as_tensor(s) for s in signs)
        held_out = valid_set is not train_set
        train_set, valid_set = ([torch.cat([z, z * sx]), torch.cat([v, v * su]), torch.cat([zn, zn * sx])]
                                for z, v, zn in (train_set, valid_set))
        valid_set = valid_set if held_out else train_set  # no validation segment: still one set
    return pairs, train_set, valid_set


def _stacked_loss(system: System, net: ResidualNet, mlp: StackedMLP, zeta: torch.Tensor,
                  u: torch.Tensor, step: torch.Tensor, dt: float) -> torch.Tensor:
    """Eq. (11) of every stacked member ``(R,)``; the pairs ``(zeta, u, step)`` (``step`` the
    observed increment ``zeta_next - zeta``, see :func:`_training_pairs`) are components first,
    ``(n, B)`` shared by all members or ``(n, R, B)`` one batch per member (the layout of
    :meth:`~learnest_codegen.learning.network.ResidualNet.derivative_t`)."""
    if zeta.dim() == 2:
        zeta, u, step = _expanded(len(mlp.weights[0]), zeta, u, step)
    return _loss_of(net, mlp, dt, zeta, u, step)


def _training_pairs(pairs: list, dtype: torch.dtype) -> list:
    """Pairs ``(zeta, u, zeta_next)`` ``(B, n)`` as training uses them: components first and
    ``zeta_next`` replaced by the observed increment ``zeta_next - zeta``, taken in float64 and
    only then cast to ``dtype``. The loss compares increments with increments: in float32 the
    rounding of a state (1e-7 of its size) would otherwise sit in every residual."""
    zeta, u, zeta_next = pairs
    return [a.T.to(dtype).contiguous() for a in (zeta, u, zeta_next - zeta)]


def _expanded(members: int, zeta: torch.Tensor, u: torch.Tensor, step: torch.Tensor):
    """Pairs ``(n, B)`` shared by ``members`` as ``(n, members, B)`` (views)."""
    zeta, u = (a[:, None].expand(a.shape[0], members, a.shape[1]) for a in (zeta, u))
    return zeta, u, step[:, None]


def _start(net: ResidualNet, members: int, zeta: torch.Tensor, u: torch.Tensor,
           step: torch.Tensor) -> tuple:
    """Pairs ``(n, B)`` with what the first RK4 stage computes at them before the weights
    enter (:meth:`~learnest_codegen.learning.network.ResidualNet.start_t`): the arguments of
    :func:`_loss_of` after ``dt``, computed once for every epoch of a full batch."""
    zeta, u, step = _expanded(members, zeta, u, step)
    with torch.no_grad():
        return zeta, u, step, net.start_t(zeta, u)


def _loss_of(net: ResidualNet, mlp: StackedMLP, dt: float, zeta: torch.Tensor, u: torch.Tensor,
             step: torch.Tensor, start: StartT | None = None) -> torch.Tensor:
    """:func:`_stacked_loss` on pairs ``(n, R, B)``; ``start`` (:func:`_start`) is taken for the
    first RK4 stage, which is at ``zeta`` itself."""
    return _pair_errors(net, mlp, dt, zeta, u, step, start).mean(dim=-1)


def _pair_errors(net: ResidualNet, mlp: StackedMLP, dt: float, zeta: torch.Tensor, u: torch.Tensor,
                 step: torch.Tensor, start: StartT | None = None) -> torch.Tensor:
    """Every pair's squared one-step error ``(R, B)``, the terms of :func:`_loss_of`'s mean: the
    RK4 step's increment against the observed one (eq. (11) with ``zeta`` taken from both)."""

    def f(x, v):
        return net.derivative_t(x, v, mlp, start if x is zeta else None)

    return ((rk4_increment(f, zeta, u, dt) - step) ** 2).sum(dim=0)


def _train_stacked(system: System, zeta: np.ndarray, u: np.ndarray, dt: float,
                   settings: TrainingSettings, observer: str, progress: bool,
                   init: TrainedModel | None = None, breaks: tuple[int, ...] = ()) -> list[TrainedModel]:
    """Train the ``settings.restarts`` initialisations together; one model per restart."""
    members = [replace(settings, seed=settings.seed + r, restarts=1) for r in range(settings.restarts)]
    nets = []
    for member in members:
        torch.manual_seed(member.seed)
        nets.append(make_net(system, settings.network))
        if init is not None:  # its weights and the input scaling they were trained with
            nets[-1].load_state_dict(init.net.state_dict())
    net = nets[0]  # the structure (features, scaling, channels); the weights live in `mlp`
    signs = system.reflection_signs()
    if init is None:  # a warm start keeps the scaling its weights were trained with
        if signs is None:
            net.set_input_scaling(zeta, u)
        else:
            net.set_input_scaling(np.vstack([zeta, zeta * signs[0]]), np.vstack([u, u * signs[1]]))
    dtype = getattr(torch, settings.precision)
    pairs, train_set, valid_set = _pair_sets(system, zeta, u, settings, breaks)
    n_train, held_out = len(train_set[0]), valid_set is not train_set
    train_set, valid_set = (_training_pairs(pairs_, dtype) for pairs_ in (train_set, valid_set))
    mlp = StackedMLP([n.mlp for n in nets]).to(dtype)
    net_t = net  # what the loss evaluates: the net's scaling and structure in `dtype`
    if dtype != torch.float64:
        with torch.random.fork_rng(devices=[]):  # its initial weights are discarded: no draw counts
            net_t = make_net(system, settings.network)
        net_t.load_state_dict(net.state_dict())
        net_t.to(dtype)
    optimiser = FusedAdam(mlp.parameters(), settings.learning_rate, settings.weight_decay)
    kept = mlp  # the weights validated and kept; with weight_average a copy holding the average
    if settings.weight_average:
        kept = copy.deepcopy(mlp).requires_grad_(False)
    means, weights = (list(kept.parameters()), list(mlp.parameters())) if kept is not mlp else ([], [])
    generators = [torch.Generator().manual_seed(m.seed) for m in members]
    full_batch = settings.batch_size >= n_train
    # One full batch validated on the weights it trains: an epoch's validation pairs ride along
    # in the next epoch's forward pass, which starts from the weights the epoch ended with (one
    # pass over train and validation pairs instead of two; the last epoch's is a pass of its own).
    joint = full_batch and held_out and kept is mlp
    # the first RK4 stage's prior and features at the data: the same every epoch, computed once
    train_start = None
    if joint:
        train_start = _start(net_t, len(members), *(torch.cat(ab, dim=1) for ab in zip(train_set, valid_set)))
    elif full_batch:
        train_start = _start(net_t, len(members), *train_set)
    valid_start = _start(net_t, len(members), *valid_set)
    start, history, valid_history = time.perf_counter(), [], []
    best_loss = torch.full((len(members),), math.inf, dtype=torch.float64)
    kept_params = list(kept.parameters())
    best_state = [p.detach().clone() for p in kept_params]
    best_epoch = torch.zeros(len(members), dtype=torch.long)

    def validate(epoch: int, loss: torch.Tensor) -> bool:
        """Record ``epoch``'s validation loss (``kept`` holds its weights); True when
        ``patience`` ends the training there."""
        nonlocal best_loss
        valid_history.append(loss)
        better = loss < best_loss
        if better.any():
            best_loss = torch.where(better, loss, best_loss)
            best_epoch[better] = epoch
            for saved, p in zip(best_state, kept_params):
                saved.copy_(torch.where(better.view(-1, *[1] * (p.dim() - 1)), p, saved))
        return settings.patience is not None and epoch - int(best_epoch.max()) >= settings.patience

    # quiet unless it draws on a terminal: redirected to a log, a bar writes a line per refresh
    bar = tqdm(range(settings.epochs), desc=f"training {system.name}", disable=None if progress else True,
               unit="epoch")
    stopped = False
    for epoch in bar:
        if full_batch:
            batches = [None]
        else:  # every member its own order, as when trained alone; gathered once per epoch
            orders = torch.cat([torch.randperm(n_train, generator=g) for g in generators])
            shuffled = [a.index_select(1, orders).view(len(a), len(members), n_train) for a in train_set]
            batches = [[a[..., k:k + settings.batch_size] for a in shuffled]
                       for k in range(0, n_train, settings.batch_size)]
        epoch_loss = torch.zeros(len(members), dtype=torch.float64)
        for batch in batches:
            optimiser.zero_grad()
            if joint:
                errors = _pair_errors(net_t, mlp, dt, *train_start)
                loss = errors[:, :n_train].mean(dim=-1)
                if epoch:  # the weights the last epoch ended with: its validation loss
                    with torch.no_grad():
                        stopped = validate(epoch - 1, errors[:, n_train:].mean(dim=-1))
                    if stopped:
                        break  # no restart improved for `patience` epochs: no further step
            elif batch is None:
                loss = _loss_of(net_t, mlp, dt, *train_start)
            else:
                loss = _stacked_loss(system, net_t, mlp, *batch, dt)
            loss.sum().backward()
            optimiser.step()
            with torch.no_grad():
                epoch_loss += loss.detach() * (n_train if batch is None else batch[0].shape[-1])
                if means:
                    torch._foreach_lerp_(means, weights, 1.0 - settings.weight_average)
        if stopped:
            break
        with torch.no_grad():  # the training loss comes free with the steps
            history.append(epoch_loss / n_train)
            if not joint:
                stopped = validate(epoch, _loss_of(net_t, kept, dt, *valid_start))
        if not bar.disable:
            valid = f"{float(valid_history[-1].min()):.3e}" if valid_history else "-"
            bar.set_postfix(loss=f"{float(history[-1].min()):.3e}", valid=valid)
        if settings.final_learning_rate is not None:
            optimiser.lr = _cosine_rate(settings, epoch + 1)
        if stopped:
            break  # no restart improved for `patience` epochs
    if joint and history and not stopped:  # the last epoch's validation: no step follows it
        with torch.no_grad():
            validate(len(history) - 1, _loss_of(net_t, kept, dt, *valid_start))
    with torch.no_grad():
        for saved, p in zip(best_state, kept.parameters()):
            p.copy_(saved)
    seconds = time.perf_counter() - start
    history, valid_history = torch.stack(history).T.tolist(), torch.stack(valid_history).T.tolist()
    models = []
    for r, member in enumerate(members):
        trained = make_net(system, settings.network)
        # the weights in float64 whatever the training's precision (load_state_dict casts them)
        trained.load_state_dict({**net.state_dict(), **kept.member_state(r)})
        with torch.no_grad():
            final_loss = float(one_step_loss(system, trained, *pairs, dt))
            prior_loss = float(one_step_loss(system, _ZeroNet(system), *pairs, dt))
        meta = {
            "system": system.name, "nx": system.nx, "nu": system.nu, "dt": dt,
            "network": settings.network.to_json(), "training": member.to_json(),
            "residual": residual_structure(system),
            "observer": observer, "data_hash": data_hash(zeta, u), "samples": int(zeta.shape[0]),
            "final_loss": final_loss, "prior_loss": prior_loss, "best_epoch": int(best_epoch[r]),
            "loss_history": history[r], "validation_history": valid_history[r],
            "train_seconds": seconds, "torch_version": torch.__version__,
        }
        models.append(TrainedModel(system, trained, meta))
    return models


class FusedAdam:
    """Adam, or AdamW with ``weight_decay``, as ``torch.optim.Adam(..., fused=True)`` (or
    ``AdamW``) steps: the same fused CPU kernel (``torch._fused_adam_`` / ``_fused_adamw_``) on the
    same state, so the same iterates, called directly. ``torch.optim``'s optimisers import torch's
    compiler stack (``torch._dynamo``) on their first use, about 2 s of CPU in a fresh process
    that a training of 250 small steps would otherwise pay once more than its epochs."""

    def __init__(self, params, lr: float, weight_decay: float = 0.0, betas=(0.9, 0.999), eps: float = 1e-8):
        self.params = list(params)
        self.lr, self.weight_decay, self.betas, self.eps = lr, weight_decay, betas, eps
        self.exp_avgs = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.exp_avg_sqs = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.steps = [torch.zeros((), dtype=torch.float32) for _ in self.params]

    def zero_grad(self) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        torch._foreach_add_(self.steps, 1)
        kernel = torch._fused_adamw_ if self.weight_decay else torch._fused_adam_
        kernel(self.params, [p.grad for p in self.params], self.exp_avgs, self.exp_avg_sqs, [], self.steps,
               amsgrad=False, lr=self.lr, beta1=self.betas[0], beta2=self.betas[1],
               weight_decay=self.weight_decay, eps=self.eps, maximize=False, grad_scale=None, found_inf=None)


def _cosine_rate(settings: TrainingSettings, epoch: int) -> float:
    """The rate of ``epoch`` under cosine annealing from ``learning_rate`` to
    ``final_learning_rate`` over ``epochs - 1`` epochs (the closed form of
    ``torch.optim.lr_scheduler.CosineAnnealingLR``)."""
    lr0, lr1, span = settings.learning_rate, settings.final_learning_rate, max(settings.epochs - 1, 1)
    return lr1 + (lr0 - lr1) * (1 + math.cos(math.pi * epoch / span)) / 2


class _ZeroNet(torch.nn.Module):
    """Delta = 0: the prior's own loss, reported next to the trained loss."""

    def __init__(self, system: System):
        super().__init__()
        self.nx = system.nx

    def forward(self, x, u):
        return torch.zeros_like(x)


def _said(progress: bool, step: int, steps: int, what: str, model: TrainedModel, start: float) -> None:
    """One line on stderr per training of :func:`train_on_run` (the first, then each refinement
    round), when ``progress``: which step, what it trained on, where it stopped, the time so far."""
    if progress:
        meta = model.meta
        print(f"[{step}/{steps}] {what}: best epoch {meta['best_epoch']}, validation loss "
              f"{min(meta['validation_history']):.3e}, {time.perf_counter() - start:.1f} s",
              file=sys.stderr, flush=True)


#: The largest RMS, in measurement-noise deviations, of the outputs of smoothed states that still
#: describe the run: a working smoother fits its measurements to about one deviation (the
#: quadrotor's: 0.93-0.97); a diverged one misses them by orders of magnitude.
SMOOTHED_OUTPUT_RMS_MAX = 10.0


def _diverged(zeta: np.ndarray, run: Run, system: System) -> str:
    """Why the smoothed states ``zeta`` cannot be trained on, or ``""``: they are not finite, or
    their outputs miss the run's measurements by more than :data:`SMOOTHED_OUTPUT_RMS_MAX`
    noise deviations (RMS over the outputs measured)."""
    if not np.isfinite(zeta).all():
        return "states not finite"
    std = np.asarray(system.noise.measurement_std, float)
    with np.errstate(all="ignore"):
        y_hat = np.asarray(system.h(zeta, run.u), float)  # every sample at once, as simulate does
        r = ((y_hat - run.y) / np.where(std > 0, std, 1.0))[:, std > 0]
        rms = float(np.sqrt(np.nanmean(r ** 2))) if np.isfinite(run.y[:, std > 0]).any() else 0.0
    if not rms <= SMOOTHED_OUTPUT_RMS_MAX:
        return f"its outputs miss the measurements by {rms:.3g} noise deviations RMS"
    return ""


def _finite(model: TrainedModel) -> bool:
    """Whether the net's weights, its input scaling and its final loss are all finite."""
    tensors = [p.detach() for p in model.net.parameters()] + [b.detach() for b in model.net.buffers()]
    return (all(bool(torch.isfinite(t).all()) for t in tensors)
            and bool(np.isfinite(model.meta.get("final_loss", 0.0))))


def _refinement_stopped(model: TrainedModel, k: int, rounds: int, why: str, progress: bool) -> TrainedModel:
    """``model`` (the last sound round's) with the reason the refinement stopped before round
    ``k + 1`` of ``rounds`` recorded in its metadata and said on stderr."""
    text = f"refinement round {k + 1} of {rounds} not used: {why}; the model of the round before is kept"
    model.meta["refinement_stopped"] = text
    if progress:
        print(text, file=sys.stderr, flush=True)
    return model


def train_on_run(run: Run, system: System, settings: TrainingSettings = DEFAULT_TRAINING, *,
                 observer: str | None = None, full_state: bool = False,
                 progress: bool = True) -> TrainedModel:
    """Alg. 1 phase 1 on one run: observe (or take noisy full states), then train.

    ``observer`` defaults to :func:`~learnest_codegen.observers.choose_observer`'s choice (said
    on stderr when ``progress``, and stored as ``observer_choice``). With ``progress`` each
    training (the first, then one per refinement round) also says on stderr, in one line, where
    it stopped and the time so far. Through an observer, restarts
    are chosen by the EKF innovation likelihood of the run's measurements
    (:func:`~learnest_codegen.observers.innovation_loglik`), not by the validation loss on the
    observer's states.

    A refinement round whose smoother diverged through the last net (states not finite, or
    outputs more than :data:`SMOOTHED_OUTPUT_RMS_MAX` noise deviations RMS from the
    measurements) or whose net is not finite ends the refinement: the model of the round
    before is returned, the reason in ``meta["refinement_stopped"]`` and on stderr.
    """
    check_sampling(run, system.dt, f"train_on_run({system.name})")
    start = time.perf_counter()
    from ..observers import ekf_rts, innovation_loglik, observe, smooth_states
    from ..simulation import noisy_states

    score, choice = None, None
    if not full_state and settings.restarts > 1:
        score = lambda m: innovation_loglik(run, system, m.net.casadi)  # noqa: E731

    if full_state:  # every state measured with noise.state_std, smoothed state by state
        noisy = noisy_states(run, system, settings.seed)
        zeta, source = smooth_states(noisy, run.dt, system.noise.state_std), "full_state+rts"
    else:
        observations = observe(run, system, observer)
        zeta, source = observations.zeta, observations.method
        choice = observations.info.get("chosen_because")
        if choice and progress:  # a choice the caller did not make: say which
            print(f"pre-training observer: {source} ({choice})", file=sys.stderr)
    rounds = 0 if full_state else settings.refine
    model = train(system, zeta, run.u, run.dt, settings, observer=source, progress=progress, score=score)
    _said(progress, 1, rounds + 1, f"trained on the {source} states", model, start)
    warm = settings.warm_refinement
    round_settings, round_score = settings, score
    if settings.refine_restarts is not None and settings.refine_restarts < settings.restarts:
        # the later rounds train fewer initialisations, from the seed the first round chose
        round_settings = replace(settings, restarts=settings.refine_restarts, seed=model.meta["restart_seed"])
        round_score = score if settings.refine_restarts > 1 else None
    for k in range(rounds):
        zeta = ekf_rts(run, system, residual=model.net.casadi).zeta
        round_observer = f"{source}+ekf_rts*{k + 1}"
        why = _diverged(zeta, run, system)
        if why:
            # The smoother diverged through the last net (it extrapolates where the smoother
            # wanders): no later round can use these states, so the last model stands.
            model = _refinement_stopped(model, k, rounds, f"the EKF-RTS through the model diverged ({why})",
                                        progress)
            break
        previous = model
        if warm is None:  # every round from scratch, with the restarts
            model = train(system, zeta, run.u, run.dt, round_settings, observer=round_observer,
                          progress=progress, score=round_score)
            model.meta["training"] = settings.to_json()
        else:  # one net, from the previous round's
            first = {key: model.meta[key] for key in ("restart_seed", "restart_validation", "restart_score")
                     if key in model.meta}  # the first round's choice of initialisation
            model = train(system, zeta, run.u, run.dt,
                          replace(settings, epochs=warm.epochs, batch_size=warm.batch_size,
                                  learning_rate=warm.learning_rate, weight_average=warm.weight_average,
                                  restarts=1, warm_refinement=None),
                          observer=round_observer, progress=progress, init=model)
            model.meta.update(first, training=settings.to_json())
        if not _finite(model):
            model = _refinement_stopped(previous, k, rounds, "its net is not finite", progress)
            break
        _said(progress, k + 2, rounds + 1, "smoothed through the model (EKF-RTS) and retrained", model, start)
    model.meta["train_seconds"] = time.perf_counter() - start  # observers and all rounds
    if choice:
        model.meta["observer_choice"] = choice
    return model
