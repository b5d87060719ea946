"""An algorithm's state attributes (networks, optimizers, replay buffers, generators) saved,
loaded and carried into a new run (``init_from``), each by its kind."""

from __future__ import annotations

from collections.abc import Collection, Iterable
from typing import Any

import torch
from torch import nn
from torchrl.data import ReplayBuffer
from torchrl.objectives import LossModule

from rlpipe.errors import check


def save_parts(owner: Any, names: Iterable[str]) -> dict[str, Any]:
    """The state of each named attribute of ``owner`` (a generator's, or a ``state_dict``)."""
    return {name: _save(getattr(owner, name)) for name in names}


def load_parts(owner: Any, names: Iterable[str], state: dict[str, Any]) -> None:
    """Load :func:`save_parts`'s ``state`` into the named attributes of ``owner``."""
    for name in names:
        part = getattr(owner, name)
        if isinstance(part, torch.Generator):
            part.set_state(state[name])
        else:
            part.load_state_dict(state[name])


def start_parts(
    owner: Any, names: Iterable[str], state: dict[str, Any], parts: Collection[str]
) -> None:
    """Another run's :func:`save_parts` ``state`` into ``owner``'s named attributes by kind:
    modules take its weights (a TorchRL loss module's networks, targets and learned parameters
    such as SAC's α; its coefficients, γ and target entropy stay ``owner``'s), an optimizer its
    state with ``"optimizer"`` in ``parts`` (learning rates and other settings stay ``owner``'s),
    a replay buffer its contents with ``"buffer"``; generators stay ``owner``'s."""
    kinds = {name: _kind(getattr(owner, name)) for name in names}
    for part in parts:
        what = {"optimizer": "optimizer", "buffer": "replay buffer"}[part]
        check(
            part in kinds.values(),
            f"init_{part}=true, but {type(owner).__name__} keeps no {what} to start from: "
            f"drop init_{part}",
        )
    for name, kind in kinds.items():
        part, saved = getattr(owner, name), state[name]
        if kind == "weights":
            part.load_state_dict(_learned(part, saved))
        elif kind == "optimizer" and kind in parts:
            groups = part.param_groups
            settings = [{k: v for k, v in g.items() if k != "params"} for g in groups]
            part.load_state_dict(saved)
            for group, own in zip(part.param_groups, settings):
                group.update(own)  # this config's lr, betas, weight decay, ...
        elif kind == "buffer" and kind in parts:
            part.load_state_dict(saved)


def _kind(part: Any) -> str | None:
    """What :func:`start_parts` takes a state attribute for (None: nothing)."""
    if isinstance(part, torch.optim.Optimizer):
        return "optimizer"
    if isinstance(part, ReplayBuffer):
        return "buffer"
    return "weights" if isinstance(part, nn.Module) else None


def _learned(module: nn.Module, saved: dict[str, Any]) -> dict[str, Any]:
    """``saved`` (a state dict of ``module``'s kind) with a TorchRL loss module's settings taken
    from ``module``: every entry outside its networks (``*network*``) that is no parameter."""
    if not isinstance(module, LossModule):
        return saved
    params = dict(module.named_parameters())
    own = {
        key: value
        for key, value in module.state_dict().items()
        if "network" not in key.split(".")[0] and key not in params
    }
    return {**saved, **own}


def _save(part: Any) -> Any:
    return part.get_state() if isinstance(part, torch.Generator) else part.state_dict()
