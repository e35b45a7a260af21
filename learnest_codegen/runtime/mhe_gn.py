"""ctypes binding of the embedded (Gauss-Newton) MHE, ``codegen/mhe_gn.py``; torch-free.

:class:`CompiledEmbeddedMHE` has the interface of the Python reference
:class:`~learnest_codegen.estimators.mhe.MHE` (``reset``, ``step``, ``x``, ``window``, ``run``,
``arrival_weight``). Each instance owns its workspace (a numpy buffer of
``<prefix>_workspace_size()`` bytes handed to ``<prefix>_init``), so any number of instances
of one library run independently.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from ..errors import ModelMismatchError
from ..estimators.mhe_gn import GaussNewtonSettings
from ..estimators.mhe_problem import MHESettings
from .mhe import _HANDLE, _INT, CompiledMHE

MODES = {"converged": 0, "rti": 1}


class CompiledEmbeddedMHE(CompiledMHE):
    """A compiled embedded MHE (``mhe_gn`` or ``mhe_rti``) loaded from its directory.

    Parameters
    ----------
    directory : folder written by :func:`~learnest_codegen.codegen.mhe_gn.generate_embedded_mhe`.
    expect : manifest entries the library must have; any difference raises
        :class:`ModelMismatchError`.
    settings : weights to use (its horizon must be the library's); default: the manifest's.
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

    def signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        return {**super().signatures(), "set_options": (_INT, [_HANDLE, _INT, _INT, self.c_real]),
                "iterations": (_INT, [_HANDLE]), "real_size": (_INT, [])}

    @property
    def iterations(self) -> int:
        """Gauss-Newton iterations of the last step."""
        return int(self._c["iterations"](self._started("iterations")))

    def _configure(self, handle: int) -> None:
        s = self.solver
        max_iterations = self.c_int(s.max_iterations, "max_iterations", "GaussNewtonSettings.max_iterations")
        self.check_status("reset", self._c["set_options"](handle, MODES[s.mode], max_iterations,
                                                          s.tolerance))
