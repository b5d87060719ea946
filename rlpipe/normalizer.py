"""Running observation statistics: ARS standardises its policy's inputs with them, MBRL's world
model its inputs and targets."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import nn

__all__ = ["Normalizer", "batch_stats"]


class Normalizer(nn.Module):
    """Running mean and variance of observations; ``forward`` standardises with frozen values.

    The statistics (float64 count, mean and sum of squared deviations) grow by :meth:`merge`
    (Chan et al.'s parallel form of Welford's update); ``loc`` and ``scale`` used by ``forward``
    are refreshed only then. The variance is clipped at ``min_var`` (1e-2, as the notebook);
    before any observation the normaliser is the identity. It has a NumPy twin
    (:class:`rlpipe.models.NumpyForward`) for ARS's population rollouts.
    """

    def __init__(self, size: int, min_var: float = 1e-2) -> None:
        super().__init__()
        self.min_var = min_var
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("loc", torch.zeros(size))
        self.register_buffer("scale", torch.ones(size))

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return (observation - self.loc) / self.scale

    def numpy_forward(self) -> Callable[[np.ndarray], np.ndarray]:
        """``forward`` as a NumPy function of a snapshot of the current ``loc`` and ``scale``
        (later merges do not change it, on any device)."""
        loc, scale = self.loc.cpu().numpy().copy(), self.scale.cpu().numpy().copy()
        return lambda observation: (observation - loc) / scale

    @torch.no_grad()
    def merge(self, count: float, mean: torch.Tensor, m2: torch.Tensor) -> None:
        """Fold in the statistics (count, mean, sum of squared deviations) of a batch."""
        if count == 0:
            return
        total = self.count + count
        delta = mean.double() - self.mean
        self.m2 += m2.double() + delta**2 * self.count * count / total
        self.mean += delta * count / total
        self.count.copy_(total)
        self.loc.copy_(self.mean)
        self.scale.copy_((self.m2 / self.count).clamp(min=self.min_var).sqrt())

    def observe(self, observations: torch.Tensor) -> None:
        """Fold in a batch of observations (rows)."""
        self.merge(*batch_stats(observations))


def batch_stats(observations: torch.Tensor) -> tuple[int, torch.Tensor, torch.Tensor]:
    """Count, mean and sum of squared deviations of a batch of observations (rows)."""
    x = observations.double().reshape(-1, observations.shape[-1])
    mean = x.mean(0) if len(x) else x.new_zeros(x.shape[-1])
    return len(x), mean, ((x - mean) ** 2).sum(0)
