"""Training on several recordings at once (a folder of runs).

One recording covers a narrow part of what a model meets in use: a flight sees one battery's
voltage range, one speed, one shape. :func:`train_on_runs` turns every recording into state
observations on its own (an observer never smooths across the join of two recordings), joins
them, and trains one net on all their consecutive pairs: no pair spans a join, and every
recording holds out its own final segment for early stopping (:func:`segment_pairs`), so the
validation loss weighs each recording as its share of the data.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Sequence

import numpy as np
import torch

from ..config import TrainingSettings
from ..data import Run, check_sampling
from ..errors import DataError, SettingsError
from ..systems import System
from .pairs import segment_pairs
from .source import KEY as SOURCE_KEY
from .source import system_source

__all__ = ["train_on_runs"]


def train_on_runs(runs: Sequence[Run], system: System, settings: TrainingSettings = TrainingSettings(), *,
                  names: Sequence[str] | None = None, observer: str | None = None,
                  observer_system: System | None = None, observations: Sequence[np.ndarray] | None = None,
                  fit_prior: Sequence[str] = (), start_at_prior: bool = False,
                  net_must_beat_prior: bool = False, net: bool = True, progress: bool = True):
    """Train one KNODE residual on several recordings (Alg. 1 phase 1 on each, one net for all).

    Parameters
    ----------
    runs : the recordings, each sampled at ``system.dt``.
    system : the system whose residual is trained (its prior may hold grey-box physics).
    settings : as :func:`~learnest_codegen.learning.training.train_on_run`; refinement rounds
        smooth every recording again through the current hybrid model.
    names : one name per recording, stored in ``model.json`` (``runs``).
    observer : the pre-training observer (default: ``observer_system``'s ``default_observer``).
    observer_system : the system the observer runs on (default ``system``). A grey-box prior
        that is not linear cannot run ``linear_rts``; its linear base system can.
    observations : the observer's states of each recording, ``(T_i, nx)``, when already
        computed (a study that trains on many subsets of the same recordings observes each
        once); ``observer`` then only names them.
    fit_prior : prior parameters of ``system`` to fit by least squares on the observations
        before the net is trained (:func:`~learnest_codegen.learning.prior_fit.fit_linear_params`):
        the grey-box route. The model's system holds the fitted values and ``model.json`` stores
        them (``prior_params``) beside ``system`` as given (``system_source``: a built-in by
        name), so that loading the model needs no system; refinement rounds keep them.
    start_at_prior : start the net with a zero output layer, so training starts from the prior
        itself (``Delta = 0``) rather than from a random residual; early stopping after a few
        epochs then keeps a small learned correction, not mostly the initialisation. Needs
        ``settings.restarts == 1``.
    net : ``False`` trains no net: the model is the fitted prior with ``Delta = 0`` (a net of
        the usual structure and input scaling with a zero output layer, so it exports, clamps
        and reports its training range like any other). Needs ``fit_prior``.
    net_must_beat_prior : keep the net only if its validation loss is below the prior's alone
        (``Delta = 0``); otherwise its output layer is zeroed, so the model is the prior
        (``model.json``: ``net_kept``, ``prior_validation_loss``). Early stopping picks the best
        epoch, but every epoch can be worse on held-out data than no net at all: then a net
        stopped after a step or two is mostly its random initialisation.

    Returns
    -------
    TrainedModel, with ``runs`` and ``run_samples`` in its metadata.
    """
    from ..observers import ekf_rts, innovation_loglik, observe
    from .training import train

    if not runs:
        raise DataError("train_on_runs: no recordings to train on")
    names = list(names) if names is not None else [f"run{i}" for i in range(len(runs))]
    if len(names) != len(runs):
        raise DataError(f"train_on_runs: {len(runs)} recordings but {len(names)} names")
    for name, run in zip(names, runs):
        check_sampling(run, system.dt, f"train_on_runs({system.name}, {name})")
    base = observer_system or system
    observer = observer or base.default_observer
    start = time.perf_counter()
    if observations is None:
        zetas = [observe(run, base, observer).zeta for run in runs]
    else:
        zetas = [np.asarray(z, float) for z in observations]
        if [z.shape for z in zetas] != [(len(run), system.nx) for run in runs]:
            raise DataError(f"train_on_runs: observations of shapes {[z.shape for z in zetas]} do not "
                            f"match the recordings' (T, {system.nx})")
    u = np.vstack([run.u for run in runs])
    breaks = tuple(int(b) for b in np.cumsum([len(run) for run in runs])[:-1])
    dt = float(system.dt)
    # the model names the system as given (a built-in by name, a file by path); the fitted
    # parameters are stored beside it and applied again when it is loaded
    source = system_source(system)
    fitted = {}
    if fit_prior:
        from .prior_fit import fit_linear_params, fitted_system

        fitted = fit_linear_params(system, fit_prior, zetas, [run.u for run in runs], dt)
        system = fitted_system(system, fitted)
    score = None
    if settings.restarts > 1:
        score = lambda m: sum(innovation_loglik(run, system, m.net.casadi) for run in runs)  # noqa: E731
    if not net:
        if not fitted:
            raise SettingsError("train_on_runs: a model without a net needs fit_prior (else it is the prior)")
        model = _prior_only(system, settings, np.vstack(zetas), u, breaks, observer)
        model.meta.update(runs=names, run_samples=[len(run) for run in runs], prior_params=fitted,
                          net_kept=False, train_seconds=time.perf_counter() - start)
        model.meta[SOURCE_KEY] = source
        return model
    init = None
    if start_at_prior:
        if settings.restarts != 1:
            raise SettingsError(f"train_on_runs: start_at_prior trains one net; got restarts="
                             f"{settings.restarts}")
        init = _prior_start(system, settings, np.vstack(zetas), u)
    model = train(system, np.vstack(zetas), u, dt, settings, observer=observer, progress=progress,
                  score=score, breaks=breaks, init=init)
    warm = settings.warm_refinement
    for k in range(settings.refine):
        zetas = [ekf_rts(run, system, residual=model.net.casadi).zeta for run in runs]
        label = f"{observer}+ekf_rts*{k + 1}"
        if warm is None:
            model = train(system, np.vstack(zetas), u, dt, settings, observer=label, progress=progress,
                          score=score, breaks=breaks)
        else:
            chosen = replace(settings, epochs=warm.epochs, batch_size=warm.batch_size,
                             learning_rate=warm.learning_rate, weight_average=warm.weight_average,
                             restarts=1, warm_refinement=None)
            model = train(system, np.vstack(zetas), u, dt, chosen, observer=label, progress=progress,
                          init=model, breaks=breaks)
            model.meta["training"] = settings.to_json()
    model.meta.update(runs=names, run_samples=[len(run) for run in runs],
                      train_seconds=time.perf_counter() - start)
    if fitted:
        model.meta["prior_params"] = fitted
    model.meta[SOURCE_KEY] = source
    if net_must_beat_prior:
        _check_against_prior(model, system, np.vstack(zetas), u, breaks, settings.validation_fraction)
    return model


def _prior_start(system: System, settings: TrainingSettings, zeta: np.ndarray, u: np.ndarray):
    """A net with the training data's input scaling and a zero output layer: ``Delta = 0``."""
    from .model import TrainedModel, make_net

    torch.manual_seed(settings.seed)
    net = make_net(system, settings.network)
    signs = system.reflection_signs()
    if signs is None:
        net.set_input_scaling(zeta, u)
    else:
        net.set_input_scaling(np.vstack([zeta, zeta * signs[0]]), np.vstack([u, u * signs[1]]))
    with torch.no_grad():
        net.mlp.output_layer.weight.zero_()
        net.mlp.output_layer.bias.zero_()
    return TrainedModel(system, net, {})


def _prior_only(system: System, settings: TrainingSettings, zeta: np.ndarray, u: np.ndarray,
                breaks: tuple[int, ...], observer: str):
    """The fitted prior as a trained model: a zero-output net and the metadata of a training."""
    from .model import data_hash, residual_structure
    from .ranges import RANGES_KEY, record_ranges
    from .training import one_step_loss

    model = _prior_start(system, settings, zeta, u)
    pairs = segment_pairs(zeta, u, breaks, 0.0)[0] if breaks else [
        torch.as_tensor(a) for a in (zeta[:-1], u[:-1], zeta[1:])]
    with torch.no_grad():
        loss = float(one_step_loss(system, model.net, *pairs, system.dt))
    model.meta.update({
        "system": system.name, "nx": system.nx, "nu": system.nu, "dt": float(system.dt),
        "network": settings.network.to_json(), "training": settings.to_json(),
        "residual": residual_structure(system), "observer": observer, "data_hash": data_hash(zeta, u),
        "samples": int(zeta.shape[0]), "final_loss": loss, "prior_loss": loss, "best_epoch": 0,
        "loss_history": [], "validation_history": [], "torch_version": torch.__version__,
        RANGES_KEY: record_ranges(model.net, system, zeta, u)})
    return model


def _check_against_prior(model, system: System, zeta: np.ndarray, u: np.ndarray, breaks: tuple[int, ...],
                         validation_fraction: float) -> None:
    """Zero the net's output layer unless it beats ``Delta = 0`` on the validation pairs."""
    from .training import one_step_loss

    _, _, valid = segment_pairs(zeta, u, breaks, validation_fraction)
    net = model.net
    with torch.no_grad():
        trained = float(one_step_loss(system, net, *valid, system.dt))
        prior = float(one_step_loss(system, _Zero(), *valid, system.dt))
        kept = trained < prior
        if not kept:
            net.mlp.output_layer.weight.zero_()
            net.mlp.output_layer.bias.zero_()
    model.meta.update(net_kept=kept, prior_validation_loss=prior, net_validation_loss=trained)


class _Zero(torch.nn.Module):
    def forward(self, x, u):
        return torch.zeros_like(x)
