"""The MHE's steady-state arrival cost: theory, and its effect on estimation."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import MHESettings, steady_state_arrival
from learnest_codegen.export import prior_model, true_model
from learnest_codegen.simulation import simulate


def test_arrival_covariance_is_the_converged_kalman_prior(cartpole):
    """For the linearised model, FilterPy's KF prior covariance converges to the DARE solution."""
    model = prior_model(cartpole)
    settings = steady_state_arrival(model, MHESettings.from_system(cartpole))
    x0, u0 = np.array(cartpole.x0), np.zeros(1)
    eps = 1e-6  # finite-difference Jacobians: independent of CasADi's
    A = np.column_stack([(model.step(x0 + eps * e, u0) - model.step(x0 - eps * e, u0)) / (2 * eps)
                         for e in np.eye(4)])
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.H = A, np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    kf.Q = np.diag(np.square(settings.process_std))
    kf.R = np.diag(np.square(settings.measurement_std))
    for _ in range(3000):
        kf.predict()
        kf.update(np.zeros(2))
    np.testing.assert_allclose(np.asarray(settings.arrival_covariance), kf.P_prior, rtol=1e-5)


def test_settings_roundtrip_and_validation(cartpole):
    settings = steady_state_arrival(prior_model(cartpole), MHESettings.from_system(cartpole))
    assert MHESettings.from_json(settings.to_json()) == settings
    P = settings.weights()[2]
    np.testing.assert_allclose(P @ np.asarray(settings.arrival_covariance), np.eye(4), atol=1e-8)
    with pytest.raises(ValueError, match="positive definite"):
        MHESettings.from_system(cartpole, arrival_covariance=-np.eye(4))


def test_steady_state_arrival_lets_the_mhe_use_its_model(cartpole):
    """With the true model, the MHE must beat the nominal MHE by a wide margin once the arrival
    cost carries past information (with a fixed initial-uncertainty weight it did not)."""
    run = simulate(cartpole, 1, duration=0.8)
    mse = {}
    for model in (prior_model(cartpole), true_model(cartpole)):
        settings = steady_state_arrival(model, MHESettings.from_system(cartpole))
        x_hat = MHE(model, settings).run(run.u, run.y, np.array(cartpole.x0))
        mse[model.kind] = np.mean((x_hat - run.x) ** 2)
    assert mse["true"] < mse["nominal"] / 10, mse


def test_every_door_builds_the_same_mhe(cartpole, tmp_path):
    """One settings path: the Python MHE by default and from ``from_system(horizon=10)``, the
    pipeline (both backends' settings), the generator with no settings, the command line with
    ``--horizon`` and the Cortex-M example all give the same weights, the steady-state arrival
    covariance of the model included (before, ``from_system(..., horizon=10)`` and the
    generators dropped it: MSE 8.0e-3 instead of 5.6e-5 on the true model)."""
    import importlib.util
    import sys
    from pathlib import Path

    from click.testing import CliRunner

    import learnest_codegen as ln
    from learnest_codegen.cli import cli
    from learnest_codegen.codegen.emit import c_list
    from learnest_codegen.codegen.mhe_gn import generate_embedded_mhe
    from learnest_codegen.compilation import estimator_settings
    from learnest_codegen.runtime.manifest import read_manifest

    model = prior_model(cartpole)
    reference = {N: steady_state_arrival(model, MHESettings.from_system(cartpole, horizon=N)).to_json()
                 for N in (10, 20)}
    doors = {
        "MHE(model)": (20, MHE(model).settings.to_json()),
        "MHE(model, from_system(horizon=10))":
            (10, MHE(model, MHESettings.from_system(cartpole, horizon=10)).settings.to_json()),
        "make_estimator python": (20, ln.make_estimator("nominal", "mhe", backend="python",
                                                         system=cartpole).settings.to_json()),
        "make_estimator python horizon=10": (10, ln.make_estimator(
            "nominal", "mhe", backend="python", system=cartpole, horizon=10).settings.to_json()),
        "estimator_settings (compile) mhe_rti": (10, estimator_settings("mhe_rti", model,
                                                                         horizon=10).to_json()),
        "generate_embedded_mhe(model, None)": (20, read_manifest(generate_embedded_mhe(
            model, None, tmp_path / "gen").directory)["settings"]),
    }
    result = CliRunner().invoke(cli, ["compile", "--nominal", "--system", "cartpole", "--estimator",
                                      "mhe_gn", "--horizon", "10", "--out", str(tmp_path / "cli")])
    assert result.exit_code == 0, result.output
    doors["learnest compile --horizon 10"] = (10, read_manifest(
        tmp_path / "cli" / "cartpole_nominal_mhe_gn_n10")["settings"])
    example_file = Path(__file__).resolve().parents[1] / "examples" / "cortex_m" / "build_and_compare.py"
    spec = importlib.util.spec_from_file_location("build_and_compare", example_file)
    example = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = example
    spec.loader.exec_module(example)
    gen = example.generate(model, tmp_path / "cortex", steps=5, estimator="mhe_gn")
    doors["Cortex-M example"] = (20, read_manifest(gen.directory)["settings"])
    for door, (N, settings) in doors.items():
        assert settings == reference[N], door
    # the firmware starts from the header's defaults (init_default): the same arrival covariance
    header = (gen.directory / f"{gen.prefix}.h").read_text()
    P0 = c_list(np.asarray(reference[20]["arrival_covariance"]))
    assert f"#define {gen.prefix.upper()}_DEFAULT_P0 {P0}" in header
