"""Pre-training observers: measurements and inputs to state observations ``zeta`` (Alg. 1, step 1).

* ``kf``  - the paper's observer for the cartpole: one linear Kalman filter per kinematic chain
  (a measured position and its derivatives, see :class:`~learnest_codegen.systems.KinematicChain`)
  with a constant-acceleration model. It needs no dynamics model, so it does not bake the
  prior's error into the training targets.
* ``rts`` - the same filter followed by the Rauch-Tung-Striebel backward pass (a smoother: each
  ``zeta_i`` uses the whole run, not only the past), through FilterPy.
* ``ukf`` - for systems without kinematic chains: a FilterPy UKF on the RK4-discretised prior.
* ``ekf_rts`` - an extended Kalman filter on the RK4-discretised model plus an RTS backward pass.
  With the prior model its accelerations come from physics plus the data, not from a
  kinematic random walk; with a hybrid model (``residual``) it refines the training targets in
  :func:`~learnest_codegen.learning.training.train_on_run`'s alternating scheme.
* ``linear_rts`` - for a prior that is linear (``f = A x``, ``h = C x``, no input): the exact
  Kalman filter and RTS smoother of that model, with white noise driving the derivatives of
  ``system.residual_state_names`` (for the quadrotor: white jerk) and every output used (the
  quadrotor's accelerometer as well as its position). Intensities by maximum likelihood.
* ``ukf_kf`` - the paper's observer for the ground robot, for systems that declare
  ``planar_pose=(x, y, v, psi)``: a precursory UKF on a kinematic model extracts the
  position and heading through the system's own ``h``, then a linear constant-acceleration KF
  extracts the speed from those positions. Causal filters only.
* ``ukf_rts`` - the same with an RTS backward pass after each stage (the ground robot's default).

The white-jerk intensity of the kinematic filters is chosen per chain by maximising the
innovation log-likelihood over a log grid, so no tuning is needed for a new system.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Callable

from ..data import Run
from ..errors import UnknownNameError
from ..systems import System
from .base import JERK_GRID as JERK_GRID
from .base import Observations as Observations
from .kinematic import _kinematic
from .kinematic import chain_groups as chain_groups
from .kinematic import chain_passes as chain_passes
from .kinematic import inferred_chains as inferred_chains
from .kinematic import kinematic_chains as kinematic_chains
from .kinematic import smooth_states as smooth_states
from .linear import _linear_kf as _linear_kf
from .linear import _linear_prior as _linear_prior
from .linear import linear_rts as linear_rts
from .model_based import _discrete_with_jacobian as _discrete_with_jacobian
from .model_based import _ekf_passes as _ekf_passes
from .model_based import _model_ukf
from .model_based import _rts_backward as _rts_backward
from .model_based import ekf_rts as ekf_rts
from .model_based import innovation_loglik as innovation_loglik
from .planar_pose import _two_stage
from .planar_pose import planar_pose_indices as planar_pose_indices


def observe(run: Run, system: System, method: str | None = None) -> Observations:
    """Turn a run's ``(y, u)`` into state observations with the named observer.

    ``method`` defaults to :func:`choose_observer`'s choice; ``info["chosen_because"]`` then
    says why. Measurements may be missing (NaN in ``run.y``): every observer predicts through
    them and updates with the outputs present.
    """
    reason = None
    if method is None:
        method, reason = choose_observer(system)
    if method not in OBSERVERS:
        raise UnknownNameError(f"unknown observer {method!r}; choose from {sorted(OBSERVERS)}")
    observations = OBSERVERS[method](run, system)
    if reason is None:
        return observations
    return replace(observations, info={**observations.info, "chosen_because": reason})


def choose_observer(system: System) -> tuple[str, str]:
    """The pre-training observer used when none is named, and why.

    A system that names another ``default_observer`` than ``"rts"`` gets it. Otherwise the
    kinematic smoother ``rts`` when every state is in a kinematic chain, declared or read from
    the equations (:func:`~.kinematic.inferred_chains`); else the EKF-RTS smoother on the prior
    (``ekf_rts``).
    """
    if system.default_observer != "rts":
        return system.default_observer, f"the system's default_observer {system.default_observer!r}"
    if system.kinematic_chains:
        return "rts", "the system declares kinematic chains covering its states"
    chains = inferred_chains(system)
    covered = {s for chain in chains for s in chain.states}
    if chains and covered == set(system.state_names):
        listing = ", ".join(" -> ".join(c.states) for c in chains)
        return "rts", f"kinematic chains read from the equations ({listing})"
    missing = [s for s in system.state_names if s not in covered]
    return "ekf_rts", (f"states {missing} are in no kinematic chain (declared or read from the "
                       "equations), so the EKF-RTS smoother on the prior")


OBSERVERS: dict[str, Callable[[Run, System], Observations]] = {
    "kf": lambda run, system: _kinematic(run, system, smooth=False),
    "rts": lambda run, system: _kinematic(run, system, smooth=True),
    "ukf": _model_ukf,
    "ekf_rts": lambda run, system: ekf_rts(run, system),
    "linear_rts": linear_rts,
    "ukf_kf": lambda run, system: _two_stage(run, system, smooth=False),
    "ukf_rts": lambda run, system: _two_stage(run, system, smooth=True),
}
