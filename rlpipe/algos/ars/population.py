"""A policy evaluated for a whole population of parameter vectors at once, as NumPy functions.

A rollout step calls the policy on a few members right after the physics has evicted torch's
dispatch code from the caches; there, a batched matmul and NumPy forms of the parameter-free
layers (the :class:`rlpipe.models.NumpyForward` twins) cost less per call than the torch form.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn

from rlpipe.errors import RlpipeError, check
from rlpipe.models import NumpyForward

__all__ = ["NUMPY_ACTIVATIONS", "PopulationPolicy", "batched_call", "numpy_layer"]


class PopulationPolicy:
    """A TensorDictModule policy evaluated for a population of flat parameter vectors at once.

    Row ``i`` of ``flat`` (``[P, n]``, the layout of ``parameters_to_vector``) holds member
    ``i``'s parameters. The policy is a ``TensorDictModule`` or a ``TensorDictSequential`` of
    them (one output key each); calling this on a TensorDict whose batch is the population runs
    them in order, as NumPy functions of the current parameters and statistics: parameter-free
    ones (normaliser, action head) through :func:`numpy_layer`, the others through
    :func:`batched_call`.
    """

    def __init__(self, policy: TensorDictModuleBase, flat: torch.Tensor) -> None:
        modules = policy.module if isinstance(policy, TensorDictSequential) else [policy]
        self.steps: list[tuple[Callable[..., np.ndarray], list[Any], Any]] = []
        offset = 0
        for module in modules:
            if not (isinstance(module, TensorDictModule) and len(module.out_keys) == 1):
                raise RlpipeError(
                    f"the policy must be made of TensorDictModules with one output, got {module}"
                )
            params = {}
            for name, param in module.module.named_parameters():
                params[name] = flat[:, offset : offset + param.numel()].view(-1, *param.shape)
                offset += param.numel()
            call = batched_call(module.module, params) if params else numpy_layer(module.module)
            self.steps.append((call, module.in_keys, module.out_keys[0]))
        check(offset == flat.shape[-1], "flat parameters do not match the policy's parameters")

    @torch.no_grad()
    def __call__(self, td: TensorDictBase) -> TensorDictBase:
        values = {k: v.cpu().numpy() for k, v in td.items(include_nested=True, leaves_only=True)}
        values = self.outputs(values)
        return td.update({key: torch.from_numpy(values[key]) for _, _, key in self.steps})

    def outputs(self, values: dict[Any, np.ndarray]) -> dict[Any, np.ndarray]:
        """The same on a plain dict of NumPy arrays (the rollout's per-step fast path)."""
        for call, in_keys, out_key in self.steps:
            values[out_key] = call(*[values[key] for key in in_keys])
        return values


def batched_call(module: nn.Module, params: dict[str, torch.Tensor]) -> Callable[..., np.ndarray]:
    """``module`` as a NumPy function of a population batch, member ``i`` using ``params[name][i]``.

    ``nn.Linear`` layers become one batched matmul, ``nn.LayerNorm`` (over the last dimension)
    a NumPy normalisation with each member's gain and bias, and ``nn.Sequential`` chains
    (TorchRL's MLP) are followed layer by layer, parameter-free layers through
    :func:`numpy_layer`; any other module goes through ``torch.vmap`` over ``functional_call``.
    ``params`` are CPU tensors.
    """
    if isinstance(module, nn.Linear):
        weight = params["weight"].detach().transpose(1, 2).numpy()  # [P, in, out]
        bias = params.get("bias")
        bias = None if bias is None else bias.detach().numpy()

        def linear(x: np.ndarray) -> np.ndarray:
            y = np.matmul(x[:, None, :], weight)[:, 0]
            return y if bias is None else y + bias

        return linear
    if isinstance(module, nn.LayerNorm) and len(module.normalized_shape) == 1:
        gain, shift = (params.get(name) for name in ("weight", "bias"))
        gain = None if gain is None else gain.detach().numpy()
        shift = None if shift is None else shift.detach().numpy()

        def layer_norm(x: np.ndarray) -> np.ndarray:
            centred = x - x.mean(-1, keepdims=True)
            y = centred / np.sqrt(np.square(centred).mean(-1, keepdims=True) + module.eps)
            y = y if gain is None else y * gain
            return y if shift is None else y + shift

        return layer_norm
    if isinstance(module, nn.Sequential):
        layers = []
        for name, layer in module.named_children():
            prefix = f"{name}."
            own = {k[len(prefix) :]: v for k, v in params.items() if k.startswith(prefix)}
            layers.append(batched_call(layer, own) if own else numpy_layer(layer))

        def chain(x: np.ndarray) -> np.ndarray:
            for layer in layers:
                x = layer(x)
            return x

        return chain
    vmapped = torch.vmap(lambda p, *args: torch.func.functional_call(module, p, args))
    return lambda *xs: vmapped(params, *map(torch.from_numpy, xs)).numpy()


# NumPy twins of common parameter-free torch layers, which cannot implement NumpyForward
# themselves (any other layer runs through torch, see numpy_layer)
NUMPY_ACTIVATIONS: dict[type[nn.Module], Callable[[np.ndarray], np.ndarray]] = {
    nn.ReLU: lambda x: np.maximum(x, 0),
    nn.Tanh: np.tanh,
    nn.Identity: lambda x: x,
}


def numpy_layer(module: nn.Module) -> Callable[..., np.ndarray]:
    """A parameter-free ``module`` as a function of NumPy arrays.

    Common activations have a twin in :data:`NUMPY_ACTIVATIONS`, a
    :class:`rlpipe.models.NumpyForward` module (rlpipe's normaliser and action heads) gives its
    own; anything else is called through torch (zero-copy conversions; module hooks are not run).
    """
    if type(module) in NUMPY_ACTIVATIONS:
        return NUMPY_ACTIVATIONS[type(module)]
    if isinstance(module, NumpyForward):
        return module.numpy_forward()
    return lambda *xs: module.forward(*map(torch.from_numpy, xs)).numpy()
