"""ctypes binding of a compiled MHE (``codegen/mhe.py``); torch-free.

:class:`CompiledMHE` has the interface of the Python reference
:class:`~learnest_codegen.estimators.mhe.MHE` (``reset``, ``step``, ``x``, ``window``, ``run``,
``arrival_weight``) over the C kit's API (``runtime/base.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import ModelMismatchError
from ..estimators import validation
from ..estimators.mhe import NO_COVARIANCE
from ..estimators.mhe_problem import MHESettings
from .base import HANDLE, INT, CompiledEstimator, _locked


class CompiledMHE(CompiledEstimator):
    """A compiled MHE loaded from its directory.

    Parameters
    ----------
    directory : folder written by :func:`~learnest_codegen.codegen.mhe.generate_mhe`.
    expect : manifest entries the library must have, e.g. ``{"system": "cartpole",
        "model_kind": "knode", "model_hash": h}``; any difference raises
        :class:`ModelMismatchError`.
    settings : tuning to use (its horizon must be the library's); default: the settings
        recorded in the manifest.

    Attributes
    ----------
    x : (nx,) current estimate; window : (N+1, nx) current window solution, oldest first.
    rejected, last_status, rejections : the innovation gate's report, as :class:`MHE`'s.
    """

    ESTIMATORS = ("mhe",)
    #: The Ipopt solver's C keeps its memories in one static pool per library (CasADi's
    #: checkout/release), so two handles of one library must not solve at the same time
    #: (two threads failed with NO_MEMORY in 1 of 4 runs): ``init``, ``reset``, ``step`` and
    #: ``run`` hold :func:`~learnest_codegen.runtime.base.library_lock`. The embedded MHE
    #: keeps everything in its workspace.
    SERIALISE = True

    def __init__(self, directory: Path, *, expect: Mapping[str, Any] | None = None,
                 settings: MHESettings | None = None):
        super().__init__(directory, expect, settings)

    def extra_signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        R = self.real_pointer
        return {"get_window": (INT, [HANDLE, R]), "get_arrival": (INT, [HANDLE, R]),
                "set_arrival": (INT, [HANDLE, R]), "get_arrival_weight": (INT, [HANDLE, R])}

    def _settings(self, settings: MHESettings | None) -> MHESettings:
        settings = settings or MHESettings.from_json(self.manifest["settings"])
        if settings.horizon != self.horizon:
            raise ModelMismatchError(f"{self.where}: settings.horizon is {settings.horizon}, "
                                     f"the library was generated for {self.horizon}")
        settings.check(self.nx, self.ny, self.where)
        return settings

    @_locked
    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """As :meth:`MHE.reset <learnest_codegen.estimators.mhe.MHE.reset>`: ``P0`` (default: the
        settings' arrival covariance) is the first prior's covariance, carried forward in C
        while it is larger than the running arrival covariance, which goes back to the
        build's (or, with other settings given, to theirs)."""
        super().reset(x0, P0)
        P = self.settings.covariances()[2]
        built = MHESettings.from_json(self.manifest["settings"]).covariances()[2]
        if not np.array_equal(P, built):
            self.check_status("reset", self._c["set_arrival"](self._handle,
                                                              self.real_array(P, exact=True)))

    def _covariances(self, P0):
        Q, R, P = self.settings.covariances()
        if P0 is not None:
            P = validation.covariance(f"{type(self).__name__}.reset: P0", P0, self.nx, definite=True,
                                      precision=self.precision)
        return P, Q, R

    @property
    def P(self):
        """Not available: an MHE has no state covariance (raises AttributeError)."""
        raise AttributeError(NO_COVARIANCE)

    @property
    @_locked
    def window(self) -> np.ndarray:
        return self.read("window", "get_window", (self.horizon + 1, self.nx)).astype(float)

    @property
    @_locked
    def arrival_covariance(self) -> np.ndarray:
        """(nx, nx) the running arrival covariance (``set_noise(P_arrival=...)``'s)."""
        return self.read("arrival_covariance", "get_arrival", (self.nx, self.nx)).astype(float)

    @property
    @_locked
    def arrival_weight(self) -> np.ndarray:
        """(nx, nx) the weight of the arrival cost in force: the running one, or the inverse of
        a first prior's covariance carried forward (as :attr:`MHE.arrival_weight`)."""
        return self.read("arrival_weight", "get_arrival_weight", (self.nx, self.nx)).astype(float)

    @_locked
    def set_noise(self, Q: np.ndarray | None = None, R: np.ndarray | None = None,
                  P_arrival: np.ndarray | None = None) -> None:
        """New covariances (None keeps one) on the running estimator, its window kept: process
        ``Q``, measurement ``R`` and the arrival cost's ``P_arrival`` (C: ``set_noise`` and
        ``set_arrival``)."""
        if P_arrival is not None:
            P = self.real_array(validation.covariance(f"{type(self).__name__}.set_noise: P_arrival",
                                                      P_arrival, self.nx, definite=True,
                                                      precision=self.precision),
                                exact=True)
            self.check_status("set_noise", self._c["set_arrival"](self._started("set_noise"), P))
        if Q is not None or R is not None:
            super().set_noise(Q, R)
