"""What a run says while it trains: PPO's, SAC's and DQN's diagnostics, training episodes at the
frame they ended, the bar's final evaluation, and off-policy batches rounded to whole steps of
the env copies with their updates per frame kept."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict

from rlpipe import Config, EnvConfig, RunDir, train
from rlpipe.algos import DQNConfig, PPOConfig, SACConfig
from rlpipe.algos.base import EPISODE_FRAMES, EPISODE_LENGTH, EPISODE_RETURN, episode_metrics


def test_episodes_carry_the_frame_they_ended_at_in_the_order_they_ended():
    """Copies 0 and 1, 3 steps, 100 frames counted at the batch's end: copy 1 ends at its first
    step (frame 96), copy 0 at its second (98) and third (100)."""
    done = torch.tensor([[False, True, True], [True, False, False]]).unsqueeze(-1)
    batch = TensorDict(
        {
            "next": {
                "done": done,
                "episode_reward": torch.tensor([[0.0, 2.0, 3.0], [1.0, 0.0, 0.0]]).unsqueeze(-1),
                "step_count": torch.tensor([[0, 5, 1], [7, 0, 0]]).unsqueeze(-1),
            }
        },
        batch_size=[2, 3],
    )
    out = episode_metrics(batch, ended_by=100)
    assert out[EPISODE_FRAMES] == [96, 98, 100]
    assert out[EPISODE_RETURN] == [1.0, 2.0, 3.0] and out[EPISODE_LENGTH] == [7.0, 5.0, 1.0]
    assert EPISODE_FRAMES not in episode_metrics(batch)  # no frame count: no frames


def _rows(run: RunDir, name: str) -> list[tuple[int, float]]:
    steps, values = run.metric(name)
    return list(zip((int(s) for s in steps), values, strict=True))


def _tiny(algo, env: EnvConfig, frames: int, tmp_path) -> RunDir:
    cfg = Config(
        env=env, algo=algo, total_frames=frames, eval_every=0, eval_episodes=2, progress=False
    )
    train(cfg, tmp_path)
    return RunDir(tmp_path)


def test_ppo_logs_its_diagnostics_and_episodes_inside_its_batches(tmp_path):
    algo = PPOConfig(frames_per_batch=256, minibatch_size=64, epochs=2)
    run = _tiny(algo, EnvConfig(id="CartPole-v1", num_envs=4), 1024, tmp_path)
    for name in (
        "train/policy_gradient_loss",
        "train/value_loss",
        "train/entropy",
        "train/approx_kl",
        "train/clip_fraction",
        "train/explained_variance",
    ):
        assert _rows(run, name), name
    entropy = [v for _, v in _rows(run, "train/entropy")]
    assert all(0 < v <= torch.log(torch.tensor(2.0)) + 1e-6 for v in entropy)  # two actions
    ended = [step for step, _ in _rows(run, "train/episode_return")]
    assert ended == sorted(ended) and ended[-1] <= 1024
    assert any(step % 256 for step in ended)  # not all stamped at a batch's end


def test_sac_logs_alpha_each_critic_and_the_actor(tmp_path):
    algo = SACConfig(learning_starts=32, batch_size=16, hidden_sizes=[16, 16])
    run = _tiny(algo, EnvConfig(id="Pendulum-v1", max_episode_steps=40), 96, tmp_path)
    names = ("alpha", "actor_loss", "q1_loss", "q2_loss", "alpha_loss", "entropy")
    for name in names:
        assert _rows(run, f"train/{name}"), name
    assert all(v >= 0 for name in ("q1_loss", "q2_loss") for _, v in _rows(run, f"train/{name}"))


def test_dqn_logs_its_mean_q(tmp_path):
    algo = DQNConfig(learning_starts=16, batch_size=8, buffer_size=64, hidden_sizes=[16])
    run = _tiny(algo, EnvConfig(id="CartPole-v1"), 96, tmp_path)
    assert _rows(run, "train/q_mean")


@pytest.mark.parametrize(
    ("copies", "frames", "updates", "expected"),
    [(8, 4, 4, (8, 8)), (3, 4, 2, (6, 3)), (4, 8, 2, (8, 2)), (16, 128, 32, (128, 32))],
)
def test_off_policy_batches_keep_their_updates_per_frame(copies, frames, updates, expected):
    cfg = Config(
        env=EnvConfig(num_envs=copies),
        algo=DQNConfig(frames_per_batch=frames, updates_per_batch=updates),
    ).resolved()
    assert (cfg.algo.frames_per_batch, cfg.algo.updates_per_batch) == expected


def test_config_yaml_records_the_rounded_batch(tmp_path):
    algo = DQNConfig(frames_per_batch=4, updates_per_batch=4, learning_starts=8, batch_size=8)
    run = _tiny(algo, EnvConfig(id="CartPole-v1", num_envs=8), 64, tmp_path)
    recorded = run.read_config().algo
    assert (recorded.frames_per_batch, recorded.updates_per_batch) == (8, 8)


def test_the_bar_ends_on_the_final_evaluation(tmp_path):
    command = [sys.executable, "-m", "rlpipe", "algo=dqn", "env=cartpole", "~tuned"]
    command += ["total_frames=200", "eval_every=0", "eval_episodes=2", "progress=true"]
    done = subprocess.run(
        [*command, f"hydra.run.dir={tmp_path}"], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    summary = RunDir(tmp_path).read_summary()
    bars = [part.strip() for part in done.stderr.split("\r") if "frame/s" in part]
    last_bar = bars[-1]
    assert f"eval={summary.eval_mean:.1f}" in last_bar, last_bar
