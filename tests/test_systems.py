"""A system is written once; its numpy, torch and CasADi forms must agree (to 1e-12)."""

from __future__ import annotations

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


def test_cartpole_matches_equation_13_at_rest():
    """Pole upright, at rest, no force: an equilibrium; a force accelerates the cart by F/(mc+mp)
    corrected for the pole's reaction, which the closed form below states independently."""
    s = get_system("cartpole")
    np.testing.assert_allclose(s.f(np.zeros(4), np.zeros(1)), np.zeros(4), atol=1e-15)
    F, mc, mp, l = 2.0, 1.0, 0.1, 0.5  # at alpha = 0: alpha_dd = -F/(l(4/3 - mp/(mc+mp)))
    a_dd = -F / (l * (4 / 3 - mp / (mc + mp)))
    p_dd = (F - mp * l * a_dd) / (mc + mp)
    np.testing.assert_allclose(s.f(np.zeros(4), np.array([F])), [0, p_dd, 0, a_dd], rtol=1e-14)
    assert s.f(np.zeros(4), np.array([F]), variant="true")[1] < p_dd  # heavier true cart


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
