"""The shared runner and greedy evaluation."""

from __future__ import annotations

import json
from functools import partial

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from rlpipe.algos import DQN, DQNConfig
from rlpipe.checkpoint import list_checkpoints, load_checkpoint
from rlpipe.config import EnvConfig, LoggerConfig
from rlpipe.envs import make_env
from rlpipe.episodes import evaluate
from rlpipe.loggers import make_logger
from rlpipe.runner import Runner


class _ConstantAction(nn.Module):
    def forward(self, obs):
        return torch.zeros(obs.shape[:-1], dtype=torch.long)


def test_evaluate_counts_exact_episodes():
    policy = TensorDictModule(_ConstantAction(), in_keys=["observation"], out_keys=["action"])
    env = make_env(EnvConfig(id="CartPole-v1", max_episode_steps=20), num_envs=3, seed=0)
    result = evaluate(policy, env, episodes=7)
    assert len(result.returns) == len(result.lengths) == 7
    # pushing left always topples the pole within a handful of steps; return == length
    assert all(1 <= n <= 20 for n in result.lengths)
    assert result.returns == [float(n) for n in result.lengths]
    assert result.metrics()["eval/return_mean"] == pytest.approx(sum(result.returns) / 7)


def test_runner_logs_checkpoints_and_summarises(tmp_path):
    torch.manual_seed(0)
    algo = DQN(
        partial(make_env, EnvConfig(num_envs=2), seed=0),
        DQNConfig(batch_size=8, buffer_size=64, learning_starts=8, frames_per_batch=10),
    )
    runner = Runner(
        algo,
        make_env(EnvConfig(), num_envs=2, seed=1),
        tmp_path,
        total_frames=400,
        eval_every=100,
        eval_episodes=2,
        checkpoint_every=100,
        keep_checkpoints=2,
        logger=make_logger(LoggerConfig("csv"), tmp_path),
        progress=False,
        log_every=50,
    )
    result = runner.run()
    algo.close()
    assert result.frames == 400 and result.eval_episodes == 2
    ckpts = list_checkpoints(tmp_path / "checkpoints")
    assert [p.name for p in ckpts] == ["ckpt_000000000300.pt", "ckpt_000000000400.pt"]
    assert load_checkpoint(ckpts[-1])["frames"] == 400
    scalars = tmp_path / "metrics" / "scalars"
    evals = (scalars / "eval" / "return_mean.csv").read_text().split()
    assert [row.split(",")[0] for row in evals] == ["100", "200", "300", "400"]
    for name in ("train/loss", "train/episode_return", "time/fps", "time/train_seconds"):
        assert (scalars / f"{name}.csv").stat().st_size > 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["frames"] == 400 and summary["eval_mean"] == pytest.approx(result.eval_mean)
    assert "final eval" in result.summary_line() and str(tmp_path) in result.summary_line()
