"""Model-based RL: collect with model-predictive control, fit learned dynamics/reward/termination
models, plan on them (PETS-style, deterministic ensemble). See :mod:`rlpipe.algos.mbrl.planning`."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded, ReplayBuffer
from torchrl.envs import EnvBase, ExplorationType
from torchrl.envs.utils import exploration_type

from rlpipe.algos.base import EnvAlgorithm, Metrics, batch_steps, episode_metrics
from rlpipe.algos.configs import MBRLConfig
from rlpipe.algos.mbrl.planning import ActionCoder, Planner, WorldModel
from rlpipe.algos.storage import LeafStorage
from rlpipe.envs import is_discrete, num_actions, observation_size
from rlpipe.errors import RlpipeError, check
from rlpipe.models import instantiate, network_spec

MODEL_LOSS = "train/model_loss"  # the models' mean training loss over a fit
_EVAL_SEED = 0  # the greedy policy's sampling noise: the same for every call
# env steps per collector batch, at most (single env: ~16 planner calls, ~1 s on 2 busy cores);
# train_step polls stop_requested between two such sub-batches
_SUB_BATCH_STEPS = 16


def action_coder(env: EnvBase, device: torch.device) -> ActionCoder:
    """The planner's action encoding for ``env`` (bounds on ``device``); a clear error for
    unsupported action spaces."""
    if is_discrete(env):
        return ActionCoder(num_actions=num_actions(env))
    spec = env.action_spec_unbatched
    box = isinstance(spec, Bounded) and spec.dtype.is_floating_point and len(spec.shape) == 1
    if not box or not bool(torch.isfinite(torch.cat([spec.space.low, spec.space.high])).all()):
        raise RlpipeError(
            f"MBRL's planner needs discrete actions or a bounded flat box of continuous actions, "
            f"but this env's actions are {type(spec).__name__} of shape {tuple(spec.shape)}"
        )
    return ActionCoder(low=spec.space.low.to(device), high=spec.space.high.to(device))


class MPCPolicy(nn.Module):
    """``observation -> action`` by planning on the world model (model-predictive control).

    In deterministic (greedy) mode, and outside any exploration context, the planner's noise is
    re-seeded on every call, so the action is a function of the observation and the models.
    In random (collection) mode it draws from ``generator``, or, while ``warmup`` is set, the
    actions are uniformly random.
    """

    def __init__(self, planner: Planner, generator: torch.Generator) -> None:
        super().__init__()
        self.planner = planner
        self.model = planner.model  # registered, so evaluation finds the policy's device
        self.generator = generator
        self.warmup = False
        self._greedy = torch.Generator()

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        batch_shape = observation.shape[:-1]
        flat = observation.reshape(-1, observation.shape[-1])
        if exploration_type() != ExplorationType.RANDOM:
            action = self.planner.plan(flat, self._greedy.manual_seed(_EVAL_SEED))
        elif self.warmup:
            action = self._random(len(flat), observation.device)
        else:
            action = self.planner.plan(flat, self.generator)
        return action.reshape(*batch_shape, *action.shape[1:])

    def _random(self, n: int, device: torch.device) -> torch.Tensor:
        coder = self.planner.coder
        if coder.discrete:
            return torch.randint(coder.num_actions, (n,), generator=self.generator).to(device)
        return coder.decode(torch.rand(n, coder.size, generator=self.generator).to(device) * 2 - 1)


_STORED_KEYS = (
    "observation",
    "action",
    ("next", "observation"),
    ("next", "reward"),
    ("next", "terminated"),
)


class MBRL(EnvAlgorithm):
    """Model-based RL on a batched TorchRL env, discrete or bounded continuous actions.

    Each :meth:`train_step` collects ``cfg.frames_per_batch`` frames (rounded up to whole steps
    of the env's copies) with the MPC planner (uniformly random actions until the first fit,
    which comes once ``cfg.warmup_frames`` are collected) through :meth:`collect`, stores
    the transitions in a ``ReplayBuffer`` (a random ``cfg.validation_fraction`` of them marked for
    validation), and, once warm-up is done, runs ``cfg.fit_steps`` Adam steps on the dynamics
    ensemble, reward and termination models and logs their validation losses. The greedy
    ``policy`` plans at every step: an evaluation costs ``eval_episodes × episode length / eval
    envs`` planner calls, each ``cem_iterations × horizon`` batched model steps over (eval envs ×
    candidates × members) rows.

    The frames come in sub-batches of at most ``_SUB_BATCH_STEPS`` env steps, each stored (buffer,
    normalisers, ``frames``) as it arrives, and :attr:`stop_requested` is polled between two of them
    and between two Adam steps: once it is True, ``train_step`` returns after the current
    sub-batch (skipping the fit) or Adam step, and a checkpoint taken then is a valid resume
    point. The next ``train_step`` completes the interrupted iteration (collects up to the next
    multiple of the iteration's frames), so fits come at the same frame counts as without a stop.

    ``network`` (or ``cfg.network``) is your world model in place of the default: see
    :meth:`world_model`.
    """

    cfg: MBRLConfig
    finite_keys = (MODEL_LOSS,)
    state_attrs = ("model", "optimizer", "buffer", "fit_generator", "plan_generator")

    def _build(self, env: EnvBase) -> None:
        cfg = self.cfg
        coder = action_coder(env, self.device)
        self.model = self.world_model(observation_size(env, "MBRL"), coder.size).to(self.device)
        planner = Planner(
            self.model,
            coder,
            method=cfg.planner,
            horizon=cfg.horizon,
            candidates=cfg.num_candidates,
            iterations=cfg.cem_iterations,
            elites=cfg.elites,
            gamma=cfg.gamma,
            init_std=cfg.init_std,
        )
        # the generators this algorithm owns, seeded from the global one (seed_everything)
        seeds = torch.randint(2**62, (2,)).tolist()
        self.fit_generator = torch.Generator().manual_seed(seeds[0])
        self.plan_generator = torch.Generator().manual_seed(seeds[1])
        self.mpc = MPCPolicy(planner, self.plan_generator)
        self.mpc.warmup = cfg.warmup_frames > 0
        self.policy = TensorDictModule(self.mpc, in_keys=["observation"], out_keys=["action"])
        self.optimizer = torch.optim.Adam(
            self.model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay
        )
        self.buffer = ReplayBuffer(
            storage=LeafStorage(cfg.buffer_size, device=self.device),
            batch_size=cfg.batch_size,
        )
        num_envs, steps = batch_steps(env, cfg.frames_per_batch)  # steps per iteration
        self.iteration_frames = steps * num_envs
        sub_batch = _sub_batch_steps(steps) * num_envs
        self.make_collector(env, self.policy, sub_batch)

    def world_model(self, obs_size: int, action_size: int) -> WorldModel:
        """``network`` (a :class:`WorldModel`, e.g. a subclass with other networks), or one
        ``cfg.network`` builds (called with ``obs_size``, ``action_size``, ``hidden_sizes`` and
        ``members`` unless it sets them), else the default :class:`WorldModel`."""
        sizes = dict(
            obs_size=obs_size,
            action_size=action_size,
            hidden_sizes=self.cfg.hidden_sizes,
            members=self.cfg.ensemble_size,
        )
        spec = network_spec(self.user_network, self.cfg.network)
        model = instantiate(spec, "algo.network", **sizes) if spec else self.user_network
        if model is None:
            return WorldModel(**sizes)
        check(
            isinstance(model, WorldModel),
            f"MBRL's network is its world model: a rlpipe.algos.mbrl.WorldModel (or a subclass), "
            f"got {type(model).__name__}",
        )
        return model

    def train_step(self) -> Metrics:
        """Collect the rest of the iteration's frames sub-batch by sub-batch, then fit; return
        early, without fitting, once :attr:`stop_requested` is True (see the class docstring)."""
        self.iterations += 1
        target = self.iteration_frames - self.frames % self.iteration_frames
        collected = 0
        metrics: Metrics = {}
        while collected < target and not self.stop_requested:
            batch = self.collect(target - collected)
            self._store(batch)
            collected += batch.numel()
            for key, values in episode_metrics(batch, self.frames).items():
                metrics.setdefault(key, []).extend(values)
        if collected < target:  # stopped: the next iteration fits on all the data
            return metrics
        if self.frames >= self.cfg.warmup_frames:
            metrics.update(self.fit())
            self.mpc.warmup = False
        return metrics

    def _store(self, batch: TensorDictBase) -> None:
        """Count the frames of a collected batch, store them and fold them into the normalisers."""
        self.frames += batch.numel()
        data = batch.reshape(-1).select(*_STORED_KEYS)
        held_out = torch.rand(len(data), generator=self.fit_generator)
        data["validation"] = (held_out < self.cfg.validation_fraction).to(self.device)
        self.model.observe(
            data["observation"],
            data["next", "observation"],
            data["next", "reward"],
            data["next", "terminated"],
        )
        self.buffer.extend(data)

    def fit(self) -> Metrics:
        """``cfg.fit_steps`` Adam steps on the models (fewer once :attr:`stop_requested` is True, at
        least one); training and validation losses."""
        data = self.buffer[: len(self.buffer)]
        train, valid = data[~data["validation"]], data[data["validation"]]
        if len(train) == 0:
            return {}
        members = self.cfg.ensemble_size
        terminal = float(train["next", "terminated"].float().mean())
        weight = (1 - terminal) / terminal if terminal > 0 else 1.0  # balanced classes
        totals = []
        for _ in range(self.cfg.fit_steps):
            idx = torch.randint(
                len(train), (members, self.cfg.batch_size), generator=self.fit_generator
            )
            losses = self.model.losses(*self._tensors(train[idx.to(self.device)]), weight)
            loss = sum(losses.values())
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            self.optimizer.step()
            totals.append(loss.detach())
            if self.stop_requested:
                break
        metrics: Metrics = {MODEL_LOSS: float(torch.stack(totals).mean())}
        if len(valid):
            with torch.no_grad():
                valid = valid.unsqueeze(0).expand(members, len(valid))
                for name, value in self.model.losses(*self._tensors(valid), weight).items():
                    metrics[f"train/val_{name}_loss"] = float(value)
        return metrics

    def _tensors(self, data: TensorDictBase) -> tuple[torch.Tensor, ...]:
        """Observation, encoded action, next observation, reward, terminated of ``[E, N]`` rows."""
        return (
            data["observation"],
            self.mpc.planner.coder.encode(data["action"]),
            data["next", "observation"],
            data["next", "reward"].squeeze(-1),
            data["next", "terminated"].squeeze(-1),
        )

    def _restored(self) -> None:
        # random actions until the first fit (an Adam step leaves optimiser state), also when a
        # stop skipped the fit that ends the warm-up
        fitted = bool(self.optimizer.state)
        warmup = self.cfg.warmup_frames
        self.mpc.warmup = self.frames < warmup or (warmup > 0 and not fitted)


def _sub_batch_steps(steps: int) -> int:
    """The largest divisor of an iteration's ``steps`` up to ``_SUB_BATCH_STEPS``: sub-batches
    that add up to the iteration exactly."""
    return max(k for k in range(1, min(steps, _SUB_BATCH_STEPS) + 1) if steps % k == 0)
