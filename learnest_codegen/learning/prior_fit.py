"""Grey-box priors: fit prior parameters to state observations before the net learns the rest.

The parameters minimise the paper's one-step loss (eq. 11, the loss the net is then trained
with) of the prior alone on the observer states: ``sum ||zeta_{k+1} - RK4(f_prior)(zeta_k,
u_k)||^2`` over every pair of every recording. Parameters that enter the dynamics linearly (a
gain, a damping, a rate) start from the linear least-squares fit of the forward difference
``(zeta_{k+1} - zeta_k) / dt`` against ``f_prior(zeta_k, u_k)``; a few Gauss-Newton steps then
take the RK4 step into account. What the fitted prior explains, the net need not learn, and a
linear term extrapolates as a line where a net would bend.
:func:`~learnest_codegen.learning.runs.train_on_runs` fits them (``fit_prior``) and stores them
in ``model.json`` (``prior_params``), which :func:`~learnest_codegen.learning.model.load_model`
applies.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from ..errors import DataError, UnknownNameError
from ..integrators import rk4_step
from ..systems import System

__all__ = ["fit_linear_params", "fitted_system"]


def fitted_system(system: System, params: dict[str, float]) -> System:
    """``system`` with prior parameters ``params`` (names it already has) replaced."""
    unknown = sorted(set(params) - set(system.params))
    if unknown:
        raise UnknownNameError(f"system {system.name!r} has no prior parameter(s) {unknown}; it has "
                               f"{sorted(system.params)}")
    return dataclasses.replace(system, params={**system.params, **{k: float(v) for k, v in params.items()}})


def fit_linear_params(system: System, names: Sequence[str], zetas: Sequence[np.ndarray],
                      us: Sequence[np.ndarray], dt: float) -> dict[str, float]:
    """The prior parameters ``names`` that minimise the one-step RK4 loss on recordings.

    Parameters
    ----------
    system : whose prior ``f`` is fitted; its other parameters stay as they are.
    names : parameters that enter ``f`` linearly (checked: :class:`DataError` otherwise).
    zetas, us : per recording, observer states ``(T_i, nx)`` and inputs ``(T_i, nu)``.
    dt : sampling period [s].
    """
    from scipy.optimize import least_squares

    names = list(names)
    if not names:
        return {}
    fitted_system(system, dict.fromkeys(names, 0.0))  # validates the names
    now = np.vstack([np.asarray(z, float)[:-1] for z in zetas])
    nxt = np.vstack([np.asarray(z, float)[1:] for z in zetas])
    inputs = np.vstack([np.asarray(u, float)[:-1] for u in us])
    start = _euler_least_squares(system, names, now, nxt, inputs, dt)

    def residual(theta: np.ndarray) -> np.ndarray:
        f = fitted_system(system, dict(zip(names, theta))).f
        return (nxt - rk4_step(f, now, inputs, dt)).reshape(-1)

    result = least_squares(residual, start, method="lm", x_scale="jac")
    return {name: float(value) for name, value in zip(names, result.x)}


def _euler_least_squares(system: System, names: list[str], now: np.ndarray, nxt: np.ndarray,
                         inputs: np.ndarray, dt: float) -> np.ndarray:
    """Linear least squares of ``(zeta_{k+1} - zeta_k) / dt`` on ``f(zeta_k, u_k)``, whose
    columns are the parameters' contributions (each checked to be linear)."""

    def prior(values: dict[str, float]) -> np.ndarray:
        return np.asarray(fitted_system(system, values).f(now, inputs))

    start = {name: float(system.params[name]) for name in names}
    at_start = prior(start)
    columns = []
    for name in names:
        one = prior({**start, name: start[name] + 1.0}) - at_start
        two = prior({**start, name: start[name] + 2.0}) - at_start
        finite = np.isfinite(one).all() and np.isfinite(two).all()
        if not finite or not np.allclose(two, 2.0 * one, rtol=1e-9, atol=1e-12 * (1.0 + np.abs(one).max())):
            raise DataError(f"fit_linear_params: parameter {name!r} of system {system.name!r} does not "
                            "enter the dynamics linearly; it cannot be fitted by least squares")
        columns.append(one.reshape(-1))
    base = at_start - sum(start[n] * c.reshape(at_start.shape) for n, c in zip(names, columns))
    target = (nxt - now) / dt - base
    theta, *_ = np.linalg.lstsq(np.column_stack(columns), target.reshape(-1), rcond=None)
    return theta
