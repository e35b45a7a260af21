"""Every estimator, Python reference and compiled C, through the same checks (the contract of
:mod:`learnest_codegen.estimators.contract`).

The checks: the protocol; ``run`` equals ``reset`` plus ``step``; ``reset`` restarts exactly;
bad input (wrong shape, NaN, step before reset) raises the documented error and leaves the state
as it was; on a simulated cartpole run the measured states are estimated better than the
measurement noise with the true model (a bound independent of every estimator); and each compiled
library agrees with its independent reference, the table's ``reference`` (FilterPy's UKF and
EKF for the Kalman filters, CasADi's ``nlpsol`` with Ipopt for every MHE).
"""

from __future__ import annotations

import numpy as np
import pytest

import learnest_codegen as ln
from learnest_codegen.compilation import ESTIMATOR_NAMES, ESTIMATORS, estimator_kind
from learnest_codegen.errors import DataError, LearnestError, ShapeError
from learnest_codegen.estimators.contract import Estimator, takes_missing_outputs

T = 250  # samples (0.5 s of the cartpole): enough for the filters to settle
#: Every estimator and backend: the C library of each, and the Python reference where it has one.
CASES = [(name, backend) for name in ESTIMATOR_NAMES for backend in ("python", "c")
         if backend == "c" or estimator_kind(name).python is not None]
#: estimator -> (reference estimator, the largest relative difference allowed between them),
#: from the table: the Kalman filters' C is FilterPy's arithmetic; mhe and mhe_gn solve the same
#: NLP to convergence; the real-time iteration takes one warm-started Gauss-Newton step per sample.
REFERENCE = {name: kind.reference for name, kind in ESTIMATORS.items()}


def test_every_registered_estimator_is_covered():
    assert {name for name, _ in CASES} == set(ESTIMATOR_NAMES)
    assert None not in REFERENCE.values()


@pytest.fixture(scope="module")
def run(cartpole):
    return ln.simulate(cartpole, seed=3, duration=T * cartpole.dt)


@pytest.fixture(scope="module")
def estimators(cartpole, tmp_path_factory):
    """Each case's estimator of the true cartpole model, built once for the module."""
    out = tmp_path_factory.mktemp("contract")
    return {(name, backend): ln.make_estimator("true", name, backend=backend, system=cartpole, out=out)
            for name, backend in CASES}


@pytest.fixture(scope="module")
def estimates(estimators, run, cartpole):
    return {case: est.run(run.u, run.y, np.asarray(cartpole.x0)) for case, est in estimators.items()}


@pytest.fixture(params=CASES, ids=lambda c: f"{c[0]}-{c[1]}")
def case(request):
    return request.param


def test_keeps_the_protocol(estimators, cartpole, case):
    estimators[case].reset(np.asarray(cartpole.x0))  # Python 3.11's isinstance reads x
    assert isinstance(estimators[case], Estimator)
    assert takes_missing_outputs(estimators[case])


def test_missing_outputs_and_predict(estimators, run, cartpole, case):
    """NaN in y is a missing output: a step without any output equals ``predict``, a step
    with one output missing leaves it out, and neither is a rejection or an error."""
    est = estimators[case]
    est.reset(np.asarray(cartpole.x0))
    for k in range(30):
        est.step(run.u[max(k - 1, 0)], run.y[k])
    before = est.x
    x_nan = est.step(run.u[29], np.full(cartpole.ny, np.nan))
    assert (est.last_status, est.missing.tolist()) == (0, [True] * cartpole.ny)
    est.reset(np.asarray(cartpole.x0))
    for k in range(30):
        est.step(run.u[max(k - 1, 0)], run.y[k])
    np.testing.assert_array_equal(est.x, before)
    np.testing.assert_array_equal(est.predict(run.u[29]), x_nan)
    half = run.y[31].copy()
    half[1] = np.nan
    x = est.step(run.u[30], half)
    assert np.all(np.isfinite(x)) and est.last_status == 0 and est.rejections == 0
    assert est.missing.tolist() == [False, True]


def test_run_equals_reset_and_step(estimators, estimates, run, cartpole, case):
    est = estimators[case]
    est.reset(np.asarray(cartpole.x0))
    stepped = np.array([est.step(run.u[max(k - 1, 0)], run.y[k]) for k in range(T)])
    np.testing.assert_array_equal(stepped, estimates[case])
    np.testing.assert_array_equal(est.x, stepped[-1])


def test_reset_restarts_exactly(estimators, estimates, run, cartpole, case):
    est = estimators[case]
    est.run(run.u[:50] + 1.0, run.y[:50] + 0.1, np.asarray(cartpole.x0) + 0.2)  # somewhere else
    np.testing.assert_array_equal(est.run(run.u, run.y, np.asarray(cartpole.x0)), estimates[case])


def test_bad_input_raises_and_leaves_the_state(estimators, run, cartpole, case):
    est = estimators[case]
    est.reset(np.asarray(cartpole.x0))
    for k in range(20):
        est.step(run.u[max(k - 1, 0)], run.y[k])
    before = est.x
    bad_y = run.y[20].copy()
    bad_y[0] = np.inf  # NaN is a missing output; an infinite y is an error everywhere
    for u, y, error in ((run.u[19][:0], run.y[20], ShapeError), (run.u[19], run.y[20][:1], ShapeError),
                        (run.u[19], bad_y, DataError)):
        with pytest.raises(error):
            est.step(u, y)
        np.testing.assert_array_equal(est.x, before)
    with pytest.raises(ShapeError):
        est.reset(np.zeros(cartpole.nx + 1))
    np.testing.assert_array_equal(est.step(run.u[19], run.y[20]), est.x)  # still usable


def test_step_before_reset_raises(cartpole, case, tmp_path):
    name, backend = case
    fresh = ln.make_estimator("nominal", name, backend=backend, system=cartpole, out=tmp_path)
    with pytest.raises((RuntimeError, LearnestError)):
        fresh.step(np.zeros(cartpole.nu), np.zeros(cartpole.ny))


def test_measured_states_beat_the_measurement_noise(estimates, run, cartpole, case):
    """p and alpha are measured with noise std sigma; a filter that uses the right model must estimate
    them with an RMS error below sigma over the settled second half of the run."""
    x_hat = estimates[case]
    sigma = np.asarray(cartpole.noise.measurement_std)
    measured = [cartpole.state_names.index(n) for n in cartpole.output_names]
    rms = np.sqrt(np.mean((x_hat[T // 2:, measured] - run.x[T // 2:, measured]) ** 2, axis=0))
    assert np.all(rms < sigma), f"RMS {rms} not below the measurement noise {sigma}"


def test_agrees_with_its_independent_reference(estimates, case):
    """C against the Python reference of the same estimator, and the embedded MHEs against the
    Ipopt MHE (CasADi nlpsol): max over the run of |x - x_ref| / max |x_ref|."""
    name, backend = case
    reference, tolerance = REFERENCE[name]
    if (reference, "python") == case:
        pytest.skip("the reference itself")
    ref = estimates[(reference, "python")]
    diff = np.max(np.abs(estimates[case] - ref)) / np.max(np.abs(ref))
    assert diff < tolerance, f"{name}/{backend} differs from the {reference} reference by {diff:.2e}"


def test_converges_from_a_start_three_sigma_off(estimators, estimates, run, cartpole, case):
    """Started 3 initial standard deviations off (alternating signs) with P0 = the initial
    covariance, every estimator's error is within the clean run's band (``|e| <= |e_clean| +
    rms_clean`` per state) from 0.4 s on (measured: UKF 0.16 s, MHE 0.28 s), and the gate
    rejects no output after 0.1 s."""
    est = estimators[case]
    std = np.asarray(cartpole.noise.initial_std)
    x0 = np.asarray(cartpole.x0) + 3 * std * np.array([1.0, -1.0, 1.0, -1.0])
    X = est.run(run.u, run.y, x0, np.diag(std ** 2))
    e, e_clean = np.abs(X - run.x), np.abs(estimates[case] - run.x)
    rms = np.sqrt(np.mean(e_clean ** 2, axis=0))
    settled = int(0.4 / cartpole.dt)
    assert np.all(e[settled:] <= e_clean[settled:] + rms), np.max(e[settled:] - e_clean[settled:] - rms)
    est.reset(x0, np.diag(std ** 2))
    for k in range(T):
        est.step(run.u[max(k - 1, 0)], run.y[k])
        assert k < int(0.1 / cartpole.dt) or est.last_status == 0, k
