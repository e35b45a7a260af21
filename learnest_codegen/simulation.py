"""Simulating a system's true dynamics to produce runs with known truth.

The truth is integrated with scipy's RK45 at tight tolerances, sample interval by sample
interval with the input held constant (zero-order hold, as the estimators assume).
Measurements get zero-mean Gaussian noise of ``system.noise.measurement_std``. The truth itself
is noise-free: the paper's "noise on all states" enters as noise on full-state observations
(:func:`noisy_states`), used by the full-state training variant.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from .data import Run
from .errors import DataError
from .systems import System

RTOL, ATOL = 1e-10, 1e-12


def simulate(system: System, seed: int, *, duration: float | None = None,
             variant: str = "true", x0: np.ndarray | None = None) -> Run:
    """Simulate ``system`` (true dynamics by default) with its excitation input.

    Parameters
    ----------
    system : the system; its ``dt``, ``duration``, ``x0``, ``excitation`` and noise are used.
    seed : seeds the excitation's randomness and the measurement noise.
    duration : overrides ``system.duration`` [s].
    variant : ``"true"`` or ``"prior"`` dynamics.
    x0 : (nx,) overrides ``system.x0``.

    Returns
    -------
    Run with ``T = round(duration / dt)`` samples, truth included.
    """
    rng = np.random.default_rng(seed)
    T = int(round((duration or system.duration) / system.dt))
    t = np.arange(T) * system.dt
    u = system.excitation(t, rng)
    x = np.empty((T, system.nx))
    x[0] = system.x0 if x0 is None else x0
    for k in range(T - 1):
        x[k + 1] = _integrate(system, variant, x[k], u[k], system.dt)
    y_clean = system.h(x, u)
    y = y_clean + rng.normal(size=y_clean.shape) * np.asarray(system.noise.measurement_std)
    return Run(t, u, y, x, system.name)


def _integrate(system: System, variant: str, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    sol = solve_ivp(lambda _t, s: system.f(s, u, variant=variant), (0.0, dt), x,
                    method="RK45", rtol=RTOL, atol=ATOL)
    if not sol.success:
        raise RuntimeError(f"simulation of {system.name!r} failed: {sol.message}")
    return sol.y[:, -1]


def noisy_states(run: Run, system: System, seed: int) -> np.ndarray:
    """Full-state observations: the truth plus N(0, ``noise.state_std``) per state, ``(T, nx)``."""
    if run.x is None:
        raise DataError("full-state observations need a run with truth (x_ columns)")
    rng = np.random.default_rng(seed + 7919)  # offset: independent of the measurement noise
    return run.x + rng.normal(size=run.x.shape) * np.asarray(system.noise.state_std)
