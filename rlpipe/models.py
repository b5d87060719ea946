"""Network factories and action heads shared by the algorithms, and the NumPy twin protocol."""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from tensordict import NestedKey, TensorDictBase
from tensordict.nn import (
    AddStateIndependentNormalScale,
    NormalParamExtractor,
    TensorDictModuleBase,
    TensorDictSequential,
    add_custom_mapping,
)
from torch import nn
from torchrl.data import Bounded
from torchrl.envs import EnvBase
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor

from rlpipe.envs import is_discrete, num_actions, observation_of
from rlpipe.errors import RlpipeError, check

add_custom_mapping("sigmoid", torch.sigmoid)  # the REINFORCE notebook's std in (0, 1)


def mlp(
    in_features: int,
    out_features: int,
    hidden_sizes: Sequence[int],
    activation: type[nn.Module] = nn.ReLU,
    layer_norm: bool = False,
) -> nn.Module:
    """A multi-layer perceptron (ReLU unless ``activation``) with the given hidden layer sizes
    (may be empty: linear); ``layer_norm``: a LayerNorm after each hidden layer, before its
    activation."""
    norm: dict[str, Any] = {}
    if layer_norm and hidden_sizes:
        norm = {
            "norm_class": nn.LayerNorm,
            "norm_kwargs": [{"normalized_shape": n} for n in hidden_sizes],
        }
    return MLP(
        in_features=in_features,
        out_features=out_features,
        num_cells=list(hidden_sizes),
        activation_class=activation,
        **norm,
    )


class TensorModule(TensorDictModuleBase):
    """Run ``module`` on the ``in_keys`` tensors and write its outputs to ``out_keys`` in place.

    What ``TensorDictModule`` does for tensor-to-tensor modules, minus its per-output
    ``TensorDict.from_any``, which in tensordict 0.14.3 looks ``pandas`` up with
    ``importlib.util.find_spec`` on every call, a cost paid per env step and per minibatch.
    """

    def __init__(
        self, module: nn.Module, in_keys: Sequence[NestedKey], out_keys: Sequence[NestedKey]
    ) -> None:
        super().__init__()
        self.module = module
        self.in_keys, self.out_keys = list(in_keys), list(out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        out = self.module(*(tensordict.get(key) for key in self.in_keys))
        outs = out if isinstance(out, tuple) else (out,)
        for key, value in zip(self.out_keys, outs, strict=True):
            tensordict.set(key, value)
        return tensordict


# how a Gaussian policy gets its std: "sigmoid": the network's second half of outputs through a
# sigmoid, in (0, 1) (the REINFORCE notebook's); "free": one trained log-std per action dimension,
# whatever the observation (PPO's, as SB3's)
SCALES = ("sigmoid", "free")


def make_policy(
    env: EnvBase,
    network: Callable[[int | tuple[int, ...], int, str], nn.Module],
    *,
    scale: str = "sigmoid",
    log_prob: bool = False,
    algo: str = "this algorithm",
) -> tuple[TensorDictModuleBase, ProbabilisticActor, str]:
    """The stochastic policy, its distribution module and the key holding what its
    log-probability is taken of; ``network(in_features, out_features, outputs)`` builds its
    network (``in_features``: the observation's size, or its shape if it is no flat vector);
    ``log_prob``: the sampling policy also writes the sample's log-probability (PPO's
    old policy); ``algo`` names the algorithm in errors.

    Discrete actions: a Categorical over logits, sampled into ``action``. Box actions: a
    Gaussian with a mean per dimension and a std as ``scale`` says; the raw sample goes to
    ``sample`` (the policy gradient's variable) and ``action`` is that sample clipped into the
    bounds. In deterministic mode: the argmax, or the clipped mean.
    """
    spec = env.action_spec_unbatched
    n_obs = observation_of(env).in_features
    if is_discrete(env):
        net = network(n_obs, num_actions(env), "one logit per action")
        module = TensorModule(net, ["observation"], ["logits"])
        actor = ProbabilisticActor(
            module,
            in_keys=["logits"],
            spec=spec,
            distribution_class=torch.distributions.Categorical,
            return_log_prob=log_prob,
        )
        return actor, actor, "action"
    if not isinstance(spec, Bounded) or not spec.dtype.is_floating_point or len(spec.shape) != 1:
        raise RlpipeError(
            f"{algo}'s policy needs discrete actions or a bounded flat box of continuous "
            f"actions, but this env's actions are {type(spec).__name__} of shape "
            f"{tuple(spec.shape)}"
        )
    size = spec.shape[0]
    if scale == "sigmoid":
        outputs = f"a mean and a pre-sigmoid std per action dimension ({size}), in that order"
        head = NormalParamExtractor(scale_mapping="sigmoid")
        net = nn.Sequential(network(n_obs, 2 * size, outputs), head)
    else:
        net = network(n_obs, size, f"a mean per action dimension ({size})")
        net = nn.Sequential(net, AddStateIndependentNormalScale(size, scale_mapping="exp"))
    module = TensorModule(net, ["observation"], ["loc", "scale"])
    actor = ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["sample"],
        distribution_class=IndependentNormal,
        distribution_kwargs={"upscale": 1.0},
        return_log_prob=log_prob,
    )
    clip = ClampAction(spec.space.low, spec.space.high)
    return TensorDictSequential(actor, TensorModule(clip, ["sample"], ["action"])), actor, "sample"


def instantiate(spec: Mapping[str, Any], what: str, **sizes: int) -> Any:
    """Build ``spec["_target_"](**kwargs)`` with Hydra's ``instantiate``; ``sizes`` fill the
    keyword arguments ``spec`` leaves out. ``what`` names the config key in errors (one line)."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate as hydra_instantiate

    target = spec.get("_target_")
    check(
        isinstance(target, str) and "." in target,
        f"{what}._target_ must name a class or function as module.Name, got {target!r}",
    )
    module, _, name = target.rpartition(".")
    try:
        found = hasattr(importlib.import_module(module), name)
    except ModuleNotFoundError as err:
        raise RlpipeError(
            f"{what}._target_={target}: no module named {err.name!r}; put the directory "
            f"holding it on PYTHONPATH (e.g. PYTHONPATH=. python -m rlpipe ...)"
        ) from err
    check(found, f"{what}._target_={target}: module {module} has no {name}")
    kwargs = {key: value for key, value in sizes.items() if key not in spec}
    try:
        return hydra_instantiate(dict(spec), **kwargs, _convert_="all")
    except InstantiationException as err:
        raise RlpipeError(
            f"{what}: cannot build {target} ({error_reason(err.__cause__ or err)})"
        ) from err


# algo.network of a run whose network was a Python object: {"_object_": "<its class>"}, a record
# (config.yaml cannot rebuild the object) that asks for the object again
OBJECT_KEY = "_object_"


def object_record(network: nn.Module) -> dict[str, str]:
    """What ``algo.network`` records for a network given as a Python object: its class."""
    return {OBJECT_KEY: f"{type(network).__module__}.{type(network).__qualname__}"}


def network_spec(
    network: nn.Module | None, spec: Mapping[str, Any] | None
) -> Mapping[str, Any] | None:
    """The ``algo.network`` spec left to build (None: use ``network``, or the default), after
    checking ``network`` and ``spec`` do not both name a network, and that a run whose network
    was an object (:func:`object_record`) gets one."""
    if spec and OBJECT_KEY in spec:
        check(
            network is not None,
            f"this run's network was a Python object ({spec[OBJECT_KEY]}), which config.yaml "
            "cannot rebuild: pass one like it as network= (load_run(run_dir, network=...), "
            "train(cfg, run_dir, network=...))",
        )
        return None
    check(
        network is None or not spec,
        "a network was given both as an object and as algo.network; give one of them",
    )
    return spec or None


def user_network(
    network: nn.Module | None,
    spec: Mapping[str, Any] | None,
    *,
    in_features: int | Sequence[int],
    out_features: int,
    outputs: str,
) -> nn.Module | None:
    """The network a user brought in place of an algorithm's default, or None.

    ``network``: a module (Python); ``spec``: ``algo.network``, a Hydra-style
    ``{"_target_": "my_pkg.MyNet", **kwargs}`` built with ``in_features`` (an observation's
    shape: its number of values) and ``out_features`` (unless it sets them). Either way the
    network must map a batch of inputs of ``in_features`` (a size, or a shape such as an image's
    ``(C, H, W)``) to ``out_features`` outputs (``outputs`` says what they are, for the error).
    """
    shape = (in_features,) if isinstance(in_features, int) else tuple(in_features)
    spec = network_spec(network, spec)
    if spec:
        network = instantiate(
            spec, "algo.network", in_features=math.prod(shape), out_features=out_features
        )
    if network is None:
        return None
    name = type(network).__name__
    check(isinstance(network, nn.Module), f"algo.network must build a torch nn.Module, got {name}")
    device = next((p.device for p in network.parameters()), torch.device("cpu"))
    inputs = f"inputs of {'size ' + str(shape[0]) if len(shape) == 1 else 'shape ' + str(shape)}"
    try:
        with torch.no_grad():
            out = network(torch.zeros(2, *shape, device=device))
    except Exception as err:  # the user's module: any failure is theirs to see, in one line
        raise RlpipeError(
            f"the network {name} fails on a batch of 2 {inputs} ({error_reason(err)})"
        ) from err
    check(
        isinstance(out, torch.Tensor) and out.shape == (2, out_features),
        f"the network {name} maps a batch of 2 {inputs} to "
        f"{tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__}; "
        f"this algorithm needs (2, {out_features}): {outputs}",
    )
    return network


def error_reason(err: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__


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
