"""Runs on the EnvPool backend: ARS's population rollouts on pools, every algorithm through the
command line, the backend a run records and resumes with, evaluation on either backend, and
every bad ``env.backend`` input as one line."""

from __future__ import annotations

import json
import os
from functools import partial

import numpy as np
import pytest
import torch
import yaml
from conftest import TINY
from test_ars_search import constant_outputs
from test_envpool import needs_envpool
from torch.nn.utils import parameters_to_vector

from rlpipe.algos.ars import ARS, ARSConfig, ARSSearch, make_ars_policy
from rlpipe.algos.ars.backends import _InProcess, _Processes
from rlpipe.algos.ars.rollout import pool_rollout, rollout
from rlpipe.config import Config, EnvConfig, config_from_dict, config_to_dict, fingerprint
from rlpipe.envs import envpool_env, make_env, sub_envs
from rlpipe.evaluate import main as evaluate_main

WALKER = EnvConfig(id="BipedalWalker-v3", backend="envpool")
CARTPOLE = EnvConfig(id="CartPole-v1", backend="envpool")


def population(env_cfg: EnvConfig, members: int, seed: int = 0):
    """An ARS policy for ``env_cfg`` and ``members`` random parameter vectors."""
    policy, _ = make_ars_policy(make_env(env_cfg, num_envs=1), ARSConfig())
    size = parameters_to_vector(policy.parameters()).numel()
    return policy, 0.1 * torch.randn(members, size, generator=torch.Generator().manual_seed(seed))


@needs_envpool
def test_a_members_episode_depends_only_on_its_seed_and_parameters():
    """Episodes of different lengths share one pool: each member steps alone once the others
    are done, and its episode is what it would be alone, with any threads."""
    policy, flat = population(WALKER, 4)
    flat[1] = flat[0]
    env = envpool_env(make_env(WALKER, num_envs=4, threads=2))
    together = pool_rollout(policy, env, flat, [7, 7, 8, 9], max_steps=300)
    assert together.returns[0] == together.returns[1] and together.lengths[0] == together.lengths[1]
    assert len(set(together.lengths.tolist())) > 1  # episodes of different lengths
    for member, seed in ((0, 7), (3, 9)):
        alone = pool_rollout(policy, env, flat[member : member + 1], [seed], max_steps=300)
        assert alone.raw_returns[0] == together.raw_returns[member]
        assert alone.lengths[0] == together.lengths[member]
    assert together.obs_count == int(together.lengths.sum())  # no filler observation seen


@needs_envpool
def test_pool_rollouts_match_gymnasium_rollouts_in_distribution():
    """CartPole pays 1 per step (a filler would pay 0); the same policy's episodes last as long
    on both backends."""
    policy, flat = population(CARTPOLE, 32)
    ours = pool_rollout(
        policy, envpool_env(make_env(CARTPOLE, num_envs=32)), flat, list(range(32)), max_steps=500
    )
    assert torch.equal(ours.raw_returns, ours.lengths.double())
    gym_env = make_env(
        EnvConfig(id="CartPole-v1", backend="gymnasium"), num_envs=32, vectorization="sync"
    )
    theirs = rollout(policy, sub_envs(gym_env), flat, list(range(32)), max_steps=500)
    assert (
        abs(ours.lengths.double().mean() - theirs.lengths.double().mean())
        < 0.3 * theirs.lengths.double().mean()
    )


@needs_envpool
def test_pool_rollouts_take_the_bound_penalty_off_the_training_returns():
    """As on gymnasium (tests/test_ars_search.py): raw torques 3 and -5 pay 0.1 x 1 and 0.1 x 3
    a step past Pendulum's bound 2, over its 200 steps."""
    pendulum = make_env(EnvConfig(id="Pendulum-v1", backend="envpool"), num_envs=3)
    policy, flat = constant_outputs(pendulum, [1.5, 3.0, -5.0])
    env = envpool_env(pendulum)
    own = pool_rollout(policy, env, flat, [0, 1, 2], max_steps=1000)
    penalised = pool_rollout(policy, env, flat, [0, 1, 2], max_steps=1000, bound_penalty=0.1)
    assert torch.equal(penalised.raw_returns, own.raw_returns)
    gap = (own.returns - penalised.returns).float()
    torch.testing.assert_close(gap, torch.tensor([0, 20, 60.0]))


@needs_envpool
def test_ars_shares_the_cores_out_among_its_workers_pools_for_the_same_theta():
    """One worker: the population on one pool here, a thread per core; two: a process each,
    its half of the population as one chunk on pools of its own; the same θ either way."""
    thetas = []
    for workers in (1, 2):
        torch.manual_seed(0)
        algo = ARS(
            partial(make_env, WALKER),
            ARSConfig(num_directions=4, num_best=2, workers=workers, episode_length=50),
        )
        algo.train_step()
        algo.train_step()
        backend = algo.search._backend
        if workers == 1:
            assert isinstance(backend, _InProcess)
            assert backend.rollouts.pool.threads == min(os.cpu_count() or 1, 8)
        else:
            assert isinstance(backend, _Processes) and len(backend.workers) == 2
            assert [len(chunk) for chunk in backend.chunks] == [4, 4]
        thetas.append(algo.search.theta)
        algo.close()
    assert torch.equal(*thetas)


@needs_envpool
def test_search_gives_the_same_theta_on_worker_processes_as_here():
    """On EnvPool an episode is decided by its seed and parameters: how the population is cut
    into chunks and spread over processes changes nothing (Box2D on gymnasium keeps a world)."""
    thetas = []
    for workers in (1, 2):
        policy, normalizer = make_ars_policy(make_env(WALKER, num_envs=1), ARSConfig())
        search = ARSSearch(
            policy,
            partial(make_env, WALKER),
            num_directions=4,
            normalizer=normalizer,
            max_steps=60,
            workers=workers,
            seed=3,
        )
        search.step()
        search.step()
        thetas.append(search.theta)
        search.close()
    assert torch.equal(*thetas)


ALGOS = {
    "dqn": [],
    "ppo": ["algo.frames_per_batch=100", "algo.minibatch_size=50"],
    "reinforce": ["env=cartpole", "algo.episodes_per_epoch=4", "algo.epochs=2"],
    "sac": ["env=pendulum", "algo.learning_starts=50", "algo.batch_size=32"],
    "mbrl": [
        "env=pendulum",
        "algo.warmup_frames=50",
        "algo.frames_per_batch=100",
        "algo.fit_steps=2",
        "algo.num_candidates=10",
        "algo.elites=2",
        "algo.horizon=3",
    ],
    "ars": ["env=bipedal", "algo.num_directions=2", "algo.num_best=2", "algo.episode_length=40"],
}


# ars runs on EnvPool by env.backend=auto in its own command-line test (and on BipedalWalker
# below); the others, on one env copy, run on gymnasium by auto: these ask for EnvPool
@needs_envpool
@pytest.mark.parametrize("algo", ["dqn", "ppo", "reinforce", "sac", "mbrl"])
def test_every_algorithm_trains_on_envpool_from_the_command_line(rlpipe_cli, tmp_path, algo):
    proc = rlpipe_cli(*TINY, f"algo={algo}", *ALGOS[algo], "env.backend=envpool")
    assert proc.returncode == 0, proc.stderr
    assert "rlpipe: env backend envpool (env.backend=envpool" in proc.stdout
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert config["env"]["backend"] == "envpool"


@needs_envpool
def test_the_same_seed_gives_the_same_numbers_run_to_run(rlpipe_cli, tmp_path):
    results = []
    for name in ("a", "b"):
        proc = rlpipe_cli(*TINY, "algo=ars", *ALGOS["ars"], run_dir=tmp_path / name)
        assert proc.returncode == 0 and "env backend envpool (auto: EnvPool" in proc.stdout
        returns = (
            tmp_path / name / "metrics" / "scalars" / "train" / "return_mean.csv"
        ).read_text()
        results.append(
            (returns, json.loads((tmp_path / name / "summary.json").read_text())["eval_mean"])
        )
    assert results[0] == results[1]


@pytest.mark.parametrize(
    "recorded, copies",
    [
        ("gymnasium", "env.num_envs=2"),  # where auto would take EnvPool (if installed)
        pytest.param("envpool", "env.num_envs=1", marks=needs_envpool),  # auto: gymnasium
    ],
)
def test_a_resume_keeps_the_backend_its_run_recorded(rlpipe_cli, tmp_path, recorded, copies):
    proc = rlpipe_cli(*TINY, copies, f"env.backend={recorded}")
    assert proc.returncode == 0, proc.stderr
    resume = [*TINY[:1], copies, "total_frames=300", "eval_every=100", "eval_episodes=2"]  # auto
    proc = rlpipe_cli(*resume)
    assert proc.returncode == 0, proc.stderr
    assert f"env backend {recorded} (auto: the one the run dir recorded)" in proc.stdout
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["frames"] == 300


def test_a_config_from_before_backends_ran_on_gymnasium():
    data = config_to_dict(Config())
    del data["env"]["backend"]
    assert config_from_dict(data).env.backend == "gymnasium"
    gymnasium_run = Config(env=EnvConfig(backend="gymnasium"))
    assert (
        fingerprint(data)
        == fingerprint(gymnasium_run)
        != fingerprint(Config(env=EnvConfig(backend="envpool")))
    )


@needs_envpool
def test_a_policy_trained_on_envpool_evaluates_and_records_a_video_on_either(rlpipe_cli, tmp_path):
    proc = rlpipe_cli(*TINY, "env.backend=envpool", "video=true")
    assert proc.returncode == 0, proc.stderr
    assert list((tmp_path / "run" / "videos").glob("*.mp4"))  # rendered by gymnasium
    for backend in ("gymnasium", "envpool"):
        out = tmp_path / f"{backend}.json"
        args = [f"run_dir={tmp_path / 'run'}", "episodes=3", f"backend={backend}", f"out={out}"]
        evaluate_main([*args, "video=true"])  # in-process (its command line: test_evaluate.py)
        summary = json.loads(out.read_text())
        assert summary["backend"] == backend and len(summary["returns"]) == 3
        assert np.isfinite(summary["return_mean"]) and summary["video"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["env.backend=pool"], "env.backend must be one of auto, gymnasium, envpool; got 'pool'"),
        (["env.backend=envpool", "env=cartpole_noop"], "not 'rlpipe/CartPoleNoop-v0'"),
        (
            ["env.backend=envpool", "+env.kwargs.sutton_barto_reward=true"],
            "cannot honour env.kwargs",
        ),
    ],
)
def test_bad_backends_are_one_line_and_write_nothing(rlpipe_cli, tmp_path, args, message):
    proc = rlpipe_cli(*TINY, *args)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error:") and message in lines[0], lines
    assert not (tmp_path / "run" / "config.yaml").exists()
