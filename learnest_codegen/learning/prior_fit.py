"""Grey-box priors: fit prior parameters to state observations before the net learns the rest.

A prior parameter that enters the dynamics linearly (a gain, a damping, a rate) can be fitted by
linear least squares on the same observer states the net is trained on: the finite-difference
derivative of the residual states, ``(zeta_{k+1} - zeta_k) / dt``, against the prior at the
midpoint ``(zeta_k + zeta_{k+1}) / 2``. What the fitted prior explains, the net need not learn,
and a linear term extrapolates as a line where a net would bend. :func:`fitted_system` gives the
system with the fitted parameters; :func:`~learnest_codegen.learning.runs.train_on_runs` uses it
(``fit_prior``) and stores the parameters in ``model.json`` (``prior_params``), which
:func:`~learnest_codegen.learning.model.load_model` applies.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import numpy as np

from ..errors import DataError, UnknownNameError
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
    """Least-squares values of the prior parameters ``names`` on recordings' state observations.

    Parameters
    ----------
    system : whose prior ``f`` is fitted; its other parameters stay as they are.
    names : parameters that enter ``f`` linearly (checked: :class:`DataError` otherwise).
    zetas, us : per recording, observer states ``(T_i, nx)`` and inputs ``(T_i, nu)``.
    dt : sampling period [s].

    Only the residual states' rows (``system.residual_state_names``) are fitted: the others are
    kinematics the parameters should not bend.
    """
    names = list(names)
    if not names:
        return {}
    fitted_system(system, dict.fromkeys(names, 0.0))  # validates the names
    rows = [system.state_names.index(n) for n in system.residual_state_names]
    mids = np.vstack([0.5 * (z[:-1] + z[1:]) for z in zetas])
    inputs = np.vstack([np.asarray(u, float)[:-1] for u in us])
    target = np.vstack([np.diff(np.asarray(z, float), axis=0) / dt for z in zetas])[:, rows]

    def prior(values: dict[str, float]) -> np.ndarray:
        return np.asarray(fitted_system(system, values).f(mids, inputs))[:, rows]

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
    theta, *_ = np.linalg.lstsq(np.column_stack(columns), (target - base).reshape(-1), rcond=None)
    return {name: float(value) for name, value in zip(names, theta)}
