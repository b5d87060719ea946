"""Network factories shared by the algorithms."""

from __future__ import annotations

from collections.abc import Sequence

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
