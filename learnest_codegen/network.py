"""The residual network ``Delta_theta(x, u)``: l4casadi's naive MLP with fixed input scaling.

The MLP is :class:`l4casadi.naive.MultiLayerPerceptron`, whose layers translate one by one into
CasADi operations, so the same object runs in torch (training) and traces into a symbolic CasADi
graph (export). Inputs are standardised with constants fixed from the training data; those
constants are buffers saved with the weights and appear in the exported graph.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import casadi as cs
import numpy as np
import torch
from l4casadi.naive import MultiLayerPerceptron

from .errors import UnknownNameError

ACTIVATIONS = ("Tanh", "Sigmoid", "ReLU", "LeakyReLU")


@dataclass(frozen=True)
class NetworkSettings:
    """Architecture of the residual MLP.

    ``layers`` counts linear layers (the paper's "2 layers, 8 hidden" is ``layers=2,
    hidden=8``: input->8->output).
    """

    layers: int = 2
    hidden: int = 8
    activation: str = "Tanh"

    def __post_init__(self) -> None:
        if self.layers < 2:
            raise ValueError(f"layers must be >= 2 (input and output layer), got {self.layers}")
        if self.hidden < 1:
            raise ValueError(f"hidden must be >= 1, got {self.hidden}")
        if self.activation not in ACTIVATIONS:
            raise UnknownNameError(f"unknown activation {self.activation!r}; choose from {ACTIVATIONS}")

    def to_json(self) -> dict:
        return asdict(self)


class ResidualNet(torch.nn.Module):
    """``Delta(x, u) = MLP((concat(x, u) - mean) / scale)``, float64."""

    def __init__(self, nx: int, nu: int, settings: NetworkSettings = NetworkSettings()):
        super().__init__()
        self.nx, self.nu, self.settings = nx, nu, settings
        self.mlp = MultiLayerPerceptron(nx + nu, settings.hidden, nx, settings.layers - 1,
                                        settings.activation).double()
        self.register_buffer("in_mean", torch.zeros(nx + nu, dtype=torch.float64))
        self.register_buffer("in_scale", torch.ones(nx + nu, dtype=torch.float64))

    def set_input_scaling(self, inputs: np.ndarray) -> None:
        """Fix the standardisation from training inputs ``(M, nx + nu)``."""
        mean, std = inputs.mean(axis=0), inputs.std(axis=0)
        self.in_mean.copy_(torch.as_tensor(mean))
        self.in_scale.copy_(torch.as_tensor(np.where(std > 1e-12, std, 1.0)))

    def forward(self, x: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        z = (torch.cat([x, u], dim=-1) - self.in_mean) / self.in_scale
        return self.mlp(z)

    def casadi(self, x: cs.SX, u: cs.SX) -> cs.SX:
        """The same network as a CasADi expression of columns ``x (nx,1)``, ``u (nu,1)``."""
        mean = self.in_mean.detach().numpy()
        scale = self.in_scale.detach().numpy()
        z = (cs.vertcat(x, u) - mean) / scale
        return self.mlp(z.T).T  # the naive MLP works on row vectors
