"""The contract every estimator keeps, Python reference and compiled library alike.

An estimator is made for one discrete model (``nx`` states, ``nu`` inputs, ``ny`` outputs, a
fixed ``dt``) and is used as::

    est.reset(x0, P0)          # start (P0 optional: the settings' initial covariance)
    x = est.step(u, y)         # one sample: predict with u (applied since the last sample), update with y
    est.x                      # the current estimate, (nx,)
    X = est.run(U, Y, x0, P0)  # reset, then step over a whole run: (T, nx)

* ``run`` equals ``reset`` followed by ``step(U[max(k-1, 0)], Y[k])`` for every sample ``k``;
  sample 0 is an update only.
* Inputs are checked by :mod:`.validation`: a wrong shape raises :class:`~..errors.ShapeError`,
  a NaN or infinite value :class:`~..errors.DataError`; a numerical failure raises
  :class:`~..errors.SolverError`. In every one of these cases the estimator is left as it was.
* ``step`` or ``x`` before ``reset`` raises (nothing to filter from).

``tests/test_estimator_contract.py`` runs every registered estimator, in Python and in C,
through the same checks. Torch-free.
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
        """Filter one sample; return the estimate ``(nx,)``."""

    @property
    def x(self) -> np.ndarray:
        """The current estimate ``(nx,)`` (a copy)."""

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None) -> np.ndarray:
        """``reset(x0, P0)`` then one ``step`` per sample; ``(T, nx)`` estimates."""
