"""Parameters estimated online: a system whose chosen parameters are states.

:func:`estimate_params` turns parameters of a system (a motor constant, a mass, a thrust gain
that falls with the battery) into augmented states with a random-walk model: the parameter's
derivative is 0 in the dynamics, and the process noise of its state (``drift_std``, per sample)
lets every estimator move it, so the MHEs, the UKF and the EKF estimate it like any other
unmeasured state, in Python and in C. A system file declares it as its ``SYSTEM``::

    from learnest_codegen.systems.cartpole import CARTPOLE
    from learnest_codegen.systems.params import Estimated, estimate_params

    SYSTEM = estimate_params(CARTPOLE, {"m_c": Estimated(initial_std=0.3, drift_std=2e-4,
                                                         bounds=(0.5, 3.0))})

``bounds`` (optional, ``(lo, hi)``, ``None`` an open side) is the parameter's box: the MHEs keep
its state inside it (it joins the system's ``state_bounds``, the default of every MHE's
``MHESettings.state_bounds``), in Python and in C, in both precisions. For simulated data the
true parameter may drift (``Estimated.true_rate``, units per second): the simulation then
integrates it from the system's ``x0`` (the parameter's prior value).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Mapping

from ..errors import SettingsError
from .base import Signal, System


@dataclass(frozen=True)
class Estimated:
    """How a parameter is estimated: ``initial_std`` of its prior value, ``drift_std`` of its
    random walk per sample, (simulation only) ``true_rate``, the true parameter's drift per
    second, and ``bounds``, the ``(lo, hi)`` the MHEs keep it in (``None``: unbounded)."""

    initial_std: float
    drift_std: float
    true_rate: float = 0.0
    unit: str = ""
    bounds: tuple[float | None, float | None] | None = None

    def __post_init__(self) -> None:
        if not (self.initial_std > 0 and self.drift_std > 0):
            raise SettingsError(f"Estimated: initial_std and drift_std must be positive, got "
                                f"{self.initial_std}, {self.drift_std}")


def estimate_params(system: System, estimated: Mapping[str, Estimated], *,
                    name: str | None = None) -> System:
    """``system`` with the parameters ``estimated`` (name -> :class:`Estimated`) as states
    appended after its own, started at their prior values (``system.params``); its name is
    ``<system>_<parameter>_...`` unless ``name`` is given."""
    names = tuple(estimated)
    unknown = [p for p in names if p not in system.params]
    if not names or unknown:
        raise SettingsError(f"estimate_params: {unknown or 'no parameter'} not among the parameters "
                            f"{sorted(system.params)} of system {system.name!r}")
    n = system.nx
    specs = [estimated[p] for p in names]

    def augmented(fn, true: bool):
        def dynamics(ops, x, u, p):
            q = {**p, **{k: x[n + i] for i, k in enumerate(names)}}
            rates = [x[n + i] * 0 + (s.true_rate if true else 0.0) for i, s in enumerate(specs)]
            return [*fn(ops, x[:n], u, q), *rates]
        return dynamics

    def measurement(ops, x, u, p):
        return system.measurement(ops, x[:n], u, p)

    noise = system.noise
    extend = lambda values, attr: (*values, *(getattr(s, attr) for s in specs))  # noqa: E731
    return dataclasses.replace(
        system, name=name or "_".join((system.name, *names)),
        description=f"{system.description} Estimated online: {', '.join(names)}.".strip(),
        states=(*system.states, *(Signal(p, s.unit, f"parameter {p}, estimated")
                                  for p, s in zip(names, specs))),
        params={k: v for k, v in system.params.items() if k not in names},
        true_params={k: v for k, v in system.true_params.items() if k not in names},
        dynamics=augmented(system.dynamics, False),
        true_dynamics=augmented(system.true_dynamics or system.dynamics, True),
        measurement=measurement,
        noise=dataclasses.replace(noise, process_std=extend(noise.process_std, "drift_std"),
                                  state_std=extend(noise.state_std, "drift_std"),
                                  initial_std=extend(noise.initial_std, "initial_std")),
        x0=(*system.x0, *(float(system.params[p]) for p in names)),
        state_bounds=_bounds(system, specs))


def _bounds(system: System, specs) -> tuple | None:
    """The augmented system's state bounds: the system's own (open where it has none), then
    each parameter's; ``None`` when nothing is bounded."""
    if system.state_bounds is None and all(s.bounds is None for s in specs):
        return None
    own = system.state_bounds or ((None, None),) * system.nx
    return (*own, *(s.bounds or (None, None) for s in specs))
