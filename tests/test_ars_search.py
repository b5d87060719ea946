"""ARS's search and rollouts outside the runner: solving CartPole alone, the state dict that
resumes it exactly, episode ends at the env's time limit, reward clipping, the penalty on
outputs past the bounds, several episodes a member, results as arrays."""

from __future__ import annotations

import io
import pickle
from dataclasses import fields, replace
from functools import partial

import gymnasium as gym
import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from test_ars import CARTPOLE, PENDULUM
from torch import nn
from torch.nn.utils import parameters_to_vector

from rlpipe.algos import ARS, ARSConfig
from rlpipe.algos.ars import ARSSearch, ars_update, centered_ranks, make_ars_policy
from rlpipe.algos.ars.rollout import rollout
from rlpipe.envs import make_env
from rlpipe.episodes import evaluate
from rlpipe.errors import RlpipeError
from rlpipe.normalizer import Normalizer


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


def constant_outputs(env, outputs: list[float]):
    """An ARS policy whose network outputs a constant (its bias) and one member per output."""
    policy, _ = make_ars_policy(env, ARSConfig(), network=nn.Linear(3, 1))
    flat = torch.zeros(len(outputs), 4)  # weight [1, 3] (zero), then the bias
    flat[:, 3] = torch.tensor(outputs)
    return policy, flat


def test_bound_penalty_takes_the_outputs_past_the_bounds_off_the_training_returns():
    """Raw torques 0, 1.5, 3 and -5 against Pendulum's bound 2: the last two pay 0.1 x 1 and
    0.1 x 3 a step over 200 steps; the env's returns stay the env's."""
    policy, flat = constant_outputs(make_env(PENDULUM), [0.0, 1.5, 3.0, -5.0])
    envs = [gym.make(PENDULUM.id) for _ in range(4)]
    own = rollout(policy, envs, flat, [0, 1, 2, 3], max_steps=1000)
    penalised = rollout(policy, envs, flat, [0, 1, 2, 3], max_steps=1000, bound_penalty=0.1)
    assert torch.equal(penalised.raw_returns, own.raw_returns)
    torch.testing.assert_close(
        own.returns - penalised.returns, torch.tensor([0, 0, 20, 60.0]).double()
    )


def test_ranks_fitness_updates_on_the_centered_ranks_of_the_returns():
    """fitness="ranks": θ moves by the ARS rule on the 2N returns' centred ranks, with the
    directions the search drew."""
    search = small_search(3, fitness="ranks", num_best=2, step_size=0.05)
    theta, state = search.theta, search.generator.get_state()
    try:
        stats = search.step()
    finally:
        search.close()
    deltas = torch.randn(3, theta.numel(), generator=torch.Generator().set_state(state))
    returns = torch.tensor(stats["episode_return"], dtype=torch.float64)
    assert len(set(returns.tolist())) > 1  # the ranks are not all one
    plus, minus = centered_ranks(returns).float().chunk(2)
    torch.testing.assert_close(search.theta, ars_update(theta, deltas, plus, minus, 2, 0.05))
    with pytest.raises(RlpipeError, match="^fitness must be one of returns, ranks; got 'rank'"):
        small_search(3, fitness="rank")


def test_episodes_average_each_members_training_returns_over_fresh_seeds():
    """episodes=2: each of the 2N members runs two episodes (seeds drawn after the directions,
    shared by θ+νδ and θ-νδ in each round), θ moves by the ARS rule on the two rounds' mean
    returns, and the normaliser takes in the observations of both."""
    search = small_search(5, episodes=2, num_best=2, step_size=0.05)
    theta, state = search.theta, search.generator.get_state()
    try:
        stats = search.step()
    finally:
        search.close()
    generator = torch.Generator().set_state(state)
    deltas = torch.randn(3, theta.numel(), generator=generator)
    seeds = torch.randint(2**31 - 1, (2, 3), generator=generator)
    assert len(set(seeds.flatten().tolist())) == 6
    returns = torch.tensor(stats["episode_return"], dtype=torch.float64).reshape(2, 6)
    assert not torch.equal(returns[0], returns[1])  # two rounds, other episodes
    plus, minus = returns.mean(0).float().chunk(2)
    torch.testing.assert_close(search.theta, ars_update(theta, deltas, plus, minus, 2, 0.05))
    assert stats["env_steps"] == sum(stats["episode_length"]) == float(search.normalizer.count)
    with pytest.raises(RlpipeError, match="^episodes must be >= 1, got 0"):
        small_search(5, episodes=0)


def test_episodes_apply_from_their_fraction_of_the_run():
    """algo.episodes from the first algo.episodes_from of the run on, one episode before."""
    torch.manual_seed(0)
    cfg = ARSConfig(num_directions=2, num_best=1, workers=1, iterations=4)
    algo, seen = ARS(partial(make_env, CARTPOLE), replace(cfg, episodes=3, episodes_from=0.5)), []
    try:
        for _ in range(4):
            stats = algo.train_step()
            seen.append((algo.search.episodes, len(stats["train/episode_return"])))
    finally:
        algo.close()
    assert seen == [(1, 4), (1, 4), (3, 12), (3, 12)]


def test_bound_penalty_is_checked():
    policy, _ = make_ars_policy(make_env(PENDULUM), ARSConfig())
    factory = partial(make_env, PENDULUM)
    with pytest.raises(RlpipeError, match="^bound_penalty must be a finite number >= 0, got -1"):
        ARSSearch(policy, factory, bound_penalty=-1)
    bare = TensorDictModule(nn.Linear(3, 1), in_keys=["observation"], out_keys=["action"])
    with pytest.raises(RlpipeError, match="^bound_penalty needs a policy that writes 'policy_out"):
        ARSSearch(bare, factory, bound_penalty=0.1)
    ARSSearch(bare, factory)  # no penalty: any policy


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
