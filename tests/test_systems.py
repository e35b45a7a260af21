"""A system is written once; its numpy, torch and CasADi forms must agree (to 1e-12)."""

from __future__ import annotations

import dataclasses

import casadi as cs
import numpy as np
import pytest
import torch

from learnest_codegen import get_system
from learnest_codegen.errors import LearnestError, ShapeError, SystemFileError, UnknownNameError
from learnest_codegen.systems import SYSTEMS


def _systems(user_system_file):
    return [*SYSTEMS.values(), get_system(str(user_system_file))]


@pytest.mark.parametrize("variant", ["prior", "true"])
def test_numpy_torch_casadi_agree(user_system_file, variant):
    rng = np.random.default_rng(0)
    for system in _systems(user_system_file):
        x, u = rng.normal(size=(50, system.nx)), rng.normal(size=(50, system.nu))
        f_np = system.f(x, u, variant=variant)
        f_torch = system.f(torch.tensor(x), torch.tensor(u), variant=variant).numpy()
        f_cs = system.casadi_f(variant).map(50)(x.T, u.T).full().T
        np.testing.assert_allclose(f_torch, f_np, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(f_cs, f_np, rtol=1e-12, atol=1e-12)
        h_cs = system.casadi_h().map(50)(x.T, u.T).full().T
        np.testing.assert_allclose(h_cs, system.h(x, u), rtol=1e-12, atol=1e-12)


def _cartpole_lagrangian(x, F, mc, mp=0.1, l=0.5, g=9.81):
    """Accelerations of a cart and a uniform pole (half-length l, pivot inertia 4/3 mp l^2)
    from the Lagrangian's mass matrix, solved numerically: an independent reference."""
    _, _, a, ad = x
    M = np.array([[mc + mp, mp * l * np.cos(a)], [mp * l * np.cos(a), 4 / 3 * mp * l**2]])
    rhs = np.array([F + mp * l * ad**2 * np.sin(a), mp * g * l * np.sin(a)])
    return np.linalg.solve(M, rhs)


def test_cartpole_matches_lagrangian_mechanics():
    """Both variants against the mass-matrix form of the Lagrangian, at random states; at rest and
    upright with no force the cartpole is in equilibrium, and the heavier true cart accelerates less."""
    s = get_system("cartpole")
    np.testing.assert_allclose(s.f(np.zeros(4), np.zeros(1)), np.zeros(4), atol=1e-15)
    rng = np.random.default_rng(3)
    for variant, mc in (("prior", 1.0), ("true", 1.5)):
        for x, F in zip(rng.normal(size=(20, 4)) * [1, 2, 3, 5], rng.normal(size=20) * 10):
            p_dd, a_dd = _cartpole_lagrangian(x, F, mc)
            np.testing.assert_allclose(s.f(x, np.array([F]), variant=variant), [x[1], p_dd, x[3], a_dd],
                                       rtol=1e-12, atol=1e-12)
    assert s.f(np.zeros(4), np.array([2.0]), variant="true")[1] < s.f(np.zeros(4), np.array([2.0]))[1]


def test_torch_gradients_flow():
    s = get_system("cartpole")
    x = torch.zeros(3, 4, dtype=torch.float64, requires_grad=True)
    s.f(x, torch.ones(3, 1, dtype=torch.float64)).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0


def test_user_system_file_is_loaded(user_system_file):
    system = get_system(str(user_system_file))
    assert system.name == "my_pendulum" and system.nx == 2
    xdot = system.f(np.array([0.0, 1.0]), np.array([0.0]), variant="true")
    np.testing.assert_allclose(xdot, [1.0, -0.3])


def test_bad_names_and_files_fail_clearly(tmp_path):
    with pytest.raises(UnknownNameError, match="cartpole"):
        get_system("cartpol")
    with pytest.raises(SystemFileError, match="does not exist"):
        get_system(str(tmp_path / "missing.py"))
    bad = tmp_path / "bad.py"
    bad.write_text("SYSTEM = 3\n")
    with pytest.raises(SystemFileError, match="must define SYSTEM"):
        get_system(str(bad))
    broken = tmp_path / "broken.py"
    broken.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(LearnestError, match="boom"):
        get_system(str(broken))


def test_wrong_shapes_are_rejected():
    s = get_system("cartpole")
    with pytest.raises(ShapeError, match="last dimension 4"):
        s.f(np.zeros(3), np.zeros(1))
    with pytest.raises(ShapeError):
        s.f(cs.SX.sym("x", 5), cs.SX.sym("u", 1))


def test_fingerprint_sees_equations_not_just_settings():
    """Same system: same fingerprint; an edit to the equations (same names and settings) or to a
    true parameter changes it, so resumed sweeps and caches notice."""
    s = get_system("cartpole")
    assert s.fingerprint() == get_system("cartpole").fingerprint()

    def edited(ops, x, u, p):
        xdot = s.dynamics(ops, x, u, p)
        return [xdot[0], xdot[1] * 1.000001, xdot[2], xdot[3]]

    assert dataclasses.replace(s, dynamics=edited).fingerprint() != s.fingerprint()
    assert s.with_true_params(m_c=1.4).fingerprint() != s.fingerprint()


# --- the check of a system when it is loaded ------------------------------------------------------

PENDULUM_BODY = '''
import math
import numpy as np
from learnest_codegen import NoiseModel, Signal, System

def dynamics(ops, x, u, p):
    q, qdot = x
    return {dyn}

SYSTEM = System(
    name="pend", states=(Signal("q", "rad"), Signal("qdot", "rad/s")), inputs=(Signal("tau", "N m"),),
    outputs=(Signal("q", "rad"),), params={{"k": 9.0}}, true_params={{"k": 9.0}},
    dynamics=dynamics, measurement=lambda ops, x, u, p: {meas},
    noise=NoiseModel(measurement_std=(0.01,), state_std=(0.01, 0.01), process_std=(1e-3, 1e-2),
                     initial_std=(0.1, 0.1)),
    dt=0.01, duration=1.0, x0=(0.5, 0.0), excitation=lambda t, rng: np.sin(2 * t)[:, None],
)
'''
GOOD = '[qdot, -p["k"] * ops.sin(q) + u[0]]'


@pytest.mark.parametrize("dyn, meas, needles", [
    (GOOD.replace("ops.sin", "np.sin"), "[x[0]]", ("dynamics in CasADi", "a numpy function was applied")),
    (GOOD.replace("ops.sin", "math.sin"), "[x[0]]", ("dynamics cannot be evaluated with numpy",)),
    ("[qdot, -9 * ops.sin(q), qdot]", "[x[0]]", ("dynamics returned 3 values", "2 states")),
    (GOOD, "[x[0], x[1]]", ("measurement returned 2 values", "1 outputs")),
    ("[qdot, (1.0 if q > 0 else -1.0) + u[0]]", "[x[0]]", ("dynamics", "ambiguous")),
    (GOOD.replace('p["k"]', 'p["damping"]'), "[x[0]]", ("dynamics reads the parameter 'damping'",)),
    ("[qdot, ops.sqrt(q - 1.0) + u[0]]", "[x[0]]", ("dynamics: value 1 is nan",)),
    (GOOD, "[x[0] * 0 + np.float64(np.sin(1.0)) * ops.cos(x[1])]", ()),  # numpy on a constant: fine
])
def test_a_system_file_mistake_is_one_line_naming_the_function(tmp_path, dyn, meas, needles):
    """Issue 26/28: np.sin passed simulate and compile and died in training with a 60-line
    traceback; a wrong count of values was broadcast. Now the load says which function and what."""
    path = tmp_path / "pend.py"
    path.write_text(PENDULUM_BODY.format(dyn=dyn, meas=meas))
    if not needles:
        assert get_system(str(path)).name == "pend"
        return
    with pytest.raises(SystemFileError) as info:
        get_system(str(path))
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"system file {path}"), message
    for needle in needles:
        assert needle in message, message


def test_every_built_in_system_and_the_readme_pendulum_pass_the_check(user_system_file):
    from learnest_codegen.systems.check import check_system

    for system in _systems(user_system_file):
        check_system(system, system.name)


def test_a_system_built_in_python_counts_its_values():
    """Without a file (no load check) the count is still checked at every evaluation."""
    s = get_system("cartpole")
    short = dataclasses.replace(s, dynamics=lambda ops, x, u, p: s.dynamics(ops, x, u, p)[:3])
    with pytest.raises(ShapeError, match="dynamics returned 3 values, the system has 4 states"):
        short.f(np.zeros(4), np.zeros(1))
    with pytest.raises(ShapeError, match="dynamics returned 3 values"):
        short.casadi_f()


@pytest.mark.parametrize("name", ["q,1", "q\nx", "", " q", "θ", "1q", "q-dot"])
def test_signal_names_are_a_safe_set(name):
    """A comma or a newline in a name wrote run CSVs that could not be read back."""
    from learnest_codegen.systems import Signal

    with pytest.raises(ValueError, match="signal name"):
        Signal(name, "rad")
    Signal("q_dot2", "rad/s")
    with pytest.raises(ValueError, match="one line"):
        Signal("q", "rad\n")


def test_system_names_and_duplicates_are_refused():
    s = get_system("cartpole")
    for name in ("my pendulum", "cart__pole", "cartpole_", "_cartpole", "2d"):
        with pytest.raises(ValueError, match="system name"):
            dataclasses.replace(s, name=name)
    with pytest.raises(ValueError, match=r"states \['p'\] are named twice"):
        dataclasses.replace(s, states=(s.states[0], s.states[0], *s.states[2:]))


def test_the_torch_part_waits_for_the_first_torch_evaluation(tmp_path):
    """A command that never trains does not import torch for the check (2.4 s of CPU); the
    torch evaluation then runs when the system first meets a tensor, with the same one line."""
    import subprocess
    import sys

    path = tmp_path / "pend.py"
    path.write_text(PENDULUM_BODY.format(
        dyn='[qdot, -ops.sin(q) + (q.detach() if hasattr(q, "detach") else 0 * q) + u[0]]',
        meas="[x[0]]"))
    code = ("import sys\nfrom learnest_codegen.systems import get_system\n"
            "s = get_system(sys.argv[1])\nprint('torch' in sys.modules)\n"
            "import torch\nz = lambda n: torch.zeros(n, dtype=torch.float64)\n"
            "try:\n    s.f(z(2), z(1))\n"
            "except Exception as e:\n    print(type(e).__name__, e)\n")
    child = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True,
                           timeout=300)
    lines = child.stdout.strip().splitlines()
    assert lines[0] == "False", child.stderr
    assert lines[1].startswith(f"SystemFileError system file {path}: dynamics gives"), lines
    assert "in torch (training) but" in lines[1]
