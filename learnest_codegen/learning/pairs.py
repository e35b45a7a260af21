"""Training pairs of recordings joined end to end (no pair spans a join).

:func:`segment_pairs` is what :func:`~learnest_codegen.learning.training.train` uses when it is
given the joins (``breaks``) of several recordings; see :mod:`.runs`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..errors import DataError

__all__ = ["segment_pairs"]


def segment_pairs(zeta: np.ndarray, u: np.ndarray, breaks: Sequence[int], validation_fraction: float):
    """``(pairs, train_set, valid_set)`` of recordings joined at the sample indices ``breaks``.

    Each is ``[zeta_k, u_k, zeta_{k+1}]`` as tensors. ``pairs`` holds every pair that does not
    span a break; each recording's final ``validation_fraction`` of pairs goes to ``valid_set``
    and the rest to ``train_set`` (with no validation, ``valid_set`` is ``train_set``).
    """
    edges = [0, *sorted(int(b) for b in breaks), len(zeta)]
    if any(b - a < 2 for a, b in zip(edges, edges[1:])):
        raise DataError(f"segment_pairs: every recording needs at least 2 samples; joins at {list(breaks)} "
                        f"of {len(zeta)} samples leave one shorter")
    index = {"all": [], "train": [], "valid": []}
    for a, b in zip(edges, edges[1:]):
        k = np.arange(a, b - 1)  # pair k: (zeta[k], u[k]) -> zeta[k + 1], inside one recording
        n_train = len(k) - int(validation_fraction * len(k))
        index["all"].append(k)
        index["train"].append(k[:n_train])
        index["valid"].append(k[n_train:])
    picks = {name: np.concatenate(parts) for name, parts in index.items()}
    zeta_t, u_t = torch.as_tensor(zeta), torch.as_tensor(u)

    def pairs_at(k: np.ndarray) -> list[torch.Tensor]:
        k = torch.as_tensor(k)
        return [zeta_t[k], u_t[k], zeta_t[k + 1]]

    train_set = pairs_at(picks["train"])
    valid_set = pairs_at(picks["valid"]) if len(picks["valid"]) else train_set
    return pairs_at(picks["all"]), train_set, valid_set
