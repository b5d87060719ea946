"""The shared runner and greedy evaluation."""

from __future__ import annotations

import json
from dataclasses import replace
from functools import partial

import pytest
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from rlpipe.algos import DQN, DQNConfig
from rlpipe.checkpoint import load_checkpoint
from rlpipe.config import Config, EnvConfig, LoggerConfig
from rlpipe.envs import make_env
from rlpipe.envs.backends import backend_of
from rlpipe.episodes import evaluate
from rlpipe.loggers import make_logger
from rlpipe.rundir import RunDir
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
        RunDir(tmp_path),
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
    ckpts = RunDir(tmp_path).checkpoints()
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
    assert " over 2 episodes | 400 frames | " in result.summary_line()
    assert " over 1 episode | " in replace(result, eval_episodes=1).summary_line()


def test_a_runner_run_is_a_run_for_evaluate_plot_and_resume(tmp_path, capsys):
    """A hand-built Runner writes config.yaml: ``rlpipe.evaluate`` evaluates it, plots group
    it, and ``train`` continues it from its checkpoint."""
    from rlpipe.evaluate import main as evaluate_main
    from rlpipe.pipeline import train
    from rlpipe.runs import find_runs, group_runs

    torch.manual_seed(3)
    env_cfg = EnvConfig(id="CartPole-v1", num_envs=2)
    algo = DQN(partial(make_env, env_cfg, seed=3), DQNConfig(frames_per_batch=16))
    eval_env = make_env(env_cfg, num_envs=2, seed=1)
    run_dir = tmp_path / "by-hand"
    logger = make_logger(LoggerConfig("csv"), run_dir)
    Runner(
        algo,
        eval_env,
        RunDir(run_dir),
        total_frames=64,
        eval_every=32,
        eval_episodes=2,
        logger=logger,
        progress=False,
    ).run()
    algo.close()
    eval_env.close()
    cfg = RunDir(run_dir).read_config()
    used = replace(env_cfg, backend=backend_of(env_cfg))  # config.yaml names the backend used
    assert (cfg.env, cfg.seed, cfg.total_frames, cfg.eval_every) == (used, 3, 64, 32)
    assert cfg.algo == DQNConfig(
        frames_per_batch=16,
        total_frames=64,
        eval_every=32,
        eval_episodes=2,
        checkpoint_every=25_000,
    )
    assert load_checkpoint(RunDir(run_dir).checkpoints()[-1])["config"]["seed"] == 3
    evaluate_main([f"run_dir={run_dir}", "episodes=2"])
    assert "on CartPole-v1: return" in capsys.readouterr().out
    assert [g.runs for g in group_runs(find_runs([tmp_path]))] == [[run_dir]]
    result = train(replace(cfg, total_frames=96, progress=False), run_dir)  # resumes at 64
    assert result.frames == 96
    assert RunDir(run_dir).metric("eval/return_mean")[0].tolist() == [32, 64, 96]
    # every eval row has its times, and no frame count has two time/elapsed rows
    elapsed = RunDir(run_dir).metric("time/elapsed")[0].tolist()
    assert len(set(elapsed)) == len(elapsed) and {32, 64, 96} <= set(elapsed)
    assert RunDir(run_dir).metric("time/train_seconds")[0].tolist() == [32, 64, 96]


def test_a_runner_without_a_known_config_writes_none(tmp_path):
    torch.manual_seed(0)
    env_cfg = EnvConfig(id="CartPole-v1")
    algo = DQN(lambda: make_env(env_cfg), DQNConfig(frames_per_batch=16))  # not a partial
    eval_env = make_env(env_cfg, seed=1)
    Runner(algo, eval_env, RunDir(tmp_path), total_frames=16, eval_episodes=1, progress=False).run()
    algo.close()
    eval_env.close()
    assert (tmp_path / "summary.json").is_file() and not (tmp_path / "config.yaml").exists()


def test_the_bar_ends_where_the_binding_budget_ends():
    """ARS with algo.iterations=3 and a large total_frames: the bar's total (and ETA) follow
    the 3 iterations, at the frames per iteration so far; the bar shows one rate; a last
    batch past total_frames raises the total rather than overrunning it."""
    from types import SimpleNamespace

    from rlpipe.progress import ProgressBar, postfix

    algo = SimpleNamespace(frames=0, iterations=0, budget=3)
    bar = ProgressBar(algo, 60_000_000, enabled=False)
    algo.frames, algo.iterations = 2_000, 1
    bar.advance()
    assert (bar.shown, bar.bar.total) == (2_000, 6_000)
    algo.budget = 10**6  # the frames bind first
    bar.advance()
    assert bar.bar.total == 60_000_000
    algo.frames = 60_000_512  # a last whole batch past total_frames
    bar.advance()
    assert (bar.shown, bar.bar.total) == (60_000_512, 60_000_512)
    assert postfix(float("nan"), None) == {}  # no "fps" beside tqdm's rate, no ep_return=nan
    assert postfix(12.0, None) == {"ep_return": "12.0"}


def test_the_best_evaluation_keeps_its_checkpoint(tmp_path):
    """checkpoints/best_<frames>.pt holds the best evaluation's state (one file, beside the
    newest checkpoints); checkpoint=best loads it; a resume drops a best from the redone part."""
    from rlpipe.pipeline import load_run, train

    cfg = Config(
        env=EnvConfig(num_envs=2),
        algo=DQNConfig(frames_per_batch=16, learning_starts=32),
        total_frames=480,
        eval_every=96,
        eval_episodes=2,
        checkpoint_every=192,
        progress=False,
    )
    train(cfg, tmp_path)
    frames, means = RunDir(tmp_path).metric("eval/return_mean")
    best = int(frames[int(means.argmax())])  # the first of the best
    assert [p.name for p in RunDir(tmp_path).bests()] == [f"best_{best:012d}.pt"]
    best_checkpoint = RunDir(tmp_path).read_checkpoint("best")
    path, state = best_checkpoint.path, best_checkpoint.state
    assert state["frames"] == best and state["runner"]["best_eval"] == pytest.approx(means.max())
    run = load_run(tmp_path, "best")
    assert run.checkpoint == path and run.algo.frames == best
    run.algo.close()
    # a best from past the checkpoint a resume starts at belongs to the part redone: dropped
    (tmp_path / "checkpoints" / f"best_{10**6:012d}.pt").write_bytes(path.read_bytes())
    train(replace(cfg, total_frames=576), tmp_path)
    assert all(int(p.stem[5:]) <= 576 for p in RunDir(tmp_path).bests())


def test_each_run_and_evaluation_meets_its_own_starts():
    """Adjacent seeds (the held-out 100-109) and successive evaluations share no start; the
    scheme before, ``seed + 10000``, shared all of 20 copies but one between seeds 100 and 101."""
    from rlpipe.episodes import EVALUATION, FINAL, episodes_seed

    env_cfg = EnvConfig(id="MountainCar-v0", backend="gymnasium")

    def starts(seed: int) -> set[float]:
        env = make_env(env_cfg, num_envs=20, seed=seed)
        try:
            return set(env.reset()["observation"][:, 0].tolist())  # the car's position
        finally:
            env.close()

    seeds = [episodes_seed(s, EVALUATION, f) for s in (100, 101) for f in (10_000, 20_000)]
    seeds.append(episodes_seed(100, FINAL))
    assert seeds[0] == episodes_seed(100, EVALUATION, 10_000)  # a resumed run's are the same
    assert len(set().union(*map(starts, seeds))) == 20 * len(seeds)
    assert len(starts(10_100) & starts(10_101)) == 19  # what the test guards against


def test_the_runner_seeds_every_evaluation_from_its_seed_and_frames(tmp_path):
    from rlpipe.episodes import EVALUATION, episodes_seed

    torch.manual_seed(0)
    env_cfg = EnvConfig(id="CartPole-v1")
    algo = DQN(partial(make_env, env_cfg, seed=7), DQNConfig(frames_per_batch=16))
    eval_env, used = make_env(env_cfg, seed=1), []
    seed_env = eval_env.set_seed
    eval_env.set_seed = lambda seed, **kw: used.append(seed) or seed_env(seed, **kw)
    runner = Runner(
        algo,
        eval_env,
        RunDir(tmp_path),
        total_frames=48,
        eval_every=16,
        eval_episodes=1,
        progress=False,
        eval_seed=7,
    )
    runner.run()
    algo.close()
    eval_env.close()
    assert used == [episodes_seed(7, EVALUATION, f) for f in (16, 32, 48)]
