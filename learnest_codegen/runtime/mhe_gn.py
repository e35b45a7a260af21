"""ctypes binding of the embedded (Gauss-Newton) MHE, ``codegen/mhe_gn.py``; torch-free.

:class:`CompiledEmbeddedMHE` has the interface of the Python reference
:class:`~learnest_codegen.estimators.mhe.MHE` and of :class:`CompiledMHE`, plus the
Gauss-Newton iterations of the last step and the solver options.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ..errors import ModelMismatchError
from ..estimators.mhe_gn import GaussNewtonSettings
from ..estimators.mhe_problem import MHESettings
from .base import HANDLE, INT, _locked
from .mhe import CompiledMHE

MODES = {"converged": 0, "rti": 1}


class CompiledEmbeddedMHE(CompiledMHE):
    """A compiled embedded MHE (``mhe_gn`` or ``mhe_rti``) loaded from its directory.

    Parameters
    ----------
    directory : folder written by :func:`~learnest_codegen.codegen.mhe_gn.generate_embedded_mhe`.
    expect : manifest entries the library must have; any difference raises
        :class:`ModelMismatchError`.
    settings : tuning to use (its horizon must be the library's); default: the manifest's.
    solver : mode, iteration limit and tolerance to use (its precision must be the
        library's); default: the manifest's.

    Attributes
    ----------
    x : (nx,) current estimate; window : (N+1, nx); iterations : Gauss-Newton iterations of
    the last step.
    """

    ESTIMATORS = ("mhe_gn", "mhe_rti")
    SERIALISE = False  # no static memory: handles of one library run in parallel

    def __init__(self, directory: Path, *, expect: Mapping[str, Any] | None = None,
                 settings: MHESettings | None = None, solver: GaussNewtonSettings | None = None):
        super().__init__(directory, expect=expect, settings=settings)
        m = self.manifest
        self.solver = solver or GaussNewtonSettings.from_json(m["solver"])
        if self.solver.precision != m["precision"]:
            raise ModelMismatchError(f"{self.where}: solver precision {self.solver.precision!r}, "
                                     f"the library was generated in {m['precision']!r}")

    def extra_signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        return {**super().extra_signatures(),
                "set_options": (INT, [HANDLE, INT, INT, self.c_real]), "iterations": (INT, [HANDLE])}

    @property
    @_locked
    def iterations(self) -> int:
        """Gauss-Newton iterations of the last step."""
        return int(self._c["iterations"](self._started("iterations")))

    def _configure(self) -> None:
        s = self.solver
        max_iterations = self.c_int(s.max_iterations, "max_iterations", "GaussNewtonSettings.max_iterations")
        self.check_status("reset", self._c["set_options"](self._handle, MODES[s.mode], max_iterations,
                                                          s.tolerance))
