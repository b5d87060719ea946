"""How an :class:`~rlpipe.algos.base.EnvAlgorithm` collects its batches: a lean loop over a
:func:`rlpipe.make_env` env's arrays (:class:`ArrayCollector`), or TorchRL's ``Collector`` for
any other env (:class:`TorchRLCollector`); both yield ``[env copies, steps]`` TensorDicts with
the keys the algorithms read.

Why the lean loop is written by hand: TorchRL's ``Collector`` over make_env's ``TransformedEnv``
(``DoubleToFloat``, ``StepCounter``, ``InitTracker``, ``RewardSum``) with a TensorDict policy
builds, checks and merges several TensorDicts per env step. Measured on 2 busy cores (torchrl
0.14.1, one thread): 1.4 ms per collected step of SAC on one Pendulum copy, on either backend,
where the lean loop takes 0.3 ms, about what a hand-written PyTorch loop's whole step (actor,
draw, env step, buffer write) costs there; 3.5 to 6.5 times less per step for the DQN, SAC and
PPO presets (``benchmarks/collection.py``, BENCHMARKS.md). The lean loop steps the backend's
copies on NumPy arrays (:func:`rlpipe.envs.env_copies`), keeps ``StepCounter``'s and
``RewardSum``'s counts itself, calls the policy on plain tensors (a :data:`CollectAction`) and
builds one TensorDict per batch.
"""

from __future__ import annotations

from collections.abc import Callable
from itertools import chain

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.data.utils import torch_to_numpy_dtype_dict
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type

from rlpipe.envs import EnvCopies, env_copies
from rlpipe.errors import RlpipeError

# what collects on plain tensors: a batch of observations (on the algorithm's device) -> the
# policy's outputs the algorithm reads, by batch key, "action" among them (e.g. PPO's sample
# and its log-probability)
CollectAction = Callable[[torch.Tensor], dict[str, torch.Tensor]]


class BatchCut:
    """A TorchRL collector interruptor that ends the next batch after ``steps`` env steps
    (``None``: the whole batch); see :meth:`TorchRLCollector.batch`."""

    def __init__(self) -> None:
        self.steps: int | None = None

    def collection_stopped(self) -> bool:
        """Called by the collector after each env step of a batch."""
        if self.steps is None:
            return False
        self.steps -= 1
        return self.steps <= 0


class TorchRLCollector:
    """An endless TorchRL ``Collector`` of ``steps`` steps of the env's copies per batch (policy
    and storage on ``device``), each batch cut to the steps :meth:`batch` asks for."""

    def __init__(
        self, env: EnvBase, policy: TensorDictModuleBase, steps: int, device: torch.device
    ) -> None:
        self.steps, self._cut = steps, BatchCut()
        # TorchRL warns of a policy with no parameter or buffer to move to ``device``: trust it
        tensorless = next(chain(policy.parameters(), policy.buffers()), None) is None
        self.collector = Collector(
            env,
            policy,
            frames_per_batch=steps * max(env.batch_size.numel(), 1),
            total_frames=-1,
            policy_device=device,
            storing_device=device,
            interruptor=self._cut,
            trust_policy=True if tensorless else None,  # None: TorchRL's own choice
        )
        self._batches = iter(self.collector)
        # on one device the collector steps the very policy; otherwise it holds a copy
        self._copy_weights = device != torch.device(env.device)

    def batch(self, steps: int) -> TensorDictBase:
        """The next ``steps`` (at most a whole batch) steps of every copy."""
        self._cut.steps = steps if steps < self.steps else None
        return next(self._batches)[..., :steps]

    def restart(self, seed: int) -> None:
        """Every copy reset, the env seeded with ``seed``."""
        self.collector.set_seed(seed)
        self.collector.reset()

    def sync(self) -> None:
        """The collector's copy of the policy (if it holds one) takes the policy's weights."""
        if self._copy_weights:
            self.collector.update_policy_weights_()

    def close(self) -> None:
        """Stop the collector and close its env."""
        self.collector.shutdown()


class ArrayCollector:
    """The lean collection path: a :func:`rlpipe.make_env` env's copies stepped on arrays
    (``copies``, from :func:`rlpipe.envs.env_copies`), ``act`` choosing the actions.

    Its batches hold what the algorithms read of TorchRL's ``Collector``'s on the same env, with
    the same dtypes, shapes and, for the same actions, values: ``observation``, the outputs of
    ``act`` and, under ``"next"``, the step's ``observation``, ``reward``, ``done``,
    ``terminated`` and ``truncated`` with the ``step_count`` and ``episode_reward`` after it
    (not the Collector's ``is_init``, ``("collector", "traj_ids")`` or the counters and flags
    before each step). Episodes run on across batches; a finished copy is reset before its next
    step; the seeds and resets are the backend's calls in TorchRL's order, so the same seed
    gives the same episodes. Observations go to ``device`` for ``act``, actions back to the
    env, and the batches are stored on ``device``.
    """

    def __init__(
        self, env: EnvBase, copies: EnvCopies, act: CollectAction, device: torch.device
    ) -> None:
        self.env, self.copies, self.act, self.device = env, copies, act, device
        self.n = env.batch_size.numel()
        self._obs_dtype = env.observation_spec["observation"].dtype
        self._reward_dtype = torch_to_numpy_dtype_dict[env.reward_spec.dtype]
        self._action_dtype = torch_to_numpy_dtype_dict[env.base_env.action_spec.dtype]
        self._start()

    def _start(self) -> None:
        """Every copy in a new episode (a full reset)."""
        self._obs = self.copies.reset_copies()
        self._count = np.zeros(self.n, np.int64)  # StepCounter's step_count
        self._return = np.zeros(self.n, self._reward_dtype)  # RewardSum's episode_reward

    @torch.no_grad()
    def batch(self, steps: int) -> TensorDictBase:
        """The next ``steps`` steps of every copy, ``[copies, steps]``."""
        rows, outs = [], []
        with set_exploration_type(ExplorationType.RANDOM):  # the Collector's
            for _ in range(steps):
                out = self.act(torch.from_numpy(self._obs).to(self.device, self._obs_dtype))
                action = out["action"].cpu().numpy().astype(self._action_dtype, copy=False)
                obs, reward, terminated, truncated = self.copies.step_copies(action)
                reward = reward.astype(self._reward_dtype, copy=False)
                count, ret = self._count + 1, self._return + reward
                rows.append((self._obs, obs, reward, terminated, truncated, count, ret))
                outs.append(out)
                done = terminated | truncated
                self._count, self._return = np.where(done, 0, count), np.where(done, 0, ret)
                if done.any():
                    fresh = self.copies.reset_copies(done)
                    obs = np.where(done.reshape(-1, *(1,) * (obs.ndim - 1)), fresh, obs)
                self._obs = obs
        return self._assemble(rows, outs)

    def _assemble(self, rows: list[tuple], outs: list[dict[str, torch.Tensor]]) -> TensorDictBase:
        """One TensorDict of the steps' arrays and the outputs of ``act``, ``[copies, steps]``."""
        obs, nxt, reward, terminated, truncated, count, ret = (
            torch.from_numpy(np.ascontiguousarray(np.array(column).swapaxes(0, 1)))
            for column in zip(*rows)
        )
        terminated, truncated = terminated.unsqueeze(-1), truncated.unsqueeze(-1)
        batch = TensorDict(
            {
                "observation": obs.to(self._obs_dtype),
                "next": {
                    "observation": nxt.to(self._obs_dtype),
                    "reward": reward.unsqueeze(-1),
                    "done": terminated | truncated,
                    "terminated": terminated,
                    "truncated": truncated,
                    "step_count": count.unsqueeze(-1),
                    "episode_reward": ret.unsqueeze(-1),
                },
            },
            batch_size=[self.n, len(rows)],
            device=self.device,
        )
        for key in outs[0]:
            batch.set(key, torch.stack([out[key] for out in outs], 1))
        return batch

    def restart(self, seed: int) -> None:
        """Every copy reset, the env seeded with ``seed`` (as the Collector does it)."""
        self.env.set_seed(seed)
        self._start()

    def sync(self) -> None:
        """Nothing: ``act`` runs the policy itself."""

    def close(self) -> None:
        """Close the env."""
        self.env.close()


def policy_action(
    policy: TensorDictModuleBase, copies: int, device: torch.device
) -> CollectAction | None:
    """``policy`` as a :data:`CollectAction`: run on one TensorDict reused step after step,
    its ``out_keys`` returned; None for a policy that reads more than the observation (what
    the lean loop hands it) or is no TensorDict module."""
    if not isinstance(policy, TensorDictModuleBase) or not set(policy.in_keys) <= {"observation"}:
        return None
    carrier = TensorDict(batch_size=[copies], device=device)
    keys = list(policy.out_keys)

    def act(observation: torch.Tensor) -> dict[str, torch.Tensor]:
        carrier.set("observation", observation)
        out = policy(carrier)
        return {key: out.get(key) for key in keys}

    return act


def lean_collection(env: EnvBase, option: str, off: str) -> None:
    """Refuse, in one line, an ``option`` that only the lean loop's collecting policy (``act``)
    knows, on an env that TorchRL's ``Collector`` would step (no :func:`rlpipe.make_env`
    env); ``off``: the option's value that turns it off."""
    if env_copies(env) is None:
        raise RlpipeError(
            f"{option} needs an env made by rlpipe.make_env, whose copies rlpipe steps itself "
            f"(TorchRL's Collector would ignore it); use make_env's env or {option}={off}"
        )


def make_collector(
    env: EnvBase,
    policy: TensorDictModuleBase,
    steps: int,
    device: torch.device,
    act: CollectAction | None = None,
) -> ArrayCollector | TorchRLCollector:
    """The lean :class:`ArrayCollector` on a :func:`rlpipe.make_env` env (``act``, or ``policy``
    through :func:`policy_action`); TorchRL's (:class:`TorchRLCollector`, ``steps`` per batch)
    for any other env, or a policy that reads more than the observation."""
    copies = env_copies(env)
    act = act or policy_action(policy, env.batch_size.numel(), device)
    if copies is None or act is None:
        return TorchRLCollector(env, policy, steps, device)
    return ArrayCollector(env, copies, act, device)
