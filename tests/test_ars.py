"""ARS: the update rule, the normaliser, population calls, the search, the algorithm, the CLI."""

from __future__ import annotations

import io
import math
import multiprocessing
import os
import pickle
import re
import signal
import sys
import threading
import time
from dataclasses import fields
from functools import partial
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch
from conftest import TINY
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from test_config import compose_config
from torch import nn
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from rlpipe.algos import ARS, Algorithm, ARSConfig
from rlpipe.algos.ars import ARSSearch, PopulationPolicy, ars_update, backends, make_ars_policy
from rlpipe.algos.ars.rollout import rollout
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.episodes import evaluate
from rlpipe.errors import RlpipeError
from rlpipe.models import ClampAction
from rlpipe.normalizer import Normalizer

# the gymnasium backend: these tests are about its rollouts and the worker processes (ARS on
# EnvPool, one pool in this process: tests/test_envpool_runs.py)
CARTPOLE = EnvConfig(id="CartPole-v1", backend="gymnasium")
PENDULUM = EnvConfig(id="Pendulum-v1", backend="gymnasium")


def test_update_rule_by_hand():
    theta = torch.zeros(2)
    deltas = torch.tensor([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    plus, minus = torch.tensor([3.0, 0.0, 1.0]), torch.tensor([1.0, 2.0, 1.0])
    # top-2 by max(r+, r-): directions 0 (3) and 1 (2); σ = std(3, 0, 1, 2) = sqrt(1.25)
    step = 2.0 * deltas[0] - 2.0 * deltas[1]
    expected = 0.1 / (2 * 1.25**0.5) * step
    assert torch.allclose(ars_update(theta, deltas, plus, minus, 2, 0.1), expected)


def test_update_rule_climbs_a_quadratic_to_its_optimum():
    """Maximise f(θ) = -||θ - θ*||² with the ARS rule alone."""
    generator = torch.Generator().manual_seed(0)
    optimum = torch.randn(10, generator=generator)
    theta = torch.zeros(10)

    def f(x: torch.Tensor) -> torch.Tensor:
        return -((x - optimum) ** 2).sum(-1)

    start = f(theta)
    for _ in range(300):
        deltas = torch.randn(8, 10, generator=generator)
        theta = ars_update(
            theta, deltas, f(theta + 0.05 * deltas), f(theta - 0.05 * deltas), 4, 0.1
        )
    assert f(theta) > 0.01 * start  # from -||θ*||² to within 1% of it
    assert torch.allclose(theta, optimum, atol=0.15)


def test_normalizer_matches_the_notebooks_sequential_welford():
    data = torch.randn(300, 3, dtype=torch.float64) * torch.tensor([5.0, 0.01, 1.0]) + 2.0
    n, mean, mean_diff = 0.0, np.zeros(3), np.zeros(3)
    for x in data.numpy():  # the notebook's Normalizer.observe
        n += 1.0
        last_mean = mean.copy()
        mean += (x - mean) / n
        mean_diff += (x - last_mean) * (x - mean)
    var = (mean_diff / n).clip(min=1e-2)
    norm = Normalizer(3)
    obs = torch.randn(4, 3)
    assert torch.equal(norm(obs), obs)  # the identity before any statistics
    for chunk in data.split([1, 120, 7, 172]):
        norm.observe(chunk)
    assert torch.allclose(norm.mean, torch.from_numpy(mean))
    assert torch.allclose(norm.scale.double(), torch.from_numpy(np.sqrt(var)), rtol=1e-5)
    expected = (obs.double() - torch.from_numpy(mean)) / torch.from_numpy(np.sqrt(var))
    assert torch.allclose(norm(obs).double(), expected, atol=1e-5)
    # the NumPy form the rollouts use computes the same float32 values
    np.testing.assert_array_equal(norm.numpy_forward()(obs.numpy()), norm(obs).numpy())
    snapshot = norm.numpy_forward()
    before = snapshot(obs.numpy())
    norm.observe(data[:50] * 3.0)
    np.testing.assert_array_equal(snapshot(obs.numpy()), before)  # later merges leave it alone


@pytest.mark.parametrize("env_id", ["CartPole-v1", "Pendulum-v1"])
@pytest.mark.parametrize("policy", ["linear", "mlp"])
def test_population_call_equals_one_call_per_member(env_id, policy):
    env = make_env(EnvConfig(id=env_id))
    net, normalizer = make_ars_policy(env, ARSConfig(policy=policy, hidden_sizes=[8]))
    size = env.observation_spec["observation"].shape[-1]
    normalizer.observe(torch.randn(50, size) * 3)
    n = parameters_to_vector(net.parameters()).numel()
    flat = torch.randn(6, n)
    obs = torch.randn(6, size)
    out = PopulationPolicy(net, flat)(TensorDict(observation=obs, batch_size=[6]))
    for i in range(6):
        vector_to_parameters(flat[i], net.parameters())
        one = net(TensorDict(observation=obs[i : i + 1], batch_size=[1]))
        assert torch.allclose(one["policy_output"][0], out["policy_output"][i], atol=1e-5)
        # NumPy's matmul may sum in another order: equal up to rounding (argmax exactly)
        torch.testing.assert_close(one["action"][0].detach(), out["action"][i], atol=1e-5, rtol=0)
    if env_id == "Pendulum-v1":
        assert out["action"].abs().max() <= 2.0  # clipped to the bounds


class _Custom(nn.Module):
    """A module of its own (no NumPy form): population calls go through torch.vmap."""

    def __init__(self) -> None:
        super().__init__()
        self.layer = nn.Linear(3, 1)

    def forward(self, x):
        return torch.sin(self.layer(x))


@pytest.mark.parametrize(
    "net",
    [
        nn.Sequential(nn.Linear(3, 8), nn.LayerNorm(8), nn.Tanh(), nn.Linear(8, 1)),
        nn.Sequential(nn.Linear(3, 8), nn.LayerNorm(8, bias=False), nn.Linear(8, 1)),
        nn.Sequential(nn.Linear(3, 8), nn.Softsign(), nn.Linear(8, 1)),  # no NumPy twin
        _Custom(),  # through torch.vmap
    ],
    ids=["layernorm", "layernorm-no-bias", "softsign", "custom"],
)
def test_population_call_of_any_layer_equals_the_torch_forward(net):
    policy = TensorDictModule(net, in_keys=["observation"], out_keys=["action"])
    flat = torch.randn(5, parameters_to_vector(net.parameters()).numel())
    obs = torch.randn(5, 3)
    out = PopulationPolicy(policy, flat)(TensorDict(observation=obs, batch_size=[5]))
    for i in range(5):
        vector_to_parameters(flat[i], net.parameters())
        assert torch.allclose(net(obs[i]), out["action"][i], atol=1e-5)


def test_workers_take_fewer_chunks_of_a_policy_that_costs_more_per_call():
    """Chunks per worker follow the measured costs: a linear policy (NumPy, microseconds a call)
    gets many small chunks on Pendulum, a module run through torch.vmap one chunk each."""
    from rlpipe.algos.ars.chunking import MAX_CHUNKS, chunks_per_worker

    factory = partial(make_env, PENDULUM, vectorization="sync")
    linear, _ = make_ars_policy(make_env(PENDULUM), ARSConfig())
    custom = TensorDictModule(_Custom(), in_keys=["observation"], out_keys=["action"])
    fine = chunks_per_worker(linear, factory, population=32, workers=2, seed=0)
    coarse = chunks_per_worker(custom, factory, population=32, workers=2, seed=0)
    assert fine > coarse == 1 and fine <= MAX_CHUNKS


def test_search_standalone_solves_cartpole_and_tracks_observations():
    torch.manual_seed(0)
    policy, normalizer = make_ars_policy(make_env(CARTPOLE), ARSConfig())
    search = ARSSearch(
        policy,
        partial(make_env, CARTPOLE),
        num_directions=8,
        num_best=4,
        step_size=0.02,
        noise=0.03,
        max_steps=500,
        normalizer=normalizer,
        seed=0,
    )
    steps = 0
    for _ in range(25):
        stats = search.step()
        steps += int(stats["env_steps"])
        if stats["return_mean"] == 500:
            break
    search.close()
    assert stats["return_max"] == 500
    assert normalizer.count == steps  # every state a perturbed policy acted on
    assert evaluate(policy, make_env(CARTPOLE, num_envs=2), 2).mean > 400


def small_search(seed: int, **kwargs) -> ARSSearch:
    policy, normalizer = make_ars_policy(make_env(CARTPOLE), ARSConfig())
    return ARSSearch(
        policy,
        partial(make_env, CARTPOLE),
        num_directions=3,
        normalizer=normalizer,
        seed=seed,
        **kwargs,
    )


@pytest.mark.parametrize(
    ("short", "here"),
    [(0.0, False), (math.inf, True)],
    ids=["workers-every-iteration", "this-process-timed-too"],
)
def test_worker_processes_give_the_same_search_as_one_process(monkeypatch, short, here):
    """Each member's episode seed comes from the search, whichever process rolls it out: the
    workers, or this process (timed against the workers when iterations are short)."""
    monkeypatch.setattr(backends, "SHORT_SECONDS", short)
    thetas, counts = [], []
    for workers in (1, 2):
        search = small_search(seed=5, workers=workers)
        try:
            before = search.theta
            # several iterations: a worker gets the policy state with its first chunk of each
            steps = [search.step()["env_steps"] for _ in range(3)]
            if workers == 2:  # the first iteration in the workers, the second as the case says
                assert ("here" in search._backend._timed) is here
        finally:
            search.close()
        assert not torch.equal(before, search.theta)
        assert search.normalizer.count == sum(steps) > 18
        thetas.append(search.theta)
        counts.append(steps)
    assert torch.allclose(thetas[0], thetas[1]) and counts[0] == counts[1]


def test_workers_or_this_process_by_seconds_per_env_step():
    """The faster way per env step rolls out; the slower is timed again once the work has
    changed RETIME_FACTOR-fold; long iterations always go to the workers."""
    short = backends.SHORT_SECONDS

    def way(steps: int, **timed: tuple[float, int]) -> str:
        pool = SimpleNamespace(_timed=timed, _steps=steps)
        return backends._Processes._way(pool)

    assert way(0) == "pool"  # nothing timed yet
    assert way(100, pool=(short / 2, 100)) == "here"  # short: this process is timed too
    assert way(100, pool=(short * 2, 100)) == "pool"
    # this process is faster per step, though its iteration (more steps) took longer
    fast_here = {"pool": (short / 5, 100), "here": (short / 4, 150)}
    assert way(150, **fast_here) == "here"
    assert way(int(100 * backends.RETIME_FACTOR) - 1, **fast_here) == "here"
    assert way(int(100 * backends.RETIME_FACTOR), **fast_here) == "pool"  # the work has doubled
    assert way(2_000, **fast_here) == "pool"  # 2,000 steps here would take over SHORT_SECONDS
    fast_pool = {"pool": (short / 4, 200), "here": (short / 3, 200)}
    assert way(200, **fast_pool) == "pool"
    assert way(90, **fast_pool) == "here"  # the work has halved since this process was timed


def test_rollout_ends_episodes_at_the_env_time_limit_inside_its_wrappers():
    """The rollout steps the env under TimeLimit & co. and applies the limit itself; an env with
    any other wrapper is stepped through it, with the same results."""
    policy, _ = make_ars_policy(make_env(PENDULUM), ARSConfig())
    flat = torch.randn(3, parameters_to_vector(policy.parameters()).numel())
    plain = [gym.make(PENDULUM.id) for _ in range(3)]
    result = rollout(policy, plain, flat, [0, 1, 2], max_steps=1000)
    assert result.lengths.tolist() == [200, 200, 200]  # Pendulum-v1's own limit
    capped = rollout(policy, plain, flat, [0, 1, 2], max_steps=30)
    assert capped.lengths.tolist() == [30, 30, 30]
    wrapped = [gym.wrappers.TransformReward(gym.make(PENDULUM.id), float) for _ in range(3)]
    same = rollout(policy, wrapped, flat, [0, 1, 2], max_steps=1000)
    assert torch.equal(same.lengths, result.lengths)
    assert torch.equal(same.raw_returns, result.raw_returns)
    assert torch.equal(same.obs_mean, result.obs_mean)


def test_training_rewards_are_the_envs_own_unless_clipped():
    """reward_clip=false ranks the env's returns; clipped at 1, Pendulum's rewards (down to -16.3
    a step) are -1 wherever the pole is more than a radian from the top, which flattens away
    the differences the swing-up needs: the Pendulum preset turns it off."""
    policy, _ = make_ars_policy(make_env(PENDULUM), ARSConfig(policy="mlp", hidden_sizes=[8]))
    flat = torch.randn(4, parameters_to_vector(policy.parameters()).numel())
    envs = [gym.make(PENDULUM.id) for _ in range(4)]
    own = rollout(policy, envs, flat, [0, 1, 2, 3], max_steps=1000)
    assert torch.equal(own.returns, own.raw_returns)
    clipped = rollout(policy, envs, flat, [0, 1, 2, 3], max_steps=1000, reward_clip=1.0)
    assert torch.equal(clipped.raw_returns, own.raw_returns)
    assert (clipped.returns >= -200).all() and (own.raw_returns < -200).all()


def test_pendulum_preset_is_a_biased_mlp_run_for_its_whole_frame_budget():
    cfg = compose_config("+experiment=ars_pendulum")
    assert isinstance(cfg.algo, ARSConfig) and cfg.env.id == PENDULUM.id
    assert cfg.algo.policy == "mlp" and not cfg.algo.reward_clip
    assert cfg.algo.workers == 0  # all cores by default
    policy, normalizer = make_ars_policy(make_env(cfg.env), cfg.algo)
    linears = [layer for layer in policy[1].module if isinstance(layer, nn.Linear)]
    assert [layer.out_features for layer in linears] == [*cfg.algo.hidden_sizes, 1]
    assert all(layer.bias is not None for layer in linears)
    assert isinstance(policy[2].module, ClampAction)  # raw outputs clipped to [-2, 2]
    assert cfg.algo.normalize_observations and policy[0].module is normalizer
    # algo.iterations must not end the run before total_frames (Pendulum: 200-step episodes)
    assert cfg.algo.iterations * 2 * cfg.algo.num_directions * 200 >= cfg.total_frames


def test_rollout_result_travels_as_numpy_arrays():
    policy, _ = make_ars_policy(make_env(CARTPOLE), ARSConfig())
    flat = torch.randn(2, parameters_to_vector(policy.parameters()).numel())
    result = rollout(policy, [gym.make(CARTPOLE.id) for _ in range(2)], flat, [3, 4], max_steps=50)
    data = pickle.dumps(result)
    assert b"torch" not in data  # not torch's reducer, which ships tensors via shared memory
    back = pickle.loads(data)
    for field in fields(result):
        before, after = getattr(result, field.name), getattr(back, field.name)
        assert torch.equal(before, after) if isinstance(before, torch.Tensor) else before == after


def test_algorithm_checkpoint_holds_normaliser_and_parameters():
    torch.manual_seed(0)
    algo = ARS(partial(make_env, CARTPOLE), ARSConfig(num_directions=4, num_best=2, workers=1))
    assert isinstance(algo, Algorithm)
    metrics = algo.train_step()
    assert algo.frames == metrics["train/env_steps"] > 0
    assert set(metrics) >= {"train/return_mean", "train/return_max", "train/env_steps"}
    # timing figures differ between identical runs: only time/ metrics may
    assert {"time/steps_per_second", "time/rollout_cpu_seconds"} <= set(metrics)
    assert not {"train/steps_per_second", "train/rollout_cpu_seconds"} & set(metrics)
    buffer = io.BytesIO()
    torch.save(algo.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    other = ARS(partial(make_env, CARTPOLE), ARSConfig(num_directions=4, num_best=2, workers=1))
    td = make_env(CARTPOLE, num_envs=3).reset()
    other.load_state_dict(state)
    assert torch.equal(
        other.policy(td.clone())["policy_output"], algo.policy(td.clone())["policy_output"]
    )
    assert other.policy[0].module.count == algo.frames
    assert other.frames == algo.frames and other.search.iterations == 1
    algo.close()
    other.close()


@pytest.mark.parametrize("budget", ["total_frames", "iterations"])
def test_step_size_anneals_over_the_budget_and_stays_put_by_default(budget):
    """α follows algo.step_size_end linearly over the run's frames (or its iterations when
    no frame budget is set); without step_size_end it is algo.step_size throughout."""

    def alphas(**kw):
        torch.manual_seed(0)
        cfg = ARSConfig(num_directions=2, num_best=1, workers=1, step_size=0.04, **kw)
        algo, seen = ARS(partial(make_env, CARTPOLE), cfg), []
        for _ in range(3):
            done = (algo.frames, cfg.total_frames) if cfg.total_frames else (algo.iterations, 4)
            algo.train_step()
            seen.append((algo.search.step_size, done))
        algo.close()
        return seen

    kw = {"total_frames": 100} if budget == "total_frames" else {"iterations": 4}
    annealed = alphas(step_size_end=0.0, **kw)
    assert [a for a, _ in annealed] == pytest.approx(
        [0.04 * (1 - min(d / t, 1)) for _, (d, t) in annealed]
    )
    assert annealed[0][0] == pytest.approx(0.04) and annealed[-1][0] < 0.04
    assert {a for a, _ in alphas(**kw)} == {0.04}


def test_search_restored_mid_way_continues_as_the_uninterrupted_one():
    """θ, the normaliser, the iteration count and the generator travel in the state dict;
    CartPole-v1's reset(seed) fixes each episode, so the env copies' own seed does not matter."""
    straight = small_search(seed=5, workers=1)
    interrupted = small_search(seed=5, workers=1)
    try:
        for _ in range(2):
            straight.step()
            interrupted.step()
        buffer = io.BytesIO()
        torch.save(interrupted.state_dict(), buffer)
    finally:
        interrupted.close()
    buffer.seek(0)
    resumed = small_search(seed=123, workers=1)  # another generator, a fresh normaliser
    try:
        resumed.load_state_dict(torch.load(buffer, weights_only=True))
        assert resumed.iterations == 2
        for _ in range(2):
            expected, got = straight.step(), resumed.step()
            assert got["episode_return"] == expected["episode_return"]
    finally:
        straight.close()
        resumed.close()
    assert not torch.equal(resumed.theta, torch.zeros_like(resumed.theta))
    assert torch.equal(resumed.theta, straight.theta)
    assert torch.equal(resumed.normalizer.mean, straight.normalizer.mean)


def test_building_ars_starts_no_workers_until_it_trains():
    """``load_run`` builds a run's algorithm only to hold its policy: that spawns nothing."""
    before = set(multiprocessing.active_children())
    algo = ARS(partial(make_env, CARTPOLE), ARSConfig(workers=2))
    assert set(multiprocessing.active_children()) == before
    algo.close()  # nothing started, nothing to stop
    assert set(multiprocessing.active_children()) == before
    algo = ARS(partial(make_env, CARTPOLE), ARSConfig(workers=2))
    try:
        metrics = algo.train_step()
        assert len(set(multiprocessing.active_children()) - before) == 2
    finally:
        algo.close()
    assert metrics["train/env_steps"] == algo.frames > 0 and algo.iterations == 1
    assert set(multiprocessing.active_children()) == before


def test_config_checks():
    with pytest.raises(RlpipeError, match="num_best"):
        ARSConfig(num_directions=4, num_best=5)
    with pytest.raises(RlpipeError, match="noise"):
        ARSConfig(noise=0)
    with pytest.raises(RlpipeError, match="step_size"):
        ARSConfig(step_size=-0.1)
    with pytest.raises(RlpipeError, match="algo.noise must be a finite number > 0, got inf"):
        ARSConfig(noise=float("inf"))
    with pytest.raises(RlpipeError, match="algo.step_size must be a finite number > 0, got nan"):
        ARSConfig(step_size=float("nan"))
    with pytest.raises(RlpipeError, match=r"step_size_end must be null or in \[0, algo.step_"):
        ARSConfig(step_size=0.02, step_size_end=0.03)
    # the search checks the same parameters, named as its own arguments
    policy, _ = make_ars_policy(make_env(CARTPOLE), ARSConfig())
    factory = partial(make_env, CARTPOLE)
    with pytest.raises(RlpipeError, match=r"^num_best \(3\) must be between 1 and num_direc"):
        ARSSearch(policy, factory, num_directions=2, num_best=3)
    with pytest.raises(RlpipeError, match="^noise must be a finite number > 0, got nan"):
        ARSSearch(policy, factory, noise=float("nan"))
    with pytest.raises(RlpipeError, match="^backend must be one of local, ray; got 'spark'"):
        ARSSearch(policy, factory, backend="spark")


def test_divergence_hint_names_ars_settings():
    """The runner's divergence error ends with the algorithm's hint: ARS has no algo.lr."""
    keys = re.findall(r"algo\.(\w+)", ARS.divergence_hint)
    assert keys and set(keys) <= {field.name for field in fields(ARSConfig)}


def test_non_flat_observation_is_rejected(image_env_id):
    with pytest.raises(RlpipeError, match="flat vector observations"):
        ARS(partial(make_env, EnvConfig(id=image_env_id)), ARSConfig(workers=1))


def test_cli_trains_ars(rlpipe_cli):
    proc = rlpipe_cli(
        *TINY, "algo=ars", "algo.num_directions=2", "algo.num_best=2", "algo.workers=1"
    )
    assert proc.returncode == 0, proc.stderr
    assert "final eval" in proc.stdout


BAD = [
    (
        ["algo.num_directions=16", "algo.num_best=17"],
        "algo.num_best (17) must be between 1 and algo.num_directions (16)",
    ),
    (["algo.noise=0"], "algo.noise must be a finite number > 0"),
    (["algo.step_size=-1"], "algo.step_size must be a finite number > 0"),
    # the preset anneals α to 0.01: a smaller α alone says how to keep it
    (["algo.step_size=0.005"], "algo.step_size_end must be null or in [0, algo.step_size (0.005)]"),
]


@pytest.mark.parametrize("args, message", BAD, ids=[a[-1] for a, _ in BAD])
def test_cli_bad_input_is_one_line(rlpipe_cli, args, message):
    proc = rlpipe_cli("progress=false", "algo=ars", "env=bipedal", *args)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"rlpipe: error: {message}"), proc.stderr


def _train_until_killed(conn, variant: str) -> None:
    """The main process of a run, forked from the test process (which has imported everything):
    ARS with two workers, whose pids it sends once they are up, trains until killed."""
    if variant == "spawn":
        backends._start_method = lambda: "spawn"
    elif variant == "fork-pipes-only":  # no PR_SET_PDEATHSIG: only EOF on the pipes
        backends._die_with_parent = lambda parent_pid: True
    elif variant == "fork-prctl-only":  # workers keep the inherited pipe ends: only the kernel
        backends._PARENT_ENDS = _Forgetful()
    cfg = ARSConfig(num_directions=4, num_best=4, episode_length=200, workers=2)
    algo = ARS(partial(make_env, PENDULUM, seed=0), cfg)
    algo.search.start()
    conn.send([proc.pid for proc in multiprocessing.active_children()])
    while True:
        algo.train_step()


class _Forgetful(set):
    """A set that keeps nothing."""

    def add(self, item: object) -> None:
        pass


def _start_time(pid: int) -> str | None:
    """``pid``'s start time (with the pid, a process's identity); None once it is gone (a
    zombie counts as gone: it holds no memory, and init reaps it)."""
    try:
        with open(f"/proc/{pid}/stat") as file:
            stat = file.read().rpartition(")")[2].split()
    except OSError:
        return None
    return None if stat[0] in ("Z", "X") else stat[19]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks, reads /proc")
@pytest.mark.parametrize(
    # spawned workers import torch & co. afresh: slow, in the fault-injection suite
    "variant",
    [
        "fork",
        "fork-pipes-only",
        "fork-prctl-only",
        pytest.param("spawn", marks=pytest.mark.faults),
    ],
)
def test_workers_exit_when_the_main_process_is_killed(variant):
    """SIGKILL of the main process leaves no worker behind: each worker sees EOF on its pipe
    (it holds no other end of any pipe) and the kernel kills it with its parent (prctl)."""
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    main = ctx.Process(target=_train_until_killed, args=(send, variant))
    main.start()
    send.close()
    try:
        assert receive.poll(120), "the workers did not start"
        workers = {pid: _start_time(pid) for pid in receive.recv()}
        assert len(workers) == 2 and None not in workers.values()
        time.sleep(0.5)  # mid-iteration
    finally:
        main.kill()
        main.join()
    deadline = time.monotonic() + 5
    while True:
        left = [pid for pid, start in workers.items() if _start_time(pid) == start]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    for pid in left:  # the same processes (pid and start time): do not leave them behind
        os.kill(pid, signal.SIGKILL)
    assert not left, f"workers {left} outlived the killed main process"


def test_a_killed_worker_stops_training_with_one_line(monkeypatch):
    """A worker killed mid-training (OOM killer, kill -9) raises one RlpipeError line in the
    main process within seconds; close() then neither raises nor hangs."""
    monkeypatch.setattr(backends, "SHORT_SECONDS", 0.0)  # every iteration in the workers
    before = set(multiprocessing.active_children())
    cfg = ARSConfig(num_directions=4, num_best=4, episode_length=200, workers=2)
    algo = ARS(partial(make_env, PENDULUM, seed=0), cfg)
    try:
        algo.train_step()
        workers = list(set(multiprocessing.active_children()) - before)
        assert len(workers) == 2
        victim, killed_at = workers[0], []

        def kill() -> None:
            killed_at.append(time.monotonic())
            os.kill(victim.pid, signal.SIGKILL)

        timer = threading.Timer(0.3, kill)
        timer.start()
        with pytest.raises(RlpipeError) as error:
            while not killed_at or time.monotonic() < killed_at[0] + 10:
                algo.train_step()
        raised_at = time.monotonic()
        timer.join()
        assert raised_at - killed_at[0] < 5
        message = str(error.value)
        assert f"ARS rollout worker (pid {victim.pid}) died: killed by SIGKILL" in message
        assert "resume=" in message and "\n" not in message
        with pytest.raises(RlpipeError, match="worker"):  # the pool is not used again
            algo.train_step()
    finally:
        start = time.monotonic()
        algo.close()
        assert time.monotonic() - start < 5
    assert set(multiprocessing.active_children()) == before  # the other worker is stopped too


def _documented_search(seed: int = 7) -> ARSSearch:
    """An ARSSearch as docs/api.md builds one: a fresh MLP on Pendulum-v1, its ``Normalizer``
    both inside the policy and passed as ``normalizer=``."""
    normalizer = Normalizer(3)
    net = nn.Sequential(nn.Linear(3, 8), nn.Tanh(), nn.Linear(8, 1))
    policy = TensorDictSequential(
        TensorDictModule(normalizer, in_keys=["observation"], out_keys=["observation_norm"]),
        TensorDictModule(net, in_keys=["observation_norm"], out_keys=["action"]),
    )
    return ARSSearch(
        policy,
        partial(make_env, PENDULUM, vectorization="sync"),
        num_directions=3,
        num_best=2,
        max_steps=20,
        normalizer=normalizer,
        workers=1,
        seed=seed,
    )


def test_search_state_dict_saved_to_a_file_resumes_exactly(tmp_path):
    """Saved after 2 iterations and loaded into a fresh search (fresh weights, fresh normaliser),
    the next 2 iterations are those the saved search ran: same returns, same θ, same statistics.
    Pendulum-v1's reset(seed) fixes each episode, so the env copies' history does not matter."""
    torch.manual_seed(0)
    search = _documented_search()
    try:
        for _ in range(2):
            search.step()
        torch.save(search.state_dict(), tmp_path / "search.pt")
        kept = search.state_dict()  # in memory: a copy too, which the next steps leave alone
        saved_theta = search.theta
        expected = [search.step() for _ in range(2)]
    finally:
        search.close()
    saved = torch.load(tmp_path / "search.pt", weights_only=True)
    assert kept["iterations"] == saved["iterations"] == 2
    assert torch.equal(kept["generator"], saved["generator"])
    for key, value in saved["policy"].items():
        assert torch.equal(kept["policy"][key], value), key
    torch.manual_seed(1)  # other initial weights: the state must bring θ back
    resumed = _documented_search()
    assert not torch.equal(resumed.theta, saved_theta)
    try:
        resumed.load_state_dict(torch.load(tmp_path / "search.pt", weights_only=True))
        assert resumed.iterations == 2 and torch.equal(resumed.theta, saved_theta)
        got = [resumed.step() for _ in range(2)]
    finally:
        resumed.close()
    for before, after in zip(expected, got):
        assert after["episode_return"] == before["episode_return"]
        assert after["episode_length"] == before["episode_length"] == [20.0] * 6
        assert after["return_mean"] == before["return_mean"]
    assert torch.equal(resumed.theta, search.theta)
    for key in ("count", "mean", "m2", "loc", "scale"):
        assert torch.equal(getattr(resumed.normalizer, key), getattr(search.normalizer, key)), key
    assert resumed.normalizer.count == 4 * 6 * 20  # every observation of the 4 iterations
