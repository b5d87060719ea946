"""Observation kinds: Dict observations as one flat vector (each key's place in it kept), images
(3-D uint8, HWC) given TorchRL's image transforms and frame stacking, and what a network sees."""

from __future__ import annotations

import importlib.util
import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import TensorSpec
from torchrl.envs import CatFrames, EnvBase, GrayScale, Resize, ToTensorImage, Transform

from rlpipe.config import EnvConfig
from rlpipe.errors import RlpipeError, check

__all__ = [
    "DictObservation",
    "dict_observation",
    "KeySlice",
    "Observation",
    "image_transforms",
    "is_image_space",
    "observation_of",
]

IMAGE_FRAME_STACK = 4  # env.frame_stack=null on an image env (Atari's, SB3's and the Zoo's)


@dataclass(frozen=True)
class KeySlice:
    """Where one key of a Dict observation lies in :class:`DictObservation`'s vector: from
    ``start``, its values flattened from ``shape`` (an image key: ``(H, W, C)``)."""

    key: str
    start: int
    shape: tuple[int, ...]
    image: bool

    @property
    def size(self) -> int:
        return math.prod(self.shape)


def is_image_space(space: gym.Space) -> bool:
    """Whether a gymnasium space holds images: a 3-D uint8 Box, height x width x channels."""
    return isinstance(space, gym.spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 3


class DictObservation(gym.ObservationWrapper):
    """A Dict observation as one float32 vector: every key but the text ones (e.g. MiniGrid's
    ``mission``), in sorted order, flattened as ``gymnasium.spaces.flatten`` does (a Discrete
    one-hot, an image's raw values); ``layout`` says where each key lies."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        spaces = env.observation_space.spaces
        self.keys = sorted(k for k, s in spaces.items() if not _is_text(s))
        layout, lows, highs, start = [], [], [], 0
        for key in self.keys:
            try:
                flat = gym.spaces.flatten_space(spaces[key])
            except NotImplementedError as err:
                raise RlpipeError(
                    f"the Dict observation's key {key!r} is a {type(spaces[key]).__name__} space, "
                    "which rlpipe cannot flatten; wrap the env to drop or convert it"
                ) from err
            image = is_image_space(spaces[key])
            shape = spaces[key].shape if image else flat.shape
            layout.append(KeySlice(key, start, tuple(shape), image))
            lows.append(flat.low), highs.append(flat.high)
            start += flat.shape[0]
        self.layout = tuple(layout)
        self.observation_space = gym.spaces.Box(
            np.concatenate(lows).astype(np.float32), np.concatenate(highs).astype(np.float32)
        )

    def observation(self, observation: dict) -> np.ndarray:
        spaces = self.env.observation_space.spaces
        parts = [gym.spaces.flatten(spaces[k], observation[k]) for k in self.keys]
        return np.concatenate(parts).astype(np.float32, copy=False)


def _is_text(space: gym.Space) -> bool:
    """Whether a space holds strings (gymnasium's ``Text``, MiniGrid's ``MissionSpace``)."""
    return isinstance(space, gym.spaces.Text) or isinstance(space.sample(), str)


def dict_observation(env: gym.Env) -> gym.Env:
    """``env`` under :class:`DictObservation` if its observations are a Dict, else itself."""
    return DictObservation(env) if isinstance(env.observation_space, gym.spaces.Dict) else env


def image_transforms(cfg: EnvConfig, spec: TensorSpec) -> list[Transform]:
    """The transforms :func:`rlpipe.make_env` puts after its own for an observation of ``spec``:
    on images (3-D uint8, HWC), ``ToTensorImage`` (CHW float in [0, 1]), then ``GrayScale``
    (``env.grayscale``), ``Resize`` (``env.resize``) and ``CatFrames`` (``env.frame_stack``,
    null: 4); on vectors, ``CatFrames`` when ``env.frame_stack`` > 1."""
    keys = ["observation"]
    image = len(spec.shape) == 3 and spec.dtype == torch.uint8
    if not image:
        check(
            not cfg.grayscale and cfg.resize is None,
            f"env.grayscale and env.resize apply to images (3-D uint8 observations), but "
            f"{cfg.id!r} observes shape {tuple(spec.shape)} of {spec.dtype}; drop them",
        )
        stack = cfg.frame_stack or 1
        return [CatFrames(N=stack, dim=-1, in_keys=keys)] if stack > 1 else []
    out: list[Transform] = [ToTensorImage(in_keys=keys)]
    if cfg.grayscale:
        out.append(GrayScale(in_keys=keys))
    if cfg.resize is not None:
        check(
            importlib.util.find_spec("torchvision") is not None,
            "env.resize uses TorchRL's Resize, which needs torchvision: pip install "
            "torch==2.13.0 torchvision, or drop env.resize",
        )
        height, width = cfg.resize
        out.append(Resize(width, height, in_keys=keys))
    stack = cfg.frame_stack or IMAGE_FRAME_STACK
    if stack > 1:
        out.append(CatFrames(N=stack, dim=-3, in_keys=keys))
    return out


@dataclass(frozen=True)
class Observation:
    """What an algorithm's networks see under ``"observation"``: its ``shape`` (one step's),
    whether it is an image (CHW floats in [0, 1], frames stacked on the channels), and the
    per-key ``layout`` of a Dict observation with ``env.dict_obs=keys`` (None otherwise)."""

    shape: tuple[int, ...]
    image: bool = False
    layout: tuple[KeySlice, ...] | None = None

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    @property
    def in_features(self) -> int | tuple[int, ...]:
        """A network's ``in_features`` for it: a flat vector's size, else the shape."""
        return self.size if self.flat else self.shape

    @property
    def flat(self) -> bool:
        """A plain vector: what an MLP takes as it is."""
        return len(self.shape) == 1 and self.layout is None


def observation_of(env: EnvBase) -> Observation:
    """The :class:`Observation` of a :func:`rlpipe.make_env` env (or any env with a tensor
    ``"observation"``; a Dict observation of another env is one line saying what to do)."""
    spec = env.observation_spec_unbatched
    if "observation" not in spec.keys() or not hasattr(spec["observation"], "shape"):
        shapes = {k: tuple(v.shape) for k, v in spec.items(include_nested=True, leaves_only=True)}
        raise RlpipeError(
            f"rlpipe's networks read one tensor under 'observation'; the env gives {shapes}: "
            "build it with rlpipe.make_env, which turns a Dict observation into one"
        )
    transforms = getattr(env, "transform", ())
    image = any(isinstance(t, ToTensorImage) for t in getattr(transforms, "transforms", ()))
    layout = getattr(env, "observation_layout", None)
    return Observation(tuple(spec["observation"].shape), image, layout)
