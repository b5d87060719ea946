"""Network factories and action heads shared by the algorithms, and the NumPy twin protocol."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from torch import nn
from torchrl.modules import MLP


def mlp(in_features: int, out_features: int, hidden_sizes: Sequence[int]) -> nn.Module:
    """A ReLU multi-layer perceptron with the given hidden layer sizes (may be empty: linear)."""
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden_sizes),
        activation_class=nn.ReLU,
    )


@runtime_checkable
class NumpyForward(Protocol):
    """A parameter-free module that can give its ``forward`` as a function of NumPy arrays.

    ARS rolls a population out step by step, calling the policy on a few observations at a
    time; there, NumPy functions cost less per call than torch's dispatch (see
    :class:`rlpipe.algos.ars.PopulationPolicy`). The twin must compute what ``forward`` does,
    from a snapshot of the module's current buffers.
    """

    def numpy_forward(self) -> Callable[..., np.ndarray]: ...


class ClampAction(nn.Module):
    """Clamp continuous actions into the action space's ``[low, high]`` (element-wise bounds)."""

    def __init__(self, low: torch.Tensor, high: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("low", low.clone())
        self.register_buffer("high", high.clone())

    def forward(self, output: torch.Tensor) -> torch.Tensor:
        return torch.clamp(output, self.low, self.high)

    def numpy_forward(self) -> Callable[[np.ndarray], np.ndarray]:
        """``forward`` on NumPy arrays: ``np.clip``, torch.clamp's twin."""
        low, high = self.low.cpu().numpy().copy(), self.high.cpu().numpy().copy()
        return lambda output: np.clip(output, low, high)


class ArgmaxAction(nn.Module):
    """Pick the discrete action with the largest output."""

    def forward(self, output: torch.Tensor) -> torch.Tensor:
        return output.argmax(-1)

    def numpy_forward(self) -> Callable[[np.ndarray], np.ndarray]:
        """``forward`` on NumPy arrays."""
        return lambda output: output.argmax(-1)
