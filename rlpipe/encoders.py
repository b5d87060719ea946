"""Observation encoders picked from the observation: a CNN for images, one encoder per key for
Dict observations (``env.dict_obs=keys``), none for flat vectors; the algorithms' heads follow."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from torchrl.modules import ConvNet

from rlpipe.envs.observations import KeySlice, Observation

__all__ = ["EncodeFirst", "KeyEncoder", "cnn", "encoded", "encoder"]

FEATURES = 256  # the CNN's output features (SB3's NatureCNN: 512, for 84x84 Atari frames)
KEY_FEATURES = 64  # each vector key's encoder's (SB3's CombinedExtractor passes them as they are)
NATURE_SIZE = 36  # images at least this high and wide get the Nature-DQN convolutions


def cnn(shape: tuple[int, ...]) -> tuple[nn.Module, int]:
    """A CNN over CHW images of ``shape`` (any batch dimensions before) and its output features:
    the Nature-DQN convolutions (32 8x8/4, 64 4x4/2, 64 3x3/1) for images of 36 pixels or more,
    else two 3x3/2 convolutions (16, 32) for small ones; then a linear layer to
    :data:`FEATURES`, ReLU after each (TorchRL's ``ConvNet``)."""
    channels, height, width = shape
    if min(height, width) >= NATURE_SIZE:
        layers = {"num_cells": [32, 64, 64], "kernel_sizes": [8, 4, 3], "strides": [4, 2, 1]}
    else:
        layers = {"num_cells": [16, 32], "kernel_sizes": 3, "strides": 2, "paddings": 1}
    conv = ConvNet(in_features=channels, activation_class=nn.ReLU, **layers)
    with torch.no_grad():
        flat = conv(torch.zeros(1, *shape)).shape[-1]
    return nn.Sequential(conv, nn.Linear(flat, FEATURES), nn.ReLU()), FEATURES


class KeyEncoder(nn.Module):
    """SB3's ``CombinedExtractor`` on :class:`~rlpipe.envs.observations.DictObservation`'s
    vector: each key's slice encoded apart (an image key, raw 0-255 HWC values, scaled to
    [0, 1] and through :func:`cnn`; a vector key through a linear layer to
    :data:`KEY_FEATURES` and a ReLU), the features concatenated in the layout's order."""

    def __init__(self, layout: tuple[KeySlice, ...]) -> None:
        super().__init__()
        self.layout = layout
        encoders, self.features = [], 0
        for part in layout:
            if part.image:
                height, width, channels = part.shape
                net, size = cnn((channels, height, width))
            else:
                net = nn.Sequential(nn.Linear(part.size, KEY_FEATURES), nn.ReLU())
                size = KEY_FEATURES
            encoders.append(net)
            self.features += size
        self.encoders = nn.ModuleList(encoders)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        outs = []
        for part, net in zip(self.layout, self.encoders, strict=True):
            values = observation[..., part.start : part.start + part.size]
            if part.image:  # back to HWC, then CHW in [0, 1] (what ToTensorImage gives)
                values = values.unflatten(-1, part.shape).movedim(-1, -3) / 255.0
            outs.append(net(values))
        return torch.cat(outs, -1)


def encoder(observation: Observation) -> tuple[nn.Module | None, int]:
    """The encoder of ``observation`` and its output features: :func:`cnn` for an image, a
    :class:`KeyEncoder` for a Dict observation's layout, ``nn.Flatten`` over any other
    multi-dimensional array, None (the vector as it is) for a flat vector."""
    if observation.image:
        return cnn(observation.shape)
    if observation.layout is not None:
        keys = KeyEncoder(observation.layout)
        return keys, keys.features
    if len(observation.shape) > 1:
        return nn.Flatten(-len(observation.shape)), observation.size
    return None, observation.size


def encoded(observation: Observation, head: Callable[[int], nn.Module]) -> nn.Module:
    """``head(features)`` after the :func:`encoder` of ``observation`` (the head alone for a
    flat vector)."""
    first, features = encoder(observation)
    return head(features) if first is None else nn.Sequential(first, head(features))


class EncodeFirst(nn.Module):
    """``head`` on the encoded observation concatenated with the other inputs (SAC's critic:
    ``Q(encoder(observation), action)``)."""

    def __init__(self, encoder: nn.Module, head: nn.Module) -> None:
        super().__init__()
        self.encoder, self.head = encoder, head

    def forward(self, observation: torch.Tensor, *rest: torch.Tensor) -> torch.Tensor:
        return self.head(torch.cat([self.encoder(observation), *rest], -1))
