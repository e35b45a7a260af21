"""Training ranges of a net's inputs, the clamp that keeps them there, and training on several runs."""

from __future__ import annotations

from dataclasses import replace

import casadi as cs
import numpy as np
import pytest
import torch

from learnest_codegen.compilation import knode_model
from learnest_codegen.errors import DataError, ModelMismatchError, SettingsError
from learnest_codegen.learning.model import TrainedModel, make_net
from learnest_codegen.learning.network import NetworkSettings
from learnest_codegen.learning.pairs import segment_pairs
from learnest_codegen.learning.ranges import RANGES_KEY, InputBox, extrapolation, record_ranges, training_box
from learnest_codegen.learning.runs import train_on_runs
from learnest_codegen.learning.training import TrainingSettings, train
from learnest_codegen.simulation import simulate
from learnest_codegen.systems import SYSTEMS

QUAD = SYSTEMS["quadrotor"]
CARTPOLE = SYSTEMS["cartpole"]


def _random_net(system, seed=0, hidden=8):
    torch.manual_seed(seed)
    net = make_net(system, NetworkSettings(layers=3, hidden=hidden))
    rng = np.random.default_rng(seed)
    with torch.no_grad():
        net.in_mean.copy_(torch.as_tensor(rng.normal(size=net.in_mean.shape)))
        net.in_scale.copy_(torch.as_tensor(rng.uniform(0.5, 2.0, size=net.in_scale.shape)))
    return net


def _numpy_net(net, feats, low, high):
    """The MLP written out in numpy from the state dict: an independent reference."""
    z = (np.clip(feats, low, high) - net.in_mean.numpy()) / net.in_scale.numpy()
    state = {k: v.detach().numpy() for k, v in net.state_dict().items()}
    layers = ["input_layer", "hidden_layers.0", "output_layer"]
    for i, name in enumerate(layers):
        z = z @ state[f"mlp.{name}.weight"].T + state[f"mlp.{name}.bias"]
        if i < len(layers) - 1:
            z = np.tanh(z)
    return z


@pytest.mark.parametrize("system", [QUAD, SYSTEMS["ground_robot"], CARTPOLE], ids=lambda s: s.name)
def test_clamped_net_numpy_torch_casadi_agree(system):
    """Inside and outside the box, the clamped net is the net of the clamped features, in numpy
    (written out here for a residual on the states), torch and CasADi alike; the clamp changes
    nothing inside the box. The cartpole's residual acts through its input with prior gains."""
    net = _random_net(system)
    rng = np.random.default_rng(3)
    x, u = rng.normal(size=(40, system.nx)), rng.normal(size=(40, system.nu))
    x[20:] *= 3.0  # the box of the first 20 points: most of the last 20 leave it
    train_x, train_u = x[:20], u[:20]
    box = InputBox.from_json(record_ranges(net, system, train_x, train_u))
    low, high = box.arrays
    feats = net.features_numpy(x, u)
    assert np.any((feats < low) | (feats > high))
    ref = _numpy_net(net, feats, low, high) if not system.residual_via_names else None
    with torch.no_grad():
        th = net(torch.as_tensor(x), torch.as_tensor(u), box=(low, high)).numpy()
    xs, us = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    fn = cs.Function("delta", [xs, us], [net.casadi(xs, us, (low, high))])
    ca = np.stack([np.asarray(fn(xi, ui)).ravel() for xi, ui in zip(x, u)])
    if not system.residual_via_names:
        rows = [system.state_names.index(n) for n in system.residual_state_names]
        np.testing.assert_allclose(th[:, rows], ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ca, th, rtol=1e-12, atol=1e-12)
    inside = ~np.any((feats < low) | (feats > high), axis=1)
    assert inside.sum() >= 5
    with torch.no_grad():
        free = net(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    np.testing.assert_array_equal(th[inside], free[inside])
    assert not np.allclose(th[~inside], free[~inside])


def test_box_names_follow_the_features():
    net = make_net(CARTPOLE)
    box = InputBox.from_json(record_ranges(net, CARTPOLE, np.zeros((3, 4)), np.zeros((3, 1))))
    assert len(box.names) == net.in_mean.shape[0]
    assert "sin(alpha)" in box.names and "cos(alpha)" in box.names
    with pytest.raises(ModelMismatchError, match="names, low and high"):
        InputBox.from_json({"names": ["a"]})


def test_training_records_ranges_and_extrapolation_counts_samples():
    run = simulate(QUAD, 0, duration=3.0)
    model = train(QUAD, run.x, run.u, run.dt, TrainingSettings(epochs=2), progress=False)
    box = training_box(model)
    feats = model.net.features_numpy(run.x, run.u)
    np.testing.assert_array_equal(box.arrays[0], feats.min(axis=0))
    np.testing.assert_array_equal(box.arrays[1], feats.max(axis=0))
    assert extrapolation(model, run.x, run.u).share == 0.0
    u = run.u.copy()
    u[:30, 3] = box.high[box.names.index("vbat")] + 0.1  # a battery above anything seen
    report = extrapolation(model, run.x, u)
    assert report.share == pytest.approx(30 / len(run))
    assert report.by_feature["vbat"] == pytest.approx(30 / len(run)) and report.worst(1)[0][0] == "vbat"
    assert "vbat" in report.describe()
    old = TrainedModel(model.system, model.net, {k: v for k, v in model.meta.items() if k != RANGES_KEY})
    assert extrapolation(old, run.x, run.u) is None


def test_knode_model_clamps_only_when_asked_and_hashes_apart():
    run = simulate(QUAD, 1, duration=2.0)
    model = train(QUAD, run.x, run.u, run.dt, TrainingSettings(epochs=2), progress=False)
    free, free_hash = knode_model(model, clamp_inputs=False)
    clamped, clamped_hash = knode_model(model, clamp_inputs=True)
    assert free_hash == model.hash and clamped_hash != model.hash
    x, u = run.x[5], run.u[5].copy()
    np.testing.assert_array_equal(free.step(x, u), clamped.step(x, u))  # inside the box
    u[3] += 5.0  # vbat far outside
    assert not np.allclose(free.step(x, u), clamped.step(x, u))
    old = TrainedModel(model.system, model.net, {k: v for k, v in model.meta.items() if k != RANGES_KEY})
    with pytest.raises(ModelMismatchError, match="no training range"):
        knode_model(old, clamp_inputs=True)


def test_segment_pairs_never_span_a_join():
    zeta = np.arange(20.0)[:, None] * [1.0, 10.0]
    u = np.arange(20.0)[:, None]
    pairs, train_set, valid_set = segment_pairs(zeta, u, [8], validation_fraction=0.25)
    starts = pairs[0][:, 0].numpy()
    np.testing.assert_array_equal(starts, [*range(7), *range(8, 19)])  # no pair 7 -> 8
    np.testing.assert_array_equal(pairs[2][:, 0].numpy(), starts + 1)
    # each recording's final quarter of pairs (7 pairs -> 1, 11 pairs -> 2) is held out
    np.testing.assert_array_equal(valid_set[0][:, 0].numpy(), [6, 17, 18])
    np.testing.assert_array_equal(train_set[0][:, 0].numpy(), [*range(6), *range(8, 17)])
    with pytest.raises(DataError, match="at least 2 samples"):
        segment_pairs(zeta, u, [19], 0.2)


def test_train_on_runs_equals_train_on_the_joined_pairs():
    """Two runs: the same net as training on their observer states joined with a break, and
    the ranges cover both runs."""
    from learnest_codegen.observers import observe

    runs = [simulate(QUAD, s, duration=2.0) for s in (0, 1)]
    settings = TrainingSettings(epochs=3)
    model = train_on_runs(runs, QUAD, settings, names=["a", "b"], progress=False)
    zeta = np.vstack([observe(r, QUAD, "linear_rts").zeta for r in runs])
    u = np.vstack([r.u for r in runs])
    direct = train(QUAD, zeta, u, QUAD.dt, settings, progress=False, breaks=[len(runs[0])])
    for (k, a), b in zip(model.net.state_dict().items(), direct.net.state_dict().values()):
        torch.testing.assert_close(a, b, rtol=0, atol=0, msg=k)
    assert model.meta["runs"] == ["a", "b"] and model.meta["run_samples"] == [len(r) for r in runs]
    feats = model.net.features_numpy(zeta, u)
    np.testing.assert_array_equal(training_box(model).arrays[1], feats.max(axis=0))
    with pytest.raises(DataError, match="2 recordings but 1 names"):
        train_on_runs(runs, QUAD, replace(settings, epochs=1), names=["a"], progress=False)


# --- grey-box priors ------------------------------------------------------------------------------

LINEAR = SYSTEMS["quadrotor_linear"]
TRUE_K = {"k_v_xy": 0.8, "k_a_xy": 0.3, "k_v_z": 2.5, "k_a_z": 0.1}


def _linear_trajectory(seed: int, n: int = 800) -> np.ndarray:
    """Exact samples of ``xdot = A x`` for the fitted quadrotor prior with ``TRUE_K`` (matrix
    exponential of the Jacobian, independent of the system's own evaluation)."""
    from scipy.linalg import expm

    A = np.zeros((9, 9))
    A[0:3, 3:6] = A[3:6, 6:9] = np.eye(3)
    for i, (kv, ka) in enumerate([("k_v_xy", "k_a_xy")] * 2 + [("k_v_z", "k_a_z")]):
        A[6 + i, 3 + i], A[6 + i, 6 + i] = -TRUE_K[kv], -TRUE_K[ka]
    step = expm(A * LINEAR.dt)
    x = [np.random.default_rng(seed).normal(size=9)]
    for _ in range(n - 1):
        x.append(step @ x[-1])
    return np.array(x)


def test_fit_linear_params_recovers_a_known_prior():
    from learnest_codegen.learning.prior_fit import fit_linear_params, fitted_system

    zetas = [_linear_trajectory(s) for s in (0, 1)]
    us = [np.zeros((len(z), 4)) for z in zetas]
    fitted = fit_linear_params(LINEAR, list(TRUE_K), zetas, us, LINEAR.dt)
    for name, value in TRUE_K.items():  # the RK4 step of the exact flow: O(dt^5) per step
        assert fitted[name] == pytest.approx(value, rel=1e-6), name
    assert fitted_system(LINEAR, fitted).params["k_v_z"] == fitted["k_v_z"]
    assert LINEAR.params["k_v_z"] == 0.0  # the registered system keeps the triple integrator
    with pytest.raises(DataError, match="does not enter the dynamics linearly"):
        fit_linear_params(CARTPOLE, ["l"], [np.random.default_rng(0).normal(size=(50, 4))],
                          [np.zeros((50, 1))], CARTPOLE.dt)
    from learnest_codegen.errors import UnknownNameError

    with pytest.raises(UnknownNameError, match="no prior parameter"):
        fit_linear_params(LINEAR, ["k_drag"], zetas, us, LINEAR.dt)


def test_a_model_with_a_fitted_prior_carries_it(tmp_path):
    """train_on_runs fits the prior, trains the net on the rest, and the model directory
    reloads with the fitted prior; a net that does not beat the prior on validation is zeroed."""
    from learnest_codegen.learning.model import load_model

    runs = [simulate(LINEAR, s, duration=3.0) for s in (0, 1)]
    model = train_on_runs(runs, LINEAR, TrainingSettings(epochs=3), fit_prior=list(TRUE_K),
                          net_must_beat_prior=True, progress=False)
    assert set(model.meta["prior_params"]) == set(TRUE_K)
    assert model.system.params == {**LINEAR.params, **model.meta["prior_params"]}
    assert model.meta["net_kept"] == (model.meta["net_validation_loss"] < model.meta["prior_validation_loss"])
    model.save(tmp_path / "m")
    loaded = load_model(tmp_path / "m", LINEAR)
    assert loaded.system.params == model.system.params and loaded.hash == model.hash
    x, u = runs[0].x[:5], runs[0].u[:5]
    np.testing.assert_allclose(loaded.system.f(x, u), model.system.f(x, u), rtol=0, atol=0)
    with torch.no_grad():  # zeroing the output layer makes the residual exactly 0
        model.net.mlp.output_layer.weight.zero_()
        model.net.mlp.output_layer.bias.zero_()
        assert not model.net(torch.as_tensor(x), torch.as_tensor(u)).any()


def test_a_prior_only_model_is_its_fitted_prior():
    """net=False: the fitted prior as a model (zero residual), with ranges and metadata."""
    runs = [simulate(LINEAR, s, duration=2.0) for s in (0, 1)]
    model = train_on_runs(runs, LINEAR, TrainingSettings(epochs=3), fit_prior=list(TRUE_K), net=False,
                          progress=False)
    x, u = runs[0].x[:20], runs[0].u[:20]
    with torch.no_grad():
        assert not model.net(torch.as_tensor(x), torch.as_tensor(u)).any()
    assert model.meta["net_kept"] is False and model.meta["final_loss"] == model.meta["prior_loss"]
    assert training_box(model) is not None
    assert model.system.params["k_v_z"] == model.meta["prior_params"]["k_v_z"]
    with pytest.raises(SettingsError, match="needs fit_prior"):
        train_on_runs(runs, LINEAR, TrainingSettings(epochs=1), net=False, progress=False)
