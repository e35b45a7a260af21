"""The moving-horizon window of the MHE, line by line the C kit's ``learnest_window.h``.

The window holds what the cost of eq. (2) reads (:mod:`.mhe_problem`): the arrival prior
``xbar``; per stage ``i`` (``N+1`` of them, oldest first) the input ``U_i`` applied since the
previous sample, the measurement ``Y_i``, the mask ``m_i`` (1: stage ``i`` holds a sample) and
the per-output weights ``G_i`` (1: output ``j`` of sample ``i`` enters the cost; 0: it was
missing, rejected by the gate, or folded into a restart prior). ``Y`` holds a measurement
only where ``G`` is 1 (0 elsewhere), so a missing output's value is never read. Both the
Python MHE and the compiled MHEs keep their windows by these rules; ``tests/test_ckit.py``
runs both on random sequences and compares every array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .mhe_problem import ParamLayout


@dataclass
class Window:
    """The window's blocks (ParamLayout's first ones): ``xbar (nx,)``, ``U (N+1, nu)``,
    ``Y (N+1, ny)``, ``mask (N+1,)``, ``G (N+1, ny)``."""

    xbar: np.ndarray
    U: np.ndarray
    Y: np.ndarray
    mask: np.ndarray
    G: np.ndarray

    @classmethod
    def empty(cls, layout: ParamLayout, x0: np.ndarray) -> "Window":
        """An empty window with prior ``x0`` (``learnest_window_reset``)."""
        n1 = layout.horizon + 1
        return cls(np.array(x0, dtype=float), np.zeros((n1, layout.nu)), np.zeros((n1, layout.ny)),
                   np.zeros(n1), np.zeros((n1, layout.ny)))

    def copy(self) -> "Window":
        return Window(*(a.copy() for a in (self.xbar, self.U, self.Y, self.mask, self.G)))

    def shift(self, X: np.ndarray) -> None:
        """One stage older (``learnest_window_shift``): once the window was full the arrival
        prior moves on to the solution ``X``'s second stage; the last stage keeps its values
        until :meth:`open`."""
        if self.mask[0] == 1:
            self.xbar = X[1].copy()
        for block in (self.U, self.Y, self.mask, self.G):
            block[:-1] = block[1:]

    def open(self, u: np.ndarray) -> None:
        """The new sample's stage: input ``u``, mask 1, no measurement yet."""
        self.U[-1], self.Y[-1], self.G[-1], self.mask[-1] = u, 0.0, 0.0, 1.0

    def weigh(self, y: np.ndarray, keep: np.ndarray) -> None:
        """The new sample's outputs: ``G = keep``, ``Y = y`` where kept, else 0."""
        self.G[-1] = np.where(keep, 1.0, 0.0)
        self.Y[-1] = np.where(keep, y, 0.0)

    def parameters(self, layout: ParamLayout, Q: np.ndarray, R: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The NLP's parameter vector: the window, then the weights (column-major)."""
        p = np.zeros(layout.size)
        for name, block in (("xbar", self.xbar), ("U", self.U), ("Y", self.Y), ("mask", self.mask),
                            ("G", self.G)):
            p[layout.slice(name)] = block.ravel()
        for name, W in (("Q", Q), ("R", R), ("P", P)):
            p[layout.slice(name)] = W.ravel(order="F")
        return p
