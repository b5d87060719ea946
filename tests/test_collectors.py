"""The lean collection path (``rlpipe.algos.collectors``): its batches equal TorchRL's Collector's
on the same env and actions, value by value on the keys the algorithms read, on both backends
(episodes across batches, partial resets, cuts, restarts); restarts reseed; DQN's, SAC's and
PPO's plain-tensor policies draw what their TensorDict policies draw; which envs get which path;
the cut at the run's frame limit; benchmarks/collection.py's table."""

from __future__ import annotations

import subprocess
import sys
import warnings
from functools import partial
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.envs import ExplorationType, RewardScaling, set_exploration_type

from rlpipe import DQN, PPO, SAC, DQNConfig, EnvConfig, PPOConfig, SACConfig, make_env
from rlpipe.algos.collectors import ArrayCollector, TorchRLCollector, make_collector
from rlpipe.envs import backends as env_backends

CPU = torch.device("cpu")
# what the lean batches hold of the Collector's: what the algorithms read
NEXT = ("observation", "reward", "done", "terminated", "truncated", "step_count", "episode_reward")
LEAN_KEYS = {"observation", "action", *(("next", key) for key in NEXT)}
NO_ENVPOOL = pytest.mark.skipif(env_backends.envpool_version() is None, reason="no EnvPool")
BACKENDS = ["gymnasium", pytest.param("envpool", marks=NO_ENVPOOL)]


class Deterministic(nn.Module):
    """A fixed policy: CartPole's cart pushed right until it runs faster than 1.5 (its episodes
    end by falling and by a time limit of 10), or a fixed linear map's tanh (continuous)."""

    def __init__(self, in_features: int, discrete: bool) -> None:
        super().__init__()
        self.discrete = discrete
        self.linear = nn.Linear(in_features, 1)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if self.discrete:
            return (observation[..., 1] < 1.5).long()
        return self.linear(observation).tanh()


@pytest.mark.parametrize(
    ("backend", "env_id", "limit", "falls"),
    [
        ("gymnasium", "CartPole-v1", 10, True),
        pytest.param("envpool", "CartPole-v1", 10, True, marks=NO_ENVPOOL),
        ("gymnasium", "Pendulum-v1", 7, False),  # Pendulum's episodes end at the limit only
        pytest.param("envpool", "Pendulum-v1", 7, False, marks=NO_ENVPOOL),
        ("gymnasium", "rlpipe/CartPoleContinuous-v0", 9, False),  # a NumPy-batched vector env
    ],
)
def test_lean_batches_equal_the_collectors(backend, env_id, limit, falls):
    cfg = EnvConfig(id=env_id, num_envs=3, max_episode_steps=limit, backend=backend)
    lean_env, ref_env = make_env(cfg, seed=3), make_env(cfg, seed=3)
    torch.manual_seed(0)
    size = lean_env.observation_spec["observation"].shape[-1]
    policy = TensorDictModule(
        Deterministic(size, discrete=env_id == "CartPole-v1"), ["observation"], ["action"]
    )
    lean = make_collector(lean_env, policy, 8, CPU)
    ref = TorchRLCollector(ref_env, policy, 8, CPU)
    assert isinstance(lean, ArrayCollector)
    ended = {"terminated": 0, "truncated": 0}
    for i, steps in enumerate([8, 8, 3, 8, 5, 8, 8]):  # cuts; a restart before the fifth
        if i == 4:
            lean.restart(11)
            ref.restart(11)
        ours, theirs = lean.batch(steps), ref.batch(steps)
        assert ours.batch_size == theirs.batch_size == (3, steps)
        assert set(ours.keys(True, True)) == LEAN_KEYS < set(theirs.keys(True, True))
        for key, value in ours.items(True, True):
            assert value.dtype == theirs[key].dtype and value.shape == theirs[key].shape, key
            assert torch.equal(value, theirs[key]), (i, key)
        for flag in ended:
            ended[flag] += int(theirs["next", flag].sum())
    # partial resets happened inside and across batches, of both kinds where the policy falls
    assert ended["truncated"] > 0 and (ended["terminated"] > 0) == falls
    lean.close()
    ref.close()
    assert lean_env.is_closed and ref_env.is_closed


@pytest.mark.parametrize("backend", BACKENDS)
def test_restart_reseeds_the_copies(backend):
    cfg = EnvConfig(id="CartPole-v1", num_envs=2, backend=backend)
    policy = TensorDictModule(Deterministic(4, True), ["observation"], ["action"])
    one, two = (make_collector(make_env(cfg, seed=s), policy, 4, CPU) for s in (1, 2))
    assert not torch.equal(one.batch(4)["observation"], two.batch(4)["observation"])
    one.restart(5)
    two.restart(5)
    first, second = one.batch(4), two.batch(4)
    assert torch.equal(first["observation"], second["observation"])
    # fresh episodes: the first step of each copy counts 1 and sums its own reward
    assert (first["next", "step_count"][:, 0] == 1).all()
    assert torch.equal(first["next", "episode_reward"][:, 0], first["next", "reward"][:, 0])
    one.restart(6)
    assert not torch.equal(one.batch(4)["observation"], first["observation"])
    one.close()
    two.close()


def test_other_envs_and_policies_keep_torchrls_collector():
    env_cfg = EnvConfig(id="CartPole-v1", num_envs=2, backend="gymnasium")
    policy = TensorDictModule(Deterministic(4, True), ["observation"], ["action"])
    assert isinstance(make_collector(make_env(env_cfg), policy, 4, CPU), ArrayCollector)
    scaled = make_env(env_cfg)
    scaled.append_transform(RewardScaling(0.0, 2.0))  # a transform make_env does not add
    assert isinstance(make_collector(scaled, policy, 4, CPU), TorchRLCollector)
    counting = TensorDictModule(  # reads the step count, which only TorchRL's Collector feeds
        lambda obs, count: count.squeeze(-1) % 2, ["observation", "step_count"], ["action"]
    )
    with warnings.catch_warnings():  # a policy without weights: nothing for TorchRL to warn about
        warnings.simplefilter("error")
        collector = make_collector(make_env(env_cfg), counting, 4, CPU)
    assert isinstance(collector, TorchRLCollector)
    assert collector.batch(4)["action"][0].tolist() == [0, 1, 0, 1]


def _drawn(algo, policy, observation: torch.Tensor) -> tuple[dict, TensorDict]:
    """The plain-tensor policy's outputs and the TensorDict policy's, from one seed each."""
    torch.manual_seed(1)
    with torch.no_grad():
        plain = algo.collector.act(observation)
    torch.manual_seed(1)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        td = policy(TensorDict(observation=observation, batch_size=observation.shape[:1]))
    return plain, td


@pytest.mark.parametrize(
    ("name", "env_id", "keys"),
    [
        ("dqn", "CartPole-v1", {"action"}),
        ("sac", "Pendulum-v1", {"action"}),
        ("ppo", "CartPole-v1", {"action", "action_log_prob"}),
        ("ppo", "Pendulum-v1", {"action", "sample", "sample_log_prob"}),
    ],
)
def test_plain_policies_draw_what_the_tensordict_policies_draw(name, env_id, keys):
    configs = {
        "dqn": (DQN, DQNConfig()),
        "sac": (SAC, SACConfig()),
        "ppo": (PPO, PPOConfig(frames_per_batch=64, minibatch_size=64)),
    }
    cls, cfg = configs[name]
    algo = cls(partial(make_env, EnvConfig(id=env_id, num_envs=4, backend="gymnasium")), cfg)
    assert isinstance(algo.collector, ArrayCollector)
    policy = algo.policy
    if name == "dqn":
        algo.exploration.eps.fill_(0.5)
        policy = TensorDictSequential(algo.policy, algo.exploration)
    observation = torch.randn(64, algo.collector.env.observation_spec["observation"].shape[-1])
    plain, td = _drawn(algo, policy, observation)
    assert set(plain) == keys
    for key, value in plain.items():
        assert value.dtype == td[key].dtype and value.shape == td[key].shape, key
        assert torch.equal(value, td[key]), key
    if name == "dqn":  # ε 0.5 over 2 actions: about a quarter of the actions are not greedy
        greedy = algo.policy(TensorDict(observation=observation, batch_size=[64]))["action"]
        assert 0 < int((plain["action"] != greedy).sum()) < 32
    algo.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_collect_cuts_at_the_frame_limit_to_whole_steps(backend):
    env_cfg = EnvConfig(id="CartPole-v1", num_envs=3, backend=backend)
    cfg = DQNConfig(frames_per_batch=12, batch_size=4, learning_starts=1000)
    algo = DQN(partial(make_env, env_cfg, seed=0), cfg)
    assert isinstance(algo.collector, ArrayCollector)
    assert algo.collect().batch_size == (3, 4)
    assert algo.collect(at_most=4).batch_size == (3, 2)  # 4 frames: 2 steps of 3 copies
    algo.limit_frames(30)
    algo.frames = 23
    assert algo.collect().batch_size == (3, 3)  # 7 frames left: 3 whole steps
    algo.frames = 29
    assert algo.collect().batch_size == (3, 1)
    algo.close()


def test_the_collection_benchmark_writes_its_table(tmp_path):
    out = tmp_path / "BENCH.md"
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "collection.py"
    args = ["--presets", "sac_pendulum", "--backends", "gymnasium", "--rounds", "1"]
    proc = subprocess.run(
        [sys.executable, str(script), *args, "--steps", "2", "--append", str(out)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in out.read_text().splitlines() if line.startswith("| `sac_pendulum`")]
    assert len(rows) == 1 and rows[0].count("|") == 9, out.read_text()
    cells = [cell.strip() for cell in rows[0].split("|")[1:-1]]
    assert cells[1:3] == ["gymnasium", "1"] and all(float(c) > 0 for c in cells[3:7])
