"""The contract every estimator keeps, Python reference and compiled library alike.

An estimator is made for one discrete model (``nx`` states, ``nu`` inputs, ``ny`` outputs, a
fixed ``dt``) and is used as::

    est.reset(x0, P0)          # start (P0 optional: the settings' initial covariance)
    x = est.step(u, y)         # one sample: predict with u (applied since the last sample), update with y
    x = est.predict(u)         # one sample with no measurement at all
    est.set_noise(Q=..., R=...)  # retune the running estimator (state, covariance, window kept)
    est.x                      # the current estimate, (nx,)
    X = est.run(U, Y, x0, P0)  # reset, then step over a whole run: (T, nx)

* ``run`` equals ``reset`` followed by ``step(U[max(k-1, 0)], Y[k])`` for every sample ``k``;
  sample 0 is an update only.
* **Missing outputs.** NaN in ``y`` means "no sample of this output" (a sensor slower than the
  estimator, a dropout): a step always predicts, a missing output contributes nothing, and a
  sample with every output missing is a pure prediction -- ``predict(u)`` is exactly
  ``step(u, [nan] * ny)``. The innovation gate neither rejects a missing output nor counts it
  towards recovery (:mod:`.gate`); ``missing`` reports the last step's. An infinite ``y`` is an
  error, not a missing output.
* **Inputs** pass a plausibility check (finite, inside the settings' ``input_limits``): an
  implausible component is replaced by its last accepted value and reported, not raised
  (:mod:`.inputs`).
* **Run-time tuning.** ``set_noise(Q=None, R=None, P_arrival=None)`` takes covariances
  (process ``(nx, nx)``, measurement ``(ny, ny)``, and for the MHEs the running arrival
  covariance ``(nx, nx)``); what is not given stays. ``reset`` returns to the settings'.
* Other bad inputs are checked by :mod:`.validation`: a wrong shape raises
  :class:`~..errors.ShapeError`, an infinite ``y`` or a non-finite ``x0`` or covariance
  :class:`~..errors.DataError`; a numerical failure raises :class:`~..errors.SolverError`. In
  every one of these cases the estimator is left as it was.
* ``step`` or ``x`` before ``reset`` raises (nothing to filter from).
* ``last_status`` holds the step's status bits: 0 OK, 1 an output was rejected by the gate,
  2 an input component was replaced (none of them is an error).

``tests/test_estimator_contract.py`` runs every registered estimator, in Python and in C,
through the same checks (the compiled libraries take missing outputs as validity flags);
:func:`takes_missing_outputs` says whether an estimator keeps the whole contract. Torch-free.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Estimator(Protocol):
    """What :func:`learnest_codegen.pipeline.evaluate` and the studies rely on.

    ``isinstance(est, Estimator)`` checks the members; before Python 3.12 it reads ``x``, which
    raises before ``reset``.
    """

    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start from the mean ``x0 (nx,)`` and covariance ``P0 (nx, nx)``."""

    def step(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Filter one sample (NaN in ``y``: missing output); return the estimate ``(nx,)``."""

    def predict(self, u: np.ndarray) -> np.ndarray:
        """One sample without measurement: ``step(u, y)`` with every output missing."""

    def set_noise(self, Q: np.ndarray | None = None, R: np.ndarray | None = None,
                  P_arrival: np.ndarray | None = None) -> None:
        """Set the process, measurement (and MHE arrival) covariances of the running estimator."""

    @property
    def x(self) -> np.ndarray:
        """The current estimate ``(nx,)`` (a copy)."""

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None) -> np.ndarray:
        """``reset(x0, P0)`` then one ``step`` per sample; ``(T, nx)`` estimates."""


def takes_missing_outputs(estimator) -> bool:
    """Whether ``estimator`` keeps the whole contract above, missing outputs included (the
    Python references do; a compiled library does once its C API takes them). Judged by the
    class (``estimator`` may be one), so it can be asked before ``reset`` or building."""
    cls = estimator if isinstance(estimator, type) else type(estimator)
    return all(callable(getattr(cls, name, None)) for name in ("predict", "set_noise"))
