"""Figures: estimates against truth, estimation errors, and training loss."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")  # files only; no display is needed or assumed
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .data import Run  # noqa: E402
from .evaluation import EstimateResult  # noqa: E402
from .systems import System  # noqa: E402


def plot_estimates(run: Run, system: System, results: Sequence[EstimateResult], path: str | Path,
                   title: str = "") -> Path:
    """One panel per state: truth, measurements where a state is measured, and each estimate."""
    fig, axes = plt.subplots(system.nx, 1, figsize=(10, 2.2 * system.nx), sharex=True)
    for i, (ax, sig) in enumerate(zip(np.atleast_1d(axes), system.states)):
        if sig.name in system.output_names:
            j = system.output_names.index(sig.name)
            ax.plot(run.t, run.y[:, j], ".", ms=1, color="0.7", label="measurement")
        if run.x is not None:
            ax.plot(run.t, run.x[:, i], "k", lw=1.5, label="truth")
        for res in results:
            ax.plot(run.t, res.x_hat[:, i], lw=1, label=res.label)
        ax.set_ylabel(f"{sig.name} [{sig.unit}]")
    np.atleast_1d(axes)[0].legend(loc="upper right", fontsize=7, ncol=3)
    np.atleast_1d(axes)[-1].set_xlabel("t [s]")
    fig.suptitle(title or f"{system.name}: estimates against truth")
    return _save(fig, path)


def plot_errors(run: Run, system: System, results: Sequence[EstimateResult], path: str | Path) -> Path:
    """Absolute estimation error per state on a log scale: where each estimator is wrong."""
    fig, axes = plt.subplots(system.nx, 1, figsize=(10, 2.2 * system.nx), sharex=True)
    for i, (ax, sig) in enumerate(zip(np.atleast_1d(axes), system.states)):
        errors = [np.abs(res.x_hat[:, i] - run.x[:, i]) + 1e-15 for res in results]
        for res, err in zip(results, errors):
            ax.semilogy(run.t, err, lw=0.8, label=res.label)
        ax.set_ylim(bottom=np.percentile(np.concatenate(errors), 1))  # the exact x0 is no signal
        ax.set_ylabel(f"|err {sig.name}| [{sig.unit}]")
    np.atleast_1d(axes)[0].legend(loc="upper right", fontsize=7, ncol=2)
    np.atleast_1d(axes)[-1].set_xlabel("t [s]")
    fig.suptitle(f"{system.name}: absolute estimation errors")
    return _save(fig, path)


def plot_loss(history: Sequence[float], prior_loss: float, path: str | Path) -> Path:
    """KNODE training loss per epoch, with the prior model's loss for reference."""
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.semilogy(np.arange(1, len(history) + 1), history, label="KNODE (prior + net)")
    ax.axhline(prior_loss, color="r", ls="--", label="prior only")
    ax.set_xlabel("epoch")
    ax.set_ylabel("one-step loss")
    ax.legend()
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
