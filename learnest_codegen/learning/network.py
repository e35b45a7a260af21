"""The residual network ``Delta_theta(x, u)``: l4casadi's naive MLP with fixed input scaling.

The MLP is :class:`l4casadi.naive.MultiLayerPerceptron`, whose layers translate one by one into
CasADi operations, so the same object runs in torch (training) and traces into a symbolic CasADi
graph (export). Inputs are standardised with constants fixed from the training data; those
constants are buffers saved with the weights and appear in the exported graph.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import casadi as cs
import numpy as np
import torch
from l4casadi.naive import MultiLayerPerceptron

from ..config import ACTIVATIONS, NetworkSettings
from ..errors import SettingsError
from ..systems.backends import TorchOps

__all__ = ["ACTIVATIONS", "NetworkSettings", "ResidualNet", "StackedMLP", "StartT"]

_TORCH_OPS = TorchOps()


class ResidualNet(torch.nn.Module):
    """``Delta(x, u) = MLP((features(x, u) - mean) / scale)``, float64 (training may run on a
    float32 copy; see ``TrainingSettings.precision``).

    ``features`` is ``concat(x, u)`` with every periodic state (an angle, index in ``periodic``)
    replaced by its sine and cosine, so the net sees the same input for ``alpha`` and
    ``alpha + 2 pi`` and never extrapolates in an unwrapped angle.

    ``outputs`` lists the states whose derivative the residual acts on (default: all); the
    others get an exact zero. A position whose derivative is a velocity state is kinematics,
    not physics to be learned: a free residual there only fits observation noise.

    ``inputs`` lists the entries of ``concat(x, u)`` the residual may depend on (default: all).
    Leaving out a coordinate the physics is invariant to (a ground robot's position and
    heading, a cart's position) keeps the net from keying on where the training run went and
    failing wherever the test run goes.

    ``via`` (indices of inputs, with ``prior`` the prior dynamics ``f(x, u)`` in any backend)
    makes the MLP's outputs input corrections instead: ``Delta(x, u) = prior(x, u + G mlp) -
    prior(x, u)`` with ``G`` placing them at ``via``; ``outputs`` is then unused. See
    :attr:`learnest_codegen.systems.System.residual_via_names`.

    ``prior_features`` (indices of states, with ``prior``) appends the prior's derivatives of
    those states, ``prior(x, u)[prior_features]``, to the features. See
    :attr:`learnest_codegen.systems.System.residual_prior_feature_names`.

    ``prior_gains`` (with ``prior_features``) adds, to each output channel ``c``, the prior
    features times learned gains: ``out[c] + sum_k g[c, k](x, u) * prior_k / s_k``, where the
    gains are further MLP outputs and ``s_k`` is prior feature ``k``'s training scale. See
    :attr:`learnest_codegen.systems.System.residual_prior_feature_names` (``residual_prior_gains``).
    """

    def __init__(self, nx: int, nu: int, settings: NetworkSettings = NetworkSettings(),
                 periodic: tuple[int, ...] = (), outputs: tuple[int, ...] | None = None,
                 inputs: tuple[int, ...] | None = None, via: tuple[int, ...] | None = None,
                 prior: Callable | None = None, prior_features: tuple[int, ...] = (),
                 prior_gains: bool = False, prior_terms: Callable | None = None):
        super().__init__()
        #: the prior's derivative as terms, ``prior_terms(ops, xs, us) -> list`` of ``nx`` scalars
        #: (a system's ``dynamics`` with its parameters bound); :meth:`derivative` needs it
        self.prior_terms = prior_terms
        self.via, self.prior_features = tuple(via or ()), tuple(prior_features)
        self.prior_gains = bool(prior_gains)
        if self.prior_gains and not self.prior_features:
            raise SettingsError("ResidualNet: prior_gains multiplies the prior features; give prior_features")
        if self.via and (prior is None or any(not 0 <= i < nu for i in self.via)):
            raise SettingsError(f"ResidualNet: via must index range({nu}) and needs the prior "
                             f"dynamics; got via={self.via}, prior={prior}")
        if self.prior_features and (prior is None or any(not 0 <= i < nx for i in self.prior_features)):
            raise SettingsError(f"ResidualNet: prior_features must index range({nx}) and need the prior "
                             f"dynamics; got prior_features={self.prior_features}, prior={prior}")
        self.prior = prior
        self.nx, self.nu, self.settings, self.periodic = nx, nu, settings, tuple(periodic)
        self.outputs = tuple(range(nx)) if outputs is None else tuple(outputs)
        self.inputs = tuple(range(nx + nu)) if inputs is None else tuple(inputs)
        if not self.outputs or any(not 0 <= i < nx for i in self.outputs):
            raise SettingsError(f"ResidualNet: outputs must be a non-empty subset of range({nx}), "
                             f"got {self.outputs}")
        if not self.inputs or any(not 0 <= i < nx + nu for i in self.inputs):
            raise SettingsError(f"ResidualNet: inputs must be a non-empty subset of range({nx + nu}), "
                             f"got {self.inputs}")
        n_in = len(self.inputs) + sum(1 for i in self.periodic if i in self.inputs) + len(self.prior_features)
        self.channels = len(self.via) or len(self.outputs)
        n_out = self.channels * (1 + len(self.prior_features) if self.prior_gains else 1)
        self.mlp = MultiLayerPerceptron(n_in, settings.hidden, n_out, settings.layers - 1,
                                        settings.activation).double()
        self.register_buffer("in_mean", torch.zeros(n_in, dtype=torch.float64))
        self.register_buffer("in_scale", torch.ones(n_in, dtype=torch.float64))

    def _features(self, parts: list, sin, cos, prior_xdot: list | None = None) -> list:
        keep = [parts[i] for i in self.inputs if i not in self.periodic]
        angles = [f(parts[i]) for i in self.periodic if i in self.inputs for f in (sin, cos)]
        return keep + angles + [prior_xdot[i] for i in self.prior_features]

    def features_numpy(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Network input features of ``x (M, nx)``, ``u (M, nu)`` before standardisation."""
        x, u = np.asarray(x, dtype=np.float64), np.asarray(u, dtype=np.float64)
        parts = list(np.hstack([x, u]).T)
        prior_xdot = list(np.asarray(self.prior(x, u)).T) if self.prior_features else None
        return np.stack(self._features(parts, np.sin, np.cos, prior_xdot), axis=-1)

    def set_input_scaling(self, x: np.ndarray, u: np.ndarray) -> None:
        """Fix the standardisation from training data ``x (M, nx)``, ``u (M, nu)``."""
        feats = self.features_numpy(x, u)
        mean, std = feats.mean(axis=0), feats.std(axis=0)
        self.in_mean.copy_(torch.as_tensor(mean))
        self.in_scale.copy_(torch.as_tensor(np.where(std > 1e-12, std, 1.0)))

    def forward(self, x: torch.Tensor, u: torch.Tensor, mlp: Callable | None = None,
                box: tuple[np.ndarray, np.ndarray] | None = None) -> torch.Tensor:
        """``Delta(x, u)`` for ``x (..., nx)``, ``u (..., nu)``; ``mlp`` replaces ``self.mlp``
        (training runs several initialisations at once through a :class:`StackedMLP`); ``box``
        clamps the features as :meth:`casadi` does."""
        return self._evaluate(x, u, mlp, plus_prior=False, box=box)

    def hybrid(self, f: Callable, x: torch.Tensor, u: torch.Tensor, mlp: Callable | None = None):
        """``f(x, u) + Delta(x, u)``, the hybrid model's derivative. When ``f`` is the net's own
        prior, its evaluation is shared with the features and ``via`` (one or two prior
        evaluations instead of two or three; equal up to rounding)."""
        if self.prior is None or f != self.prior:  # bound methods compare by ==, not is
            return f(x, u) + self._evaluate(x, u, mlp, plus_prior=False)
        return self._evaluate(x, u, mlp, plus_prior=True)

    def _evaluate(self, x, u, mlp, plus_prior: bool, box=None):
        fp = self.prior(x, u) if self.prior is not None else None  # once, for features and via
        prior_xdot = list(fp.unbind(-1)) if self.prior_features else None
        parts = [*x.unbind(-1), *u.unbind(-1)]
        feats = torch.stack(self._features(parts, torch.sin, torch.cos, prior_xdot), dim=-1)
        if box is not None:
            feats = torch.clamp(feats, *(torch.as_tensor(b, dtype=feats.dtype) for b in box))
        out = (mlp or self.mlp)((feats - self.in_mean) / self.in_scale)
        out = self._channels(list(out.unbind(-1)), prior_xdot)
        if self.via:
            if self.via == tuple(range(self.nu)):  # every input corrected: no zero channels
                du = torch.stack(out[:self.nu], dim=-1)
            else:
                zero = torch.zeros_like(out[0])
                du = torch.stack([out[self.via.index(i)] if i in self.via else zero
                                  for i in range(self.nu)], dim=-1)
            shifted = self.prior(x, u + du)
            return shifted if plus_prior else shifted - fp
        zero = torch.zeros_like(out[0])
        rows = [out[self.outputs.index(i)] if i in self.outputs else zero for i in range(self.nx)]
        delta = torch.stack(rows, dim=-1)
        return fp + delta if plus_prior else delta

    def derivative(self, x: torch.Tensor, u: torch.Tensor, mlp: Callable | None = None) -> torch.Tensor:
        """``f_prior(x, u) + Delta(x, u)`` (torch) with the prior's terms from
        :attr:`prior_terms`: the prior, the net's features, its gains and its input correction
        share one evaluation of every sine and cosine of a state and no intermediate vector is
        stacked and split again. Equal to :meth:`hybrid` with the system's prior up to rounding;
        training's loss runs on it (a third fewer operations on the cartpole)."""
        ops = _SharedTrig()
        xs, us = list(x.unbind(-1)), list(u.unbind(-1))
        fp = self.prior_terms(ops, xs, us)
        feats = self._features([*xs, *us], ops.sin, ops.cos, fp)
        out = (mlp or self.mlp)((_stack(feats) - self.in_mean) / self.in_scale)
        out = self._channels(list(out.unbind(-1)), fp)
        if self.via:
            shifted = [v + out[self.via.index(i)] if i in self.via else v for i, v in enumerate(us)]
            return _stack(self.prior_terms(ops, xs, shifted))
        return _stack([fp[i] + out[self.outputs.index(i)] if i in self.outputs else fp[i]
                            for i in range(self.nx)])

    def derivative_t(self, x: torch.Tensor, u: torch.Tensor, mlp: "StackedMLP",
                     start: "StartT | None" = None) -> torch.Tensor:
        """:meth:`derivative` in training's layout: components first, ``x (nx, R, B)`` and
        ``u (nu, R, B)`` for the ``R`` members of ``mlp`` (a :class:`StackedMLP`) and ``B``
        pairs; returns ``(nx, R, B)``. Every component is then a contiguous ``(R, B)`` block,
        so the elementwise arithmetic of the prior runs on contiguous memory and stacking or
        splitting components copies blocks instead of interleaving them. Equal to
        :meth:`derivative` up to the matrix products' rounding.

        ``start`` (:meth:`start_t` of these ``x`` and ``u``) holds what does not depend on the
        weights: the prior, the sines and cosines and the standardised features at ``(x, u)``.
        Training's first RK4 stage is at the data, the same every epoch, and takes them from it
        (the same numbers, computed once)."""
        if start is None:
            start = self.start_t(x, u)
        ops = _SharedTrig(start.memo)
        xs, us, fp = start.xs, start.us, start.fp
        out = self._channels(list(mlp.forward_t(start.z).unbind(-2)), fp)
        if self.via:
            shifted = [v + out[self.via.index(i)] if i in self.via else v for i, v in enumerate(us)]
            return _stack(self.prior_terms(ops, xs, shifted), dim=0)
        return _stack([fp[i] + out[self.outputs.index(i)] if i in self.outputs else fp[i]
                       for i in range(self.nx)], dim=0)

    def start_t(self, x: torch.Tensor, u: torch.Tensor) -> "StartT":
        """What :meth:`derivative_t` computes at ``(x, u)`` before the MLP: the prior's terms,
        the sines and cosines taken, and the standardised features ``(R, in, B)``."""
        ops = _SharedTrig()
        xs, us = list(x.unbind(0)), list(u.unbind(0))
        fp = self.prior_terms(ops, xs, us)
        feats = self._features([*xs, *us], ops.sin, ops.cos, fp)
        z = (_stack(feats, dim=-2) - self.in_mean[:, None]) / self.in_scale[:, None]
        return StartT(xs, us, fp, z, ops.memo)

    def _channels(self, out: list, prior_xdot: list | None) -> list:
        """The residual's channels from the MLP's outputs (any backend): the outputs themselves,
        or with ``prior_gains`` each plus its gains times the scaled prior features."""
        if not self.prior_gains:
            return out
        n, g = self.channels, len(self.prior_features)
        scales = self.in_scale[-g:].tolist()
        channels = []
        for c in range(n):
            terms = [out[n + c * g + k] * (prior_xdot[j] / scales[k])
                     for k, j in enumerate(self.prior_features)]
            channels.append(out[c] + sum(terms[1:], terms[0]))  # as sum(terms) without its 0 + first
        return channels

    def casadi(self, x: cs.SX, u: cs.SX, box: tuple[np.ndarray, np.ndarray] | None = None) -> cs.SX:
        """The same network as a CasADi expression of columns ``x (nx,1)``, ``u (nu,1)``.

        ``box = (low, high)``, one bound per feature (see :mod:`.ranges`), clamps the features
        before the MLP: outside its training range the net sees the nearest point of the range
        instead of extrapolating. Being part of the graph, the clamp reaches every generated
        estimator and precision.
        """
        xu = cs.vertcat(x, u)
        fp = self.prior(x, u) if self.prior is not None else None  # once, for features and via
        prior_xdot = [fp[i] for i in range(self.nx)] if self.prior_features else None
        feats = cs.vertcat(*self._features([xu[i] for i in range(xu.shape[0])], cs.sin, cs.cos, prior_xdot))
        if box is not None:
            low, high = (np.asarray(b, dtype=float).reshape(-1) for b in box)
            if low.shape != (feats.shape[0],) or high.shape != low.shape:
                raise SettingsError(f"ResidualNet.casadi: box needs {feats.shape[0]} bounds each, got "
                                 f"{low.shape}, {high.shape}")
            feats = cs.fmin(cs.fmax(feats, low), high)
        z = (feats - self.in_mean.detach().numpy()) / self.in_scale.detach().numpy()
        out = self.mlp(z.T).T  # the naive MLP works on row vectors
        out = self._channels([out[j] for j in range(out.shape[0])], prior_xdot)
        if self.via:
            du = cs.vertcat(*[out[self.via.index(i)] if i in self.via else cs.SX(0)
                              for i in range(self.nu)])
            return self.prior(x, u + du) - fp
        return cs.vertcat(*[out[self.outputs.index(i)] if i in self.outputs else cs.SX(0)
                            for i in range(self.nx)])


class _SharedTrig:
    """The torch backend of a system's equations for one evaluation, remembering each sine and
    cosine it took: the prior at ``(x, u)``, at ``(x, u + du)`` and the net's angle features
    then take ``sin(alpha)`` once (and the backward pass its derivative once)."""

    def __init__(self, memo: dict | None = None) -> None:
        self._torch = _TORCH_OPS
        self._memo: dict[tuple[str, int], tuple[torch.Tensor, torch.Tensor]] = dict(memo or {})

    @property
    def memo(self) -> dict:
        """The sines and cosines taken so far (a copy starts another evaluation with them)."""
        return self._memo

    def __getattr__(self, name):  # every other function of the torch backend
        return getattr(self._torch, name)

    def _remember(self, fn: str, value):
        if not isinstance(value, torch.Tensor):
            return getattr(torch, fn)(torch.as_tensor(value))
        key = (fn, id(value))
        hit = self._memo.get(key)
        if hit is None or hit[0] is not value:
            hit = self._memo[key] = (value, getattr(torch, fn)(value))  # keeps value alive: no id reuse
        return hit[1]

    def sin(self, value):
        return self._remember("sin", value)

    def cos(self, value):
        return self._remember("cos", value)


class StartT(NamedTuple):
    """:meth:`ResidualNet.start_t`'s result: the components of ``x`` and ``u``, the prior's
    terms, the standardised features and the sines and cosines taken (see :class:`_SharedTrig`)."""

    xs: list
    us: list
    fp: list
    z: torch.Tensor
    memo: dict


def _stack(parts: list, dim: int = -1) -> torch.Tensor:
    """``parts`` stacked on a new axis ``dim``: one ``torch.stack`` when they are tensors of one
    shape (else broadcast, constants filled in)."""
    first = parts[0]
    if not all(isinstance(p, torch.Tensor) and p.shape == first.shape for p in parts):
        ref = next(p for p in parts if isinstance(p, torch.Tensor))
        parts = [p if isinstance(p, torch.Tensor) else torch.full_like(ref, float(p)) for p in parts]
        parts = list(torch.broadcast_tensors(*parts))
    return torch.stack(parts, dim=dim)


class _Tanh(torch.autograd.Function):
    """``tanh(x)`` as ``2 sigmoid(2 x) - 1``, with tanh's own backward ``g (1 - y^2)``.

    torch's float64 tanh costs about twice its sigmoid and was the largest single operation of
    a training epoch (see the project's ``docs/reports/training.md``). The two differ by at most 4e-16
    (absolute; the rounding of an O(1) value), which is all a trained net can see of it. Only
    training's :meth:`StackedMLP.forward_t` uses it; the trained model, its export and every
    estimator evaluate tanh itself.
    """

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        y = torch.sigmoid(x * 2.0)
        y.mul_(2.0).sub_(1.0)
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


class StackedMLP(torch.nn.Module):
    """``R`` MLPs of the same architecture with stacked weights, evaluated together.

    Layer ``l`` holds ``weights[l] (R, out, in)`` and ``biases[l] (R, out, 1)`` (training's
    features-first layout, :meth:`forward_t`); an input ``(B, in)`` shared by all members or
    ``(R, B, in)`` gives ``(R, B, out)``, one batched matrix product per layer. Training ``R``
    initialisations this way costs about what one costs (the step is dominated by
    per-operation overhead). Every optimiser in use (Adam, AdamW, the weight average) acts
    element by element, so the members train independently, exactly as they would one after
    another (in float32 to its rounding: the batched products of ``R`` members and of one may
    round differently).
    """

    def __init__(self, mlps: list):
        super().__init__()
        layers = [[m.input_layer, *m.hidden_layers, m.output_layer] for m in mlps]
        self.weights = torch.nn.ParameterList(
            torch.nn.Parameter(torch.stack([ls[i].weight.detach() for ls in layers]).clone())
            for i in range(len(layers[0])))
        self.biases = torch.nn.ParameterList(
            torch.nn.Parameter(torch.stack([ls[i].bias.detach() for ls in layers])[:, :, None].clone())
            for i in range(len(layers[0])))
        self.act = mlps[0].act
        # training's activation: tanh through the sigmoid, within 4e-16 of torch.tanh
        self._act_t = _Tanh.apply if isinstance(self.act, torch.nn.Tanh) else self.act
        self._layers = self._pairs()

    def _pairs(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``(weights[l], biases[l])`` of every layer, listed once: iterating the parameter
        lists at every evaluation costs more than a small layer's product."""
        return list(zip(self.weights, self.biases))

    def _apply(self, fn, *args, **kwargs):
        out = super()._apply(fn, *args, **kwargs)
        self._layers = self._pairs()  # a conversion may have replaced the parameters
        return out

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        last = len(self._layers) - 1
        z = z.expand(len(self.weights[0]), *z.shape[-2:])
        for i, (w, b) in enumerate(self._layers):
            z = torch.baddbmm(b.transpose(1, 2), z, w.transpose(1, 2))  # one fused product and bias
            if i < last:
                z = self.act(z)
        return z

    def forward_t(self, z: torch.Tensor) -> torch.Tensor:
        """The members on features-first inputs: ``z (R, in, B)`` -> ``(R, out, B)`` (the layout
        of :meth:`ResidualNet.derivative_t`); the same products as :meth:`forward`, transposed,
        and a tanh activation evaluated as :class:`_Tanh` (within 4e-16 of :meth:`forward`'s)."""
        last = len(self._layers) - 1
        for i, (w, b) in enumerate(self._layers):
            z = torch.baddbmm(b, w, z)
            if i < last:
                z = self._act_t(z)
        return z

    def member_state(self, r: int) -> dict[str, torch.Tensor]:
        """Member ``r``'s weights under the names of a :class:`ResidualNet`'s ``mlp``."""
        names = (["input_layer"] + [f"hidden_layers.{i}" for i in range(len(self.weights) - 2)]
                 + ["output_layer"])
        out = {}
        for name, w, b in zip(names, self.weights, self.biases):
            out[f"mlp.{name}.weight"] = w[r].detach().clone()
            out[f"mlp.{name}.bias"] = b[r, :, 0].detach().clone()
        return out
