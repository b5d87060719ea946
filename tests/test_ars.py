"""ARS: the update rule, the normaliser, population calls, the algorithm and its config, the CLI."""

from __future__ import annotations

import io
import re
from dataclasses import fields, replace
from functools import partial

import numpy as np
import pytest
import torch
from conftest import TINY, assert_auto_chose
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from test_config import compose_config
from test_envpool import needs_envpool
from torch import nn
from torch.nn.utils import parameters_to_vector, vector_to_parameters

from rlpipe.algos import ARS, Algorithm, ARSConfig
from rlpipe.algos.ars import (
    ARSSearch,
    PopulationPolicy,
    ars_update,
    centered_ranks,
    make_ars_policy,
)
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.models import ClampAction
from rlpipe.normalizer import Normalizer
from rlpipe.pipeline import train

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


def test_centered_ranks_span_minus_half_to_half_in_order():
    values = torch.tensor([3.0, -100.0, 5.0, 5.0, 0.0], dtype=torch.float64)
    expected = torch.tensor([0.0, -0.5, 0.25, 0.5, -0.25], dtype=torch.float64)
    torch.testing.assert_close(centered_ranks(values), expected)  # ties: in the order they come
    torch.testing.assert_close(centered_ranks(torch.tensor([7.0])), torch.tensor([-0.5]))


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


def test_a_module_through_vmap_costs_many_numpy_calls_a_call():
    """The costs chunking reads: a linear policy (NumPy, microseconds a call) costs far less a
    population call than a module run through torch.vmap (measured here: about 15 times less;
    asserted: over 3, so that a busy machine cannot flip it)."""
    from rlpipe.algos.ars.chunking import measured_costs

    factory = partial(make_env, PENDULUM, vectorization="sync")
    linear, _ = make_ars_policy(make_env(PENDULUM), ARSConfig())
    custom = TensorDictModule(_Custom(), in_keys=["observation"], out_keys=["action"])
    numpy_call, env_step = measured_costs(linear, factory, members=2, seed=0)
    vmap_call, _ = measured_costs(custom, factory, members=2, seed=0)
    assert 0 < numpy_call and 0 < env_step and vmap_call > 3 * numpy_call


@pytest.mark.parametrize(
    ("call", "env_step", "chunks"),
    [(2e-5, 1e-4, 8), (3e-4, 1e-4, 1), (1e-4, 1e-4, 4), (1e-2, 1e-4, 1), (1e-7, 1e-4, 8)],
)
def test_workers_take_fewer_chunks_of_a_policy_that_costs_more_per_call(
    monkeypatch, call, env_step, chunks
):
    """Chunks per worker follow the costs: the most (up to MAX_CHUNKS, at least one) whose
    calls stay within OVERHEAD of a worker's env steps (32 members on 2 workers: 16 member-steps
    a worker, so 0.25 * 16 = 4 env steps' worth of calls)."""
    from rlpipe.algos.ars import chunking

    monkeypatch.setattr(chunking, "measured_costs", lambda *args: (call, env_step))
    factory = partial(make_env, PENDULUM, vectorization="sync")
    got = chunking.chunks_per_worker(None, factory, population=32, workers=2, seed=0)
    assert got == chunks and 1 <= got <= chunking.MAX_CHUNKS


@needs_envpool
def test_workers_take_their_share_as_one_chunk_on_envpool(monkeypatch):
    """On EnvPool every chunk is a fresh pool stepped through a hand-off to its threads: one
    chunk a worker, whatever the costs would allow on gymnasium."""
    from rlpipe.algos.ars import chunking

    monkeypatch.setattr(chunking, "measured_costs", lambda *args: (1e-7, 1e-4))  # 8 on gymnasium
    pooled = partial(make_env, replace(PENDULUM, backend="envpool"))
    assert chunking.chunks_per_worker(None, pooled, population=32, workers=2, seed=0) == 1


def test_pendulum_preset_is_a_biased_mlp_run_for_its_whole_frame_budget():
    cfg = compose_config("+experiment=ars_pendulum")
    assert isinstance(cfg.algo, ARSConfig) and cfg.env.id == PENDULUM.id
    assert cfg.algo.policy == "mlp" and not cfg.algo.reward_clip
    assert cfg.algo.bound_penalty > 0  # raw outputs far past the torque bounds cost
    assert cfg.algo.workers == 0  # all cores by default
    policy, normalizer = make_ars_policy(make_env(cfg.env), cfg.algo)
    linears = [layer for layer in policy[1].module if isinstance(layer, nn.Linear)]
    assert [layer.out_features for layer in linears] == [*cfg.algo.hidden_sizes, 1]
    assert all(layer.bias is not None for layer in linears)
    assert isinstance(policy[2].module, ClampAction)  # raw outputs clipped to [-2, 2]
    assert cfg.algo.normalize_observations and policy[0].module is normalizer
    # algo.iterations must not end the run before total_frames (Pendulum: 200-step episodes)
    assert cfg.algo.iterations * 2 * cfg.algo.num_directions * 200 >= cfg.total_frames


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
def test_step_size_noise_and_clip_anneal_over_the_budget_and_stay_put_by_default(budget):
    """α follows algo.step_size_end, ν algo.noise_end, and the reward clip's bound
    algo.reward_clip_end, linearly over the run's frames (or its iterations when no frame budget
    is set); without them they are algo.step_size, algo.noise and algo.reward_clip's bound
    throughout (none with reward_clip=false)."""

    def schedule(**kw):  # (α, ν, clip bound, fraction of the run done) before each step
        torch.manual_seed(0)
        cfg = ARSConfig(num_directions=2, num_best=1, workers=1, step_size=0.04, **kw)
        algo, seen = ARS(partial(make_env, CARTPOLE), cfg), []
        for _ in range(3):
            done = (algo.frames, cfg.total_frames) if cfg.total_frames else (algo.iterations, 4)
            algo.train_step()
            search = algo.search
            seen.append(
                (search.step_size, search.noise, search.reward_clip, min(done[0] / done[1], 1))
            )
        algo.close()
        return seen

    kw = {"total_frames": 100} if budget == "total_frames" else {"iterations": 4}
    annealed = schedule(step_size_end=0.0, noise_end=0.01, reward_clip=2, reward_clip_end=10, **kw)
    assert [a for a, *_ in annealed] == pytest.approx([0.04 * (1 - f) for *_, f in annealed])
    assert [n for _, n, *_ in annealed] == pytest.approx([0.03 - 0.02 * f for *_, f in annealed])
    assert [c for *_, c, _ in annealed] == pytest.approx([2 + 8 * f for *_, f in annealed])
    assert annealed[0][:3] == pytest.approx((0.04, 0.03, 2)) and annealed[-1][1:3] != (0.03, 2)
    assert {(a, n, c) for a, n, c, _ in schedule(**kw)} == {(0.04, 0.03, 1.0)}
    assert {c for *_, c, _ in schedule(reward_clip=False, **kw)} == {None}
    # held at its start for the first reward_clip_from of the run, then moved over the rest
    late = schedule(reward_clip=2, reward_clip_end=10, reward_clip_from=0.5, **kw)
    assert [c for *_, c, _ in late] == pytest.approx(
        [2 + 8 * max(f - 0.5, 0) / 0.5 for *_, f in late]
    )


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
    with pytest.raises(RlpipeError, match=r"noise_end must be null or in \(0, algo.noise \(0.03"):
        ARSConfig(noise_end=0.05)
    with pytest.raises(RlpipeError, match=r"noise_end must be null or in \(0, algo.noise"):
        ARSConfig(noise_end=0)
    with pytest.raises(RlpipeError, match="algo.reward_clip must be true, false or a number > 0"):
        ARSConfig(reward_clip=float("inf"))
    for bad in ({"reward_clip": False, "reward_clip_end": 10}, {"reward_clip_end": 0}):
        with pytest.raises(RlpipeError, match="algo.reward_clip_end must be null, or a number"):
            ARSConfig(**bad)
    with pytest.raises(RlpipeError, match=r"algo.reward_clip_from must be in \[0, 1\)"):
        ARSConfig(reward_clip_from=1)
    with pytest.raises(RlpipeError, match=r"^algo.episodes_from must be in \[0, 1\), got -0.5"):
        ARSConfig(episodes_from=-0.5)
    with pytest.raises(RlpipeError, match="^algo.episodes must be >= 1, got 0"):
        ARSConfig(episodes=0)
    # true: the notebook's [-1, 1]; a number: that bound; false: no clip
    bounds = [ARSConfig(reward_clip=v).reward_bound for v in (True, 10, 2.5, False)]
    assert bounds == [1.0, 10.0, 2.5, None]
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


def test_bound_penalty_is_refused_for_discrete_actions():
    with pytest.raises(RlpipeError, match=r"^algo.bound_penalty \(0.1\) applies to continuous"):
        ARS(partial(make_env, CARTPOLE), ARSConfig(bound_penalty=0.1, workers=1))


def test_non_flat_observation_is_rejected(image_env_id):
    with pytest.raises(RlpipeError, match="flat vector observations"):
        ARS(partial(make_env, EnvConfig(id=image_env_id)), ARSConfig(workers=1))


def test_cli_trains_ars(rlpipe_cli):
    proc = rlpipe_cli(
        *TINY, "algo=ars", "algo.num_directions=2", "algo.num_best=2", "algo.workers=1"
    )
    assert proc.returncode == 0, proc.stderr
    assert "final eval" in proc.stdout
    assert_auto_chose(proc.stdout, copies=4)  # its population: 2 x 2 directions


def test_cli_says_when_iterations_end_the_run_before_total_frames(rlpipe_cli, tmp_path, capsys):
    base = ["~tuned", "progress=false", "eval_every=0", "eval_episodes=2", "algo=ars"]
    small = ["algo.num_directions=2", "algo.num_best=2", "algo.workers=1"]
    proc = rlpipe_cli(*base, *small, "total_frames=100000", "algo.iterations=2")
    assert proc.returncode == 0, proc.stderr
    assert re.search(
        r"rlpipe: warning: the run ended at algo.iterations=2 after [\d,]+ of "
        r"total_frames=100,000 frames: raise algo.iterations to train to total_frames",
        proc.stderr,
    ), proc.stderr
    # the control, in-process: a run that total_frames ends says nothing of iterations
    cfg = compose_config(*base, *small, "total_frames=100", "algo.iterations=1000")
    assert train(cfg, tmp_path / "frames").frames >= 100
    assert "raise algo" not in capsys.readouterr().err


BAD = [
    (
        ["algo.num_directions=16", "algo.num_best=17"],
        "algo.num_best (17) must be between 1 and algo.num_directions (16)",
    ),
    (["algo.noise=0"], "algo.noise must be a finite number > 0"),
    (["algo.step_size=-1"], "algo.step_size must be a finite number > 0"),
    (["algo.noise_end=0.05"], "algo.noise_end must be null or in (0, algo.noise (0.03)], got 0.05"),
    (["algo.reward_clip=-1"], "algo.reward_clip must be true, false or a number > 0, got -1"),
    (["algo.starts=0"], "algo.starts must be"),
    (["algo.bound_penalty=-0.1"], "algo.bound_penalty must be a finite number >= 0, got -0.1"),
    (["algo.starts_until=1"], "algo.starts_until must be in (0, 1)"),
    (["algo.fitness=rank"], "algo.fitness must be one of returns, ranks; got 'rank'"),
    (["algo.episodes=0"], "algo.episodes must be >= 1, got 0"),
    (["algo.episodes_from=1.5"], "algo.episodes_from must be in [0, 1), got 1.5"),
    (
        ["algo.reward_clip=false", "algo.reward_clip_end=10"],
        "algo.reward_clip_end must be null, or a number > 0 with algo.reward_clip true or a number",
    ),
    # the preset anneals α to 0.01: a smaller α alone says how to keep it
    (["algo.step_size=0.005"], "algo.step_size_end must be null or in [0, algo.step_size (0.005)]"),
]


@pytest.mark.parametrize("args, message", BAD, ids=[a[-1] for a, _ in BAD])
def test_cli_bad_input_is_one_line(rlpipe_cli, args, message):
    proc = rlpipe_cli("progress=false", "algo=ars", "env=bipedal", *args)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"rlpipe: error: {message}"), proc.stderr
