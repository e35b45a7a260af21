"""The fast training path: stacked restarts, the CasADi EKF-RTS, one source of defaults, and
models saved by earlier code."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import casadi as cs
import numpy as np
import pytest
import torch

from learnest_codegen import config
from learnest_codegen.errors import SettingsError, UnknownNameError
from learnest_codegen.integrators import rk4_step
from learnest_codegen.learning.training import load_model, make_net, one_step_loss
from learnest_codegen.observers import _discrete_with_jacobian, _ekf_passes, _rts_backward
from learnest_codegen.simulation import simulate

OLD_MODEL = Path(__file__).parent / "data" / "model_b12bfa1"


def _sequential_reference(system, zeta, u, dt, settings):
    """The training loop as it ran before restarts were stacked: one net at a time, plain
    ResidualNet, AdamW, its own mini-batch order, the per-step weight average."""
    nets = []
    for r in range(settings.restarts):
        seed = settings.seed + r
        torch.manual_seed(seed)
        net = make_net(system, settings.network)
        net.set_input_scaling(zeta, u)
        pairs = [torch.as_tensor(a) for a in (zeta[:-1], u[:-1], zeta[1:])]
        optimiser = torch.optim.AdamW(net.parameters(), lr=settings.learning_rate,
                                      weight_decay=settings.weight_decay)
        mean = [p.detach().clone() for p in net.parameters()]
        generator = torch.Generator().manual_seed(seed)
        for _ in range(settings.epochs):
            for idx in torch.randperm(len(pairs[0]), generator=generator).split(settings.batch_size):
                optimiser.zero_grad()
                one_step_loss(system, net, *(a[idx] for a in pairs), dt).backward()
                optimiser.step()
                for m, p in zip(mean, net.parameters()):
                    m.lerp_(p.detach(), 1.0 - settings.weight_average)
        with torch.no_grad():
            for m, p in zip(mean, net.parameters()):
                p.copy_(m)
        nets.append(net)
    return nets


def test_stacked_restarts_follow_the_sequential_paths(cartpole, cartpole_run):
    """Three initialisations trained together as one stacked model end where each ends when
    trained alone, weight decay, mini-batches and weight average included (to 1e-12)."""
    system = cartpole.with_residual(reflection=None)
    run = cartpole_run
    zeta, u = run.x[:300], run.u[:300]
    # float64: the reference is the float64 loop, to 1e-12 (float32 training is held to float64
    # in test_a_float32_training_takes_float64s_steps_and_returns_a_float64_model)
    settings = config.TrainingSettings(epochs=3, batch_size=64, seed=3, restarts=3, weight_decay=0.1,
                                       weight_average=0.9, validation_fraction=0.0, precision="float64")
    from learnest_codegen.learning.training import _train_stacked

    models = _train_stacked(system, zeta, u, run.dt, settings, "", progress=False)
    # validation on the training pairs keeps the best epoch; the last one is compared
    assert [m.meta["best_epoch"] for m in models] == [2, 2, 2]
    for model, ref in zip(models, _sequential_reference(system, zeta, u, run.dt, settings)):
        for name, value in ref.state_dict().items():
            np.testing.assert_allclose(model.net.state_dict()[name], value, rtol=0, atol=1e-12)


def _rk4_step_and_ad_jacobian(system, residual, dt):
    """One RK4 step of ``f_prior + residual`` and its Jacobian by CasADi's AD of the whole step."""
    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    xn = rk4_step(lambda s, v: system.f(s, v) + (residual(s, v) if residual else 0), x, u, dt)
    return cs.Function("F", [x, u], [xn]), cs.Function("A", [x, u], [cs.jacobian(xn, x)])


@pytest.mark.parametrize("name", ["cartpole", "ground_robot"])
def test_the_observers_step_and_jacobian_equal_the_rk4_step_and_its_ad(name):
    """The EKF's step and state Jacobian (the chain rule through the RK4 stages, shared
    subexpressions) equal the RK4 step and CasADi's AD of it at states along a run, to the
    rounding of a few thousand operations (1e-12 of the largest entry)."""
    from learnest_codegen.systems import get_system

    system = get_system(name)
    run = simulate(system, 0, duration=0.2)
    residual = load_model(OLD_MODEL, system).net.casadi if name == "cartpole" else None
    stage = _discrete_with_jacobian(system, residual, run.dt)
    F, A = _rk4_step_and_ad_jacobian(system, residual, run.dt)
    for k in range(0, len(run), 10):
        x, u = run.x[k], run.u[k]
        got_F, got_A = (v.full() for v in stage(x, u))
        ref_F, ref_A = F(x, u).full(), A(x, u).full()
        np.testing.assert_allclose(got_F, ref_F, rtol=0, atol=1e-12 * np.abs(ref_F).max())
        np.testing.assert_allclose(got_A, ref_A, rtol=0, atol=1e-12 * np.abs(ref_A).max())


def _numpy_ekf_rts(run, system, residual, q_scale):
    """The EKF and RTS passes step by step in numpy (the implementation before the CasADi one),
    on the RK4 step and CasADi's AD of the whole step (not the chain rule of the observers)."""
    F, A = _rk4_step_and_ad_jacobian(system, residual, run.dt)
    xs_, us_ = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    H = cs.Function("H", [xs_, us_], [cs.jacobian(system.h(xs_, us_), xs_)])
    R = np.diag(np.square(system.noise.measurement_std))
    Q = np.diag(np.square(system.noise.process_std) * q_scale)
    T, n = len(run), system.nx
    xs, Ps, xps, Pps = np.empty((T, n)), np.empty((T, n, n)), np.empty((T, n)), np.empty((T, n, n))
    x, P, loglik = run.x[0].copy(), np.diag(np.square(system.noise.initial_std)), 0.0
    for k in range(T):
        if k:
            Ak = A(x, run.u[k - 1]).full()
            x, P = F(x, run.u[k - 1]).full().ravel(), Ak @ P @ Ak.T + Q
        xps[k], Pps[k] = x, P
        rows = np.flatnonzero(np.isfinite(run.y[k]))  # the outputs present: an update with them
        if len(rows):
            Hk = H(x, run.u[k]).full()[rows]
            innov = (run.y[k] - system.h(x, run.u[k]))[rows]
            S = Hk @ P @ Hk.T + R[np.ix_(rows, rows)]
            K = np.linalg.solve(S, Hk @ P).T
            x, P = x + K @ innov, (np.eye(n) - K @ Hk) @ P
            loglik -= 0.5 * (innov @ np.linalg.solve(S, innov) + np.linalg.slogdet(2 * np.pi * S)[1])
        xs[k], Ps[k] = x, P
    zeta, covs = xs.copy(), Ps.copy()
    for k in range(T - 2, -1, -1):
        G = np.linalg.solve(Pps[k + 1], A(xs[k], run.u[k]).full() @ Ps[k]).T
        zeta[k] = xs[k] + G @ (zeta[k + 1] - xps[k + 1])
        covs[k] = Ps[k] + G @ (covs[k + 1] - Pps[k + 1]) @ G.T
    return xs, Ps, loglik, zeta, covs


@pytest.mark.parametrize("missing", [False, True])
@pytest.mark.parametrize("name", ["cartpole", "ground_robot"])
def test_casadi_ekf_rts_equals_the_step_by_step_numpy_passes(name, missing):
    """The EKF's forward recursion and the RTS pass, run as CasADi ``mapaccum``s, equal the
    step-by-step numpy passes (states to 1e-9, log-likelihood to 1e-9 relative); with missing
    outputs (NaN), the update uses those present and a sample with none is a prediction."""
    from learnest_codegen.systems import get_system

    system = get_system(name)
    run = simulate(system, 0, duration=1.0)
    if missing:
        y = run.y.copy()
        y[::3, 0] = np.nan  # the first output at two thirds of the rate
        y[200:260] = np.nan  # every output, 60 samples
        run = dataclasses.replace(run, y=y)
    residual = None
    if name == "cartpole":
        residual = load_model(OLD_MODEL, system).net.casadi
    passes, stage = _ekf_passes(run, system, residual, (3.0,))
    xs, Ps, xps, Pps, loglik = passes[3.0]
    zeta, covs = _rts_backward(xs, Ps, xps, Pps, stage, run.u)
    likelihood_alone, _ = _ekf_passes(run, system, residual, (3.0,), states=False)
    assert likelihood_alone[3.0][-1] == loglik  # the same recursion, folded
    ref_xs, ref_Ps, ref_loglik, ref_zeta, ref_covs = _numpy_ekf_rts(run, system, residual, 3.0)
    np.testing.assert_allclose(xs, ref_xs, rtol=0, atol=1e-9)
    np.testing.assert_allclose(Ps, ref_Ps, rtol=0, atol=1e-9 * np.abs(ref_Ps).max())
    np.testing.assert_allclose(zeta, ref_zeta, rtol=0, atol=1e-9)
    np.testing.assert_allclose(covs, ref_covs, rtol=0, atol=1e-9 * np.abs(ref_covs).max())
    assert loglik == pytest.approx(ref_loglik, rel=1e-9)


def test_a_model_saved_by_earlier_code_loads_and_predicts_the_same(cartpole):
    """A model directory written by the code of commit b12bfa1 (before the stacked training)
    loads, keeps its hash and gives the residual it gave then."""
    model = load_model(OLD_MODEL, cartpole)
    expect = json.loads((OLD_MODEL.parent / "model_b12bfa1_expect.json").read_text())
    with torch.no_grad():
        x, u = (torch.tensor(expect[k], dtype=torch.float64) for k in ("x", "u"))
        delta = model.net(x, u).numpy()
    np.testing.assert_allclose(delta, expect["delta"], rtol=0, atol=1e-14)
    assert model.hash == expect["hash"]


def test_training_settings_live_in_config_and_keep_their_old_homes():
    from learnest_codegen.learning import network, training

    assert training.TrainingSettings is config.TrainingSettings
    assert network.NetworkSettings is config.NetworkSettings
    assert training.DEFAULT_TRAINING is config.DEFAULT_TRAINING
    assert config.recipe("table1_cartpole") is config.TABLE1_CARTPOLE_TRAINING
    assert config.recipe("paper") == config.TrainingSettings()
    with pytest.raises(UnknownNameError, match="table1_cartpole"):
        config.recipe("fastest")


def test_one_default_training_for_the_command_line_and_the_library(cartpole, monkeypatch):
    """``learnest train``'s option defaults are DEFAULT_TRAINING's fields, and ``ln.train``
    without settings trains with DEFAULT_TRAINING itself: the two doors give the same settings."""
    import learnest_codegen as ln
    from learnest_codegen.cli import cli
    from learnest_codegen.learning import training

    seen = []
    monkeypatch.setattr(training, "train_on_run", lambda run, system, settings, **kw: seen.append(settings))
    ln.train(simulate(cartpole, 0, duration=0.1), cartpole)
    assert seen == [config.DEFAULT_TRAINING]
    defaults = {p.name: p.default for p in cli.commands["train"].params}
    settings = config.DEFAULT_TRAINING
    for name in ("epochs", "learning_rate", "batch_size", "seed", "validation_fraction", "refine",
                 "restarts", "weight_decay", "final_learning_rate", "weight_average"):
        assert defaults[name] == getattr(settings, name), name
    for name in ("layers", "hidden", "activation"):
        assert defaults[name] == getattr(settings.network, name), name


def test_help_imports_no_torch():
    """``learnest --help`` and ``learnest train --help`` do not import torch."""
    code = ("import sys\nfrom click.testing import CliRunner\nfrom learnest_codegen.cli import cli\n"
            "for args in (['--help'], ['train', '--help'], ['demo', '--help']):\n"
            "    assert CliRunner().invoke(cli, args).exit_code == 0\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"



def _hand_made_adam_step(system, settings, zeta, u, dt):
    """The net of ``settings.seed`` after one float64 Adam step on :func:`one_step_loss` of all
    pairs: what one full-batch epoch of ``train`` must give."""
    torch.manual_seed(settings.seed)
    ref = make_net(system, settings.network)
    ref.set_input_scaling(zeta, u)
    optimiser = torch.optim.Adam(ref.parameters(), lr=settings.learning_rate)
    pairs = [torch.as_tensor(a) for a in (zeta[:-1], u[:-1], zeta[1:])]
    one_step_loss(system, ref, *pairs, dt).backward()
    optimiser.step()
    return ref


def test_the_default_is_full_batch_one_adam_step_per_epoch(cartpole, cartpole_run):
    """With the default batch size an epoch is one Adam step on the loss of all training pairs:
    one epoch of ``train`` equals one hand-made Adam step on ``one_step_loss`` (to 1e-13)."""
    from learnest_codegen.learning.training import train

    system = cartpole.with_residual(reflection=None)
    run = cartpole_run
    zeta, u = run.x[:400], run.u[:400]
    # float64: a hand-made float64 step to 1e-13 (float32: the test of the precision setting)
    settings = config.TrainingSettings(epochs=1, seed=11, validation_fraction=0.0, precision="float64")
    assert settings.batch_size == config.FULL_BATCH
    model = train(system, zeta, u, run.dt, settings, progress=False)
    ref = _hand_made_adam_step(system, settings, zeta, u, run.dt)
    for name, value in ref.state_dict().items():
        np.testing.assert_allclose(model.net.state_dict()[name], value, rtol=0, atol=1e-13)


def test_the_recipes_keep_the_weight_averages_window_and_other_batches_get_other_job_identities():
    """The recommended recipe's weight average spans the epochs of 0.99 per 256-pair step (32
    steps per epoch on the demo's 8000 pairs), and batch size and weight average are part of a
    Table I job's identity: the cartpole task trained full batch (average 0.725 per step) has
    another configuration and task hash, so a resumed sweep never takes one's results for the
    other's."""
    from learnest_codegen.experiments.table1 import DEFAULT_TASKS, Job

    recommended = config.TABLE1_CARTPOLE_TRAINING
    steps = -(-8000 // recommended.batch_size)
    assert recommended.weight_average ** steps == pytest.approx(0.99 ** 32, rel=1e-3)
    full = dataclasses.replace(recommended, batch_size=config.FULL_BATCH, weight_average=0.725)
    task = DEFAULT_TASKS["cartpole"]
    full_task = dataclasses.replace(task, training=full,
                                    full_state_training=dataclasses.replace(full, refine=0, restarts=1))
    new, other = (Job("cartpole", 0, t, "c", "/tmp/out", "/tmp/out/shared") for t in (task, full_task))
    assert new.config_hash() != other.config_hash()
    assert new.task_hash() != other.task_hash()


def test_training_leaves_the_thread_setting_as_it_was(cartpole, cartpole_run):
    """``train`` runs on one thread and restores the caller's torch thread count."""
    from learnest_codegen.learning.training import train

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        train(cartpole, cartpole_run.x[:100], cartpole_run.u[:100], cartpole_run.dt,
              config.TrainingSettings(epochs=1), progress=False)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_patience_and_warm_refinement_settings_and_identity():
    """``patience`` and ``warm_refinement`` are validated, and left out of the settings' JSON
    when off, so models and jobs trained before they existed keep their identities."""
    plain = config.TrainingSettings().to_json()
    assert "patience" not in plain and "warm_refinement" not in plain
    warm = config.WarmRefinement(epochs=7, batch_size=64, learning_rate=1e-3, weight_average=0.5)
    out = config.TrainingSettings(patience=3, warm_refinement=warm).to_json()
    assert out["patience"] == 3
    assert out["warm_refinement"] == {"epochs": 7, "batch_size": 64, "learning_rate": 1e-3,
                                      "weight_average": 0.5}
    for bad in ({"patience": 0}, {"patience": -2}):
        with pytest.raises(SettingsError, match="patience"):
            config.TrainingSettings(**bad)
    for bad in ({"epochs": 0}, {"learning_rate": 0.0}, {"weight_average": 1.0}):
        with pytest.raises(SettingsError, match="WarmRefinement"):
            config.WarmRefinement(**bad)


def test_patience_stops_where_the_validation_loss_stalled_and_keeps_that_runs_best(cartpole, cartpole_run):
    """With ``patience = P`` training stops at the first epoch ``e`` that is ``P`` epochs past
    the best so far, and the result is bit for bit that of training ``e + 1`` epochs."""
    from learnest_codegen.learning.training import train

    system = cartpole.with_residual(reflection=None)
    run = cartpole_run
    zeta, u = run.x[:600], run.u[:600]
    base = config.TrainingSettings(epochs=80, seed=5, learning_rate=5e-2)
    long = train(system, zeta, u, run.dt, base, progress=False)
    history = long.meta["validation_history"]
    patience, stop = None, None
    for p in range(2, 12):  # the smallest patience that stops before the end
        best = 0
        for e, value in enumerate(history):
            best = e if value < history[best] else best
            if e - best >= p:
                patience, stop = p, e
                break
        if stop is not None:
            break
    assert stop is not None and stop < base.epochs - 1, "the validation loss never stalled"
    stopped = train(system, zeta, u, run.dt, dataclasses.replace(base, patience=patience), progress=False)
    assert len(stopped.meta["validation_history"]) == stop + 1
    same = train(system, zeta, u, run.dt, dataclasses.replace(base, epochs=stop + 1), progress=False)
    assert stopped.meta["best_epoch"] == same.meta["best_epoch"] < stop
    for name, value in same.net.state_dict().items():
        assert torch.equal(stopped.net.state_dict()[name], value), name


def test_a_warm_start_begins_at_the_given_net_and_keeps_its_input_scaling(cartpole, cartpole_run):
    """``train(init=model)`` starts from ``model``'s weights and input scaling, not a fresh
    initialisation or a scaling recomputed from the new data: at a vanishing rate the result is
    ``model`` itself; a fresh start on the same data is not. It trains one net."""
    from learnest_codegen.learning.training import train

    system = cartpole.with_residual(reflection=None)
    run = cartpole_run
    first = train(system, run.x[:300], run.u[:300], run.dt, config.TrainingSettings(epochs=5, seed=2),
                  progress=False)
    # float64: a float32 training starts from the given weights rounded to float32 (1e-7 of them)
    still = config.TrainingSettings(epochs=1, seed=2, learning_rate=1e-12, precision="float64")
    warm = train(system, run.x[600:900], run.u[600:900], run.dt, still, init=first, progress=False)
    fresh = train(system, run.x[600:900], run.u[600:900], run.dt, still, progress=False)
    for name, value in first.net.state_dict().items():
        np.testing.assert_allclose(warm.net.state_dict()[name], value, rtol=0, atol=1e-10)
    assert not torch.allclose(fresh.net.in_mean, first.net.in_mean)
    with pytest.raises(SettingsError, match="warm start"):
        train(system, run.x[:300], run.u[:300], run.dt, dataclasses.replace(still, restarts=2),
              init=first, progress=False)


def test_warm_refinement_rounds_train_one_net_from_the_previous_round(cartpole):
    """With ``warm_refinement`` the first round trains ``restarts`` nets and picks one; each later
    round trains one net from the previous round's with the warm settings. The model records
    the recipe, the rounds and the first round's choice."""
    from learnest_codegen.learning.training import train_on_run

    run = simulate(cartpole, seed=4, duration=2.0)
    warm = config.WarmRefinement(epochs=2, batch_size=128, learning_rate=1e-3)
    settings = config.TrainingSettings(epochs=3, restarts=2, refine=2, seed=1, batch_size=256,
                                       warm_refinement=warm)
    model = train_on_run(run, cartpole, settings, progress=False)
    assert model.meta["observer"].endswith("+ekf_rts*2")
    assert model.meta["training"] == settings.to_json()
    assert len(model.meta["validation_history"]) == warm.epochs  # the last round's
    assert len(model.meta["restart_score"]) == settings.restarts  # the first round's choice
    assert model.meta["restart_seed"] in (1, 2)


def test_refinement_rounds_can_train_the_first_rounds_choice_alone(cartpole, monkeypatch):
    """With ``refine_restarts=1`` the first round trains ``restarts`` initialisations and the
    measurements choose one; every refinement round then trains that initialisation alone (its
    seed), unscored. The model records the whole recipe."""
    from learnest_codegen.learning import training

    run = simulate(cartpole, seed=4, duration=1.0)
    settings = config.TrainingSettings(epochs=2, restarts=3, refine=2, refine_restarts=1, seed=5)
    calls = []
    real_train = training.train

    def spy(system, zeta, u, dt, s, **kw):
        calls.append((s.restarts, s.seed, kw.get("score") is not None))
        return real_train(system, zeta, u, dt, s, **kw)

    monkeypatch.setattr(training, "train", spy)
    model = training.train_on_run(run, cartpole, settings, progress=False)
    winner = model.meta["restart_seed"]  # the last round trained the first round's choice
    assert calls[0] == (3, 5, True)
    assert calls[1:] == [(1, winner, False), (1, winner, False)] and winner in (5, 6, 7)
    assert model.meta["training"] == settings.to_json() and settings.to_json()["refine_restarts"] == 1
    assert "refine_restarts" not in config.TrainingSettings().to_json()


@pytest.mark.parametrize("name", ["cartpole", "ground_robot", "quadrotor"])
def test_the_training_derivative_equals_the_hybrid_model(name):
    """``ResidualNet.derivative`` (shared sines and cosines, no stacking in between) and its
    components-first form ``derivative_t``, which the loss runs on, equal ``f_prior + Delta`` as
    ``hybrid`` evaluates it, and so do the gradients of a loss through them, for three restarts
    stacked."""
    from learnest_codegen.integrators import rk4_step
    from learnest_codegen.learning.network import StackedMLP
    from learnest_codegen.systems import get_system

    system = get_system(name)
    run = simulate(system, 0, duration=0.5)
    torch.manual_seed(0)
    net = make_net(system)
    net.set_input_scaling(run.x, run.u)
    mlp = StackedMLP([make_net(system).mlp for _ in range(3)])
    x = torch.as_tensor(run.x).expand(3, *run.x.shape)
    u = torch.as_tensor(run.u).expand(3, *run.u.shape)
    losses = []
    for fn, layout in ((lambda a, b: net.hybrid(system.f, a, b, mlp), lambda a: a),
                       (lambda a, b: net.derivative(a, b, mlp), lambda a: a),
                       (lambda a, b: net.derivative_t(a, b, mlp), lambda a: a.permute(2, 0, 1))):
        loss = (rk4_step(fn, layout(x), layout(u), run.dt) ** 2).sum()
        losses.append((loss, torch.autograd.grad(loss, list(mlp.parameters()))))
    l_ref, g_ref = losses[0]
    for l_new, g_new in losses[1:]:
        assert l_new.item() == pytest.approx(l_ref.item(), rel=1e-14)
        for a, b in zip(g_new, g_ref):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14 * float(b.abs().max()))


def test_progress_stays_quiet_off_a_terminal(cartpole, cartpole_run, capsys):
    """Redirected to a file (not a terminal), training writes no progress bar: one log line per
    refresh would fill a log; only the observer choice, said once, and one line per training of
    ``train_on_run`` (the first, then each refinement round) are written."""
    from learnest_codegen.learning.training import train, train_on_run

    train(cartpole, cartpole_run.x[:300], cartpole_run.u[:300], cartpole_run.dt,
          config.TrainingSettings(epochs=30), progress=True)
    err = capsys.readouterr().err
    assert "training cartpole" not in err and "it/s" not in err and len(err) < 100, err
    run = simulate(cartpole, 0, duration=0.4)
    train_on_run(run, cartpole, config.TrainingSettings(epochs=2, refine=1), progress=True)
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == "pre-training observer: rts (the system declares kinematic chains covering its states)"
    assert [line.split(":")[0] for line in err[1:]] == [
        "[1/2] trained on the rts states", "[2/2] smoothed through the model (EKF-RTS) and retrained"], err
    assert all(re.search(r"best epoch \d+, validation loss \S+, \d+\.\d s$", line) for line in err[1:]), err
    train_on_run(run, cartpole, config.TrainingSettings(epochs=2), progress=False)
    assert capsys.readouterr().err == ""


def test_the_validation_loss_riding_along_in_the_next_epoch_equals_a_pass_of_its_own(cartpole, cartpole_run):
    """A full batch validates epoch ``e`` in epoch ``e + 1``'s forward pass, the last epoch in a
    pass of its own. Training ``k`` epochs ends on that pass at the weights after epoch ``k -
    1``: it equals the loss the longer training recorded for the same epoch (to 1e-12), and the
    training losses of the shared epochs are the same."""
    from learnest_codegen.learning.training import train

    run = cartpole_run
    zeta, u = run.x[:500], run.u[:500]
    # float64: a joint pass and a pass of its own round differently; 1e-12 is float64's rounding
    settings = config.TrainingSettings(epochs=6, seed=3, weight_decay=0.1, precision="float64")
    long = train(cartpole, zeta, u, run.dt, settings, progress=False)
    for k in (1, 2, 5):
        short = train(cartpole, zeta, u, run.dt, dataclasses.replace(settings, epochs=k), progress=False)
        assert short.meta["validation_history"][-1] == pytest.approx(long.meta["validation_history"][k - 1],
                                                                     rel=1e-12)
        np.testing.assert_allclose(short.meta["loss_history"], long.meta["loss_history"][:k], rtol=1e-12)
    assert len(set(long.meta["validation_history"])) == settings.epochs  # a loss per epoch, each its own


@pytest.mark.parametrize("name", ["cartpole", "ground_robot", "quadrotor"])
def test_the_first_stage_taken_from_its_start_is_the_same_number(name):
    """Training computes the first RK4 stage's prior and features at the data once
    (``ResidualNet.start_t``): ``derivative_t`` from that start is bit for bit the derivative
    computed from scratch, and so are the gradients through it."""
    from learnest_codegen.learning.network import StackedMLP
    from learnest_codegen.systems import get_system

    system = get_system(name)
    run = simulate(system, 0, duration=0.2)
    torch.manual_seed(0)
    net = make_net(system)
    net.set_input_scaling(run.x, run.u)
    mlp = StackedMLP([make_net(system).mlp for _ in range(2)])
    x, u = (torch.as_tensor(a).T[:, None].expand(a.shape[1], 2, a.shape[0]) for a in (run.x, run.u))
    with torch.no_grad():
        start = net.start_t(x, u)
    results = []
    for s in (None, start):
        out = net.derivative_t(x, u, mlp, s)
        results.append((out, torch.autograd.grad((out ** 2).sum(), list(mlp.parameters()))))
    assert torch.equal(results[0][0], results[1][0])
    for a, b in zip(results[0][1], results[1][1]):
        assert torch.equal(a, b)


def test_trainings_tanh_is_torchs_to_rounding_and_trains_the_same_model(cartpole, cartpole_run, monkeypatch):
    """Training evaluates tanh as ``2 sigmoid(2x) - 1`` (half the cost of torch's float64
    tanh): within 4e-16 of ``torch.tanh`` from -30 to 30 and on tiny arguments, its gradient
    within 1e-15 of ``1 - tanh^2``; and a training with it ends on the model that a training
    with ``torch.tanh`` ends on (best epoch equal, final loss to 1e-9, weights to 1e-9)."""
    import types

    from learnest_codegen.learning import network
    from learnest_codegen.learning.training import train

    x = torch.cat([torch.linspace(-30, 30, 600001, dtype=torch.float64),
                   torch.logspace(-300, 0, 3001, dtype=torch.float64),
                   -torch.logspace(-300, 0, 3001, dtype=torch.float64)]).requires_grad_()
    y = network._Tanh.apply(x)
    (grad,) = torch.autograd.grad(y.sum(), x)
    ref = torch.tanh(x.detach())
    assert float((y.detach() - ref).abs().max()) <= 4e-16
    assert float((grad - (1 - ref ** 2)).abs().max()) <= 1e-15
    run = cartpole_run
    zeta, u = run.x[:1500], run.u[:1500]
    # float64: the 4e-16 of the two tanh forms is float64's; float32 rounds both to 6e-8
    settings = config.TrainingSettings(epochs=120, seed=4, weight_decay=0.1, precision="float64")
    fast = train(cartpole, zeta, u, run.dt, settings, progress=False)
    monkeypatch.setattr(network, "_Tanh", types.SimpleNamespace(apply=torch.tanh))
    plain = train(cartpole, zeta, u, run.dt, settings, progress=False)
    assert fast.meta["best_epoch"] == plain.meta["best_epoch"] > 10
    assert fast.meta["final_loss"] == pytest.approx(plain.meta["final_loss"], rel=1e-9)
    for name, value in plain.net.state_dict().items():
        np.testing.assert_allclose(fast.net.state_dict()[name], value, rtol=0, atol=1e-9)


def test_the_precision_setting_is_checked_and_left_out_of_the_identity_when_float64():
    """``precision`` names a torch floating type; float64 (what every model was trained in
    before the setting existed) is left out of the settings' JSON, so those models and Table I
    jobs keep their identities, and float32 is recorded."""
    assert "precision" not in config.TrainingSettings(precision="float64").to_json()
    assert config.TrainingSettings(precision="float32").to_json()["precision"] == "float32"
    with pytest.raises(UnknownNameError, match="precision.*float16"):
        config.TrainingSettings(precision="float16")


def test_the_loss_compares_the_rk4_increment_with_the_observed_increment(cartpole, cartpole_run):
    """Training's loss (increments, the observed one taken in float64 before any cast) is the
    paper's eq. (11) as :func:`one_step_loss` computes it on whole states: the same number to
    1e-12 in float64, and to 1e-6 in float32 (the float32 residual then holds no rounding of
    the states themselves, which would be 6e-8 of the cart's position per component)."""
    from learnest_codegen.learning.network import StackedMLP
    from learnest_codegen.learning.training import _loss_of, _start, _training_pairs

    system = cartpole.with_residual(reflection=None)
    run = cartpole_run
    torch.manual_seed(2)
    net = make_net(system)
    net.set_input_scaling(run.x, run.u)
    pairs = [torch.as_tensor(a) for a in (run.x[:-1], run.u[:-1], run.x[1:])]
    with torch.no_grad():
        ref = float(one_step_loss(system, net, *pairs, run.dt))
        for dtype, rel in ((torch.float64, 1e-12), (torch.float32, 1e-6)):
            net_t = make_net(system)
            net_t.load_state_dict(net.state_dict())
            net_t.to(dtype)
            mlp = StackedMLP([net_t.mlp])
            got = _loss_of(net_t, mlp, run.dt, *_start(net_t, 1, *_training_pairs(pairs, dtype)))
            assert got.dtype == dtype
            assert float(got[0]) == pytest.approx(ref, rel=rel)


def test_a_float32_training_takes_float64s_steps_and_returns_a_float64_model(cartpole, cartpole_run):
    """Trained in float32, the net follows the float64 training: one full-batch epoch is one
    hand-made float64 Adam step on :func:`one_step_loss` to 1e-6 (float32 rounding of weights
    near 1); 120 epochs end on the same best epoch with the final loss to 1e-6 and the
    validation losses to 1e-4 (relative). The model comes back in float64, its weights the float32
    ones cast."""
    from learnest_codegen.learning.training import train

    system = cartpole.with_residual(reflection=None)
    run = cartpole_run
    zeta, u = run.x[:400], run.u[:400]
    one = config.TrainingSettings(epochs=1, seed=11, validation_fraction=0.0, precision="float32")
    model = train(system, zeta, u, run.dt, one, progress=False)
    ref = _hand_made_adam_step(system, one, zeta, u, run.dt)
    for name, value in ref.state_dict().items():
        assert model.net.state_dict()[name].dtype == torch.float64, name
        np.testing.assert_allclose(model.net.state_dict()[name], value, rtol=0, atol=1e-6)

    zeta, u = run.x[:1500], run.u[:1500]
    settings = config.TrainingSettings(epochs=120, seed=4, weight_decay=0.1)
    single, double = (train(cartpole, zeta, u, run.dt, dataclasses.replace(settings, precision=p),
                            progress=False) for p in ("float32", "float64"))
    assert single.meta["training"]["precision"] == "float32"
    assert single.meta["best_epoch"] == double.meta["best_epoch"] > 10
    assert single.meta["final_loss"] == pytest.approx(double.meta["final_loss"], rel=1e-6)
    np.testing.assert_allclose(single.meta["validation_history"], double.meta["validation_history"],
                               rtol=1e-4)
    assert all(v.dtype == torch.float64 for v in single.net.state_dict().values())


@pytest.mark.parametrize("weight_decay", [0.0, 0.1])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_fused_adam_takes_torch_optims_fused_steps(weight_decay, dtype):
    """Training's Adam (AdamW with decay) calls torch's fused kernel itself: five steps on the
    same gradients give torch.optim's ``fused=True`` optimiser's iterates bit for bit (the same
    kernel on the same state)."""
    from learnest_codegen.learning.training import FusedAdam

    torch.manual_seed(0)
    ours, ref = (torch.nn.Linear(5, 3).to(dtype) for _ in range(2))
    ref.load_state_dict(ours.state_dict())
    optimiser = FusedAdam(ours.parameters(), 1e-2, weight_decay)
    kind = torch.optim.AdamW if weight_decay else torch.optim.Adam
    reference = kind(ref.parameters(), lr=1e-2, weight_decay=weight_decay, fused=True)
    x = torch.randn(16, 5, dtype=dtype)
    for _ in range(5):
        for net, opt in ((ours, optimiser), (ref, reference)):
            opt.zero_grad()
            (net(x) ** 2).sum().backward()
            opt.step()
        for a, b in zip(ours.parameters(), ref.parameters()):
            assert torch.equal(a, b)


def test_integrator_chains_in_closed_form_equal_expm_and_filterpys_noise():
    """The kinematic observers' chain model in closed form: ``F`` is ``expm(A dt)`` of the
    integrator chain and ``Q`` FilterPy's ``Q_continuous_white_noise`` (orders 2-4), to 1e-15
    relative (the closed forms against a Pade approximation and FilterPy's literals)."""
    from filterpy.common import Q_continuous_white_noise
    from scipy.linalg import expm

    from learnest_codegen.observers.kalman import integrator_chain

    for order in (1, 2, 3, 4):
        for dt in (0.002, 0.01, 1.3):
            F, Q = integrator_chain(order, dt)
            np.testing.assert_allclose(F, expm(np.diag(np.full(order - 1, dt), 1)), rtol=1e-15, atol=0)
            ref = Q_continuous_white_noise(dim=order, dt=dt, spectral_density=1.0) if order > 1 else [[dt]]
            np.testing.assert_allclose(Q, ref, rtol=1e-15, atol=0)


def test_a_cold_training_imports_neither_torchs_compiler_nor_filterpy():
    """The first ``ln.train`` in a fresh process pays for torch and its epochs only: neither
    torch.optim's compiler stack (``torch._dynamo``, about 2 s of CPU) nor FilterPy (with
    scipy.stats, about 0.7 s) is imported on the way (a kinematic observer, one round)."""
    code = ("import sys\nfrom dataclasses import replace\nimport learnest_codegen as ln\n"
            "run = ln.simulate('cartpole', 0, duration=1.0)\n"
            "ln.train(run, 'cartpole', replace(ln.DEFAULT_TRAINING, refine=0, epochs=2), progress=False)\n"
            "print(sorted(m for m in ('torch._dynamo', 'filterpy', 'torch') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "['torch']"
