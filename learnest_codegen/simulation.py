"""Simulating a system's true dynamics to produce runs with known truth.

The truth is integrated with scipy's RK45 at tight tolerances, sample interval by sample
interval with the input held constant (zero-order hold, as the estimators assume).
Measurements get zero-mean Gaussian noise of ``system.noise.measurement_std``. The truth itself
is noise-free: the paper's "noise on all states" enters as noise on full-state observations
(:func:`noisy_states`), used by the full-state training variant.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.integrate import RK45

from .data import Run
from .errors import DataError, ShapeError, SolverError
from .systems import System

RTOL, ATOL = 1e-10, 1e-12
#: Integrator steps allowed within one sample interval: a few at the tolerances above for the
#: built-in systems; more means dynamics too stiff or too fast for an explicit integrator at
#: ``dt`` (a spring of 1e14 N/m needs about 1e6 per 10 ms), which would otherwise run for hours.
MAX_STEPS_PER_SAMPLE = 10_000
#: The longest run ``simulate`` makes (a 2 ms system: 33 minutes; about 150 MB of float64 for
#: the quadrotor's 19 columns).
MAX_SAMPLES = 1_000_000


class _NonFinite(Exception):
    """The dynamics returned NaN or inf (carries where, for the message)."""


def simulate(system: System, seed: int, *, duration: float | None = None,
             variant: str = "true", x0: np.ndarray | None = None) -> Run:
    """Simulate ``system`` (true dynamics by default) with its excitation input.

    Parameters
    ----------
    system : the system; its ``dt``, ``duration``, ``x0``, ``excitation`` and noise are used.
    seed : seeds the excitation's randomness and the measurement noise.
    duration : overrides ``system.duration`` [s]; at least two samples, at most
        :data:`MAX_SAMPLES`.
    variant : ``"true"`` or ``"prior"`` dynamics.
    x0 : (nx,) overrides ``system.x0``.

    Returns
    -------
    Run with ``T = round(duration / dt)`` samples, truth included.

    Raises
    ------
    SolverError : the dynamics returned a non-finite value, or needed more than
        :data:`MAX_STEPS_PER_SAMPLE` integrator steps within one sample; the message names the
        time and the state.
    """
    rng = np.random.default_rng(seed)
    T = _samples(system, system.duration if duration is None else duration)
    t = np.arange(T) * system.dt
    u = np.asarray(system.excitation(t, rng), dtype=float)
    if u.shape != (T, system.nu) or not np.all(np.isfinite(u)):
        raise ShapeError(f"simulation of {system.name!r}: excitation(t, rng) must return finite "
                         f"values of shape ({T}, {system.nu}), got shape {u.shape}")
    x = np.empty((T, system.nx))
    x[0] = system.x0 if x0 is None else x0
    if not np.all(np.isfinite(x[0])):
        raise DataError(f"simulation of {system.name!r}: x0 {x[0].tolist()} is not finite")
    for k in range(T - 1):
        x[k + 1] = _integrate(system, variant, x[k], u[k], system.dt, t[k])
    y_clean = system.h(x, u)
    y = y_clean + rng.normal(size=y_clean.shape) * np.asarray(system.noise.measurement_std)
    return Run(t, u, y, x, system.name)


def _samples(system: System, duration) -> int:
    """``round(duration / dt)``, checked: a finite run of 2 to :data:`MAX_SAMPLES` samples."""
    duration = float(duration)
    T = round(duration / system.dt) if math.isfinite(duration) else None
    if T is None or not 2 <= T <= MAX_SAMPLES:
        raise DataError(f"simulation of {system.name!r}: duration {duration:g} s must give 2 to "
                        f"{MAX_SAMPLES} samples of dt = {system.dt:g} s "
                        f"({2 * system.dt:g} to {MAX_SAMPLES * system.dt:g} s)")
    return T


def integrate_interval(system: System, variant: str, x: np.ndarray, u: np.ndarray, dt: float,
                       t0: float = 0.0) -> np.ndarray:
    """The state ``dt`` after ``x`` under the held input ``u``, as :func:`simulate` steps it
    (``variant``: ``"true"`` or ``"prior"`` dynamics; ``t0`` only names the time in errors)."""
    return _integrate(system, variant, x, u, dt, t0)


def _integrate(system: System, variant: str, x: np.ndarray, u: np.ndarray, dt: float,
               t0: float) -> np.ndarray:
    """One sample interval by RK45 (solve_ivp's stepping, with a step limit and finite values)."""
    def rhs(t, s):
        with np.errstate(all="ignore"):  # a non-finite value is reported below, with its time
            xdot = system.f(s, u, variant=variant)
        if not np.all(np.isfinite(xdot)):
            raise _NonFinite(t, s, xdot)
        return xdot

    where = f"simulation of {system.name!r} ({variant} dynamics)"
    try:
        solver = RK45(rhs, 0.0, x, dt, rtol=RTOL, atol=ATOL)
        message = ""
        for _ in range(MAX_STEPS_PER_SAMPLE):
            message = solver.step()
            if solver.status != "running":
                break
        else:
            raise SolverError(f"{where}: more than {MAX_STEPS_PER_SAMPLE} integrator steps in the "
                              f"sample at t = {t0:.6g} s (reached t = {t0 + solver.t:.9g} s, step "
                              f"{solver.step_size:.3g} s) from x = {_round(x)}: the dynamics are too "
                              f"stiff or too fast for dt = {dt:g} s")
    except _NonFinite as exc:
        t, s, xdot = exc.args
        raise SolverError(f"{where}: the dynamics returned {_round(xdot)} at t = {t0 + t:.6g} s, "
                          f"x = {_round(s)}, u = {_round(u)}; the state is no longer finite or left "
                          "the domain of the equations") from None
    if solver.status == "failed":
        raise SolverError(f"{where} failed at t = {t0 + solver.t:.6g} s from x = {_round(solver.y)}: "
                          f"{message} (the state grows without bound?)")
    return solver.y


def _round(v) -> list:
    return [float(f"{a:.6g}") for a in np.ravel(v)]


def noisy_states(run: Run, system: System, seed: int) -> np.ndarray:
    """Full-state observations: the truth plus N(0, ``noise.state_std``) per state, ``(T, nx)``."""
    if run.x is None:
        raise DataError("full-state observations need a run with truth (x_ columns)")
    rng = np.random.default_rng(seed + 7919)  # offset: independent of the measurement noise
    return run.x + rng.normal(size=run.x.shape) * np.asarray(system.noise.state_std)
