"""The notebooks' CartPole variants: gymnasium and TorchRL checks, physics limits, rendering, and
the NumPy-batched versions against copies of the single env."""

from __future__ import annotations

import math
import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import SyncVectorEnv
from test_config import compose_config
from torchrl.envs.utils import check_env_specs

from rlpipe.config import EnvConfig
from rlpipe.envs import is_discrete, make_env, num_actions, observation_size
from rlpipe.envs.cartpole import ContinuousCartPoleVectorEnv, NoopCartPoleVectorEnv

CONTINUOUS, NOOP = "rlpipe/CartPoleContinuous-v0", "rlpipe/CartPoleNoop-v0"
VECTOR = {CONTINUOUS: ContinuousCartPoleVectorEnv, NOOP: NoopCartPoleVectorEnv}


@pytest.mark.parametrize("env_id", [CONTINUOUS, NOOP])
def test_gymnasium_env_checker(env_id):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning either
        check_env(gym.make(env_id).unwrapped)


@pytest.mark.parametrize("vectorization", ["vector", "sync"])
@pytest.mark.parametrize("env_id, discrete", [(CONTINUOUS, False), (NOOP, True)])
def test_torchrl_specs(env_id, discrete, vectorization):
    env = make_env(EnvConfig(id=env_id, num_envs=3), seed=0, vectorization=vectorization)
    kind = VECTOR[env_id] if vectorization == "vector" else SyncVectorEnv
    assert type(env.base_env._env) is kind
    check_env_specs(env)
    assert observation_size(env) == 4 and is_discrete(env) is discrete
    if discrete:
        assert num_actions(env) == 3
    else:
        assert env.action_spec_unbatched.space.low.item() == -1.0
    env.close()


def start(env_id: str, state) -> gym.Env:
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    env.state = np.array(state, dtype=np.float64)
    return env


def test_continuous_force_is_clipped_to_10_newtons():
    full, beyond = start(CONTINUOUS, [0, 0, 0, 0]), start(CONTINUOUS, [0, 0, 0, 0])
    half = start(CONTINUOUS, [0, 0, 0, 0])
    full.step(np.array([1.0], dtype=np.float32))
    beyond.step(np.array([7.0], dtype=np.float32))
    half.step(np.array([0.5], dtype=np.float32))
    assert np.array_equal(full.state, beyond.state)
    assert half.state[1] == pytest.approx(full.state[1] / 2) and full.state[1] > 0


@pytest.mark.parametrize(
    "env_id, limit_degrees, action",
    [(CONTINUOUS, 20, np.zeros(1, dtype=np.float32)), (NOOP, 24, 1)],
)
def test_failure_angle_and_reward_per_step_survived(env_id, limit_degrees, action):
    limit = math.radians(limit_degrees)
    _, reward, terminated, _, _ = start(env_id, [0, 0, limit - 0.01, 0]).step(action)
    assert (reward, terminated) == (1.0, False)
    _, reward, terminated, _, _ = start(env_id, [0, 0, limit + 0.01, 0]).step(action)
    assert (reward, terminated) == (0.0, True)
    _, _, terminated, _, _ = start(env_id, [2.41, 0, 0, 0]).step(action)
    assert terminated


def test_noop_actions_push_left_nothing_right():
    velocities = []
    for action in range(3):
        env = start(NOOP, [0, 0, 0, 0])
        env.step(action)
        velocities.append(env.state[1])
    assert velocities[0] < 0 and velocities[1] == 0 and velocities[2] > 0
    assert start(NOOP, [0, 0, 0, 0]).length == 2 * gym.make("CartPole-v1").unwrapped.length


@pytest.mark.parametrize("env_id", [CONTINUOUS, NOOP])
def test_seeding_and_rgb_rendering(env_id):
    env = gym.make(env_id, render_mode="rgb_array")
    first, _ = env.reset(seed=3)
    again, _ = env.reset(seed=3)
    other, _ = env.reset(seed=4)
    assert np.array_equal(first, again) and not np.array_equal(first, other)
    frame = env.render()
    assert frame.shape == (400, 600, 3) and frame.dtype == np.uint8
    env.unwrapped.state = np.array([1.0, 0, 0.3, 0])
    assert not np.array_equal(env.render(), frame)
    env.close()


def test_continuous_config_uses_the_notebooks_horizon():
    env_cfg = compose_config("algo=reinforce", "env=cartpole_continuous").env
    assert (env_cfg.id, env_cfg.max_episode_steps) == (CONTINUOUS, 50)
    env = make_env(env_cfg, num_envs=2, seed=0)
    td = env.rollout(200, break_when_any_done=False)  # zero-mean random actions
    assert td["next", "step_count"].max() <= 50
    env.close()


@pytest.mark.parametrize("env_id", [CONTINUOUS, NOOP])
def test_vector_env_steps_like_single_envs(env_id):
    """Same seeds and actions: the same bits, through failures, time limits, partial resets and
    reseeding; the continuous actions go past the bounds."""
    n, limit = 6, 25
    vector = gym.make_vec(
        env_id, n, vectorization_mode="vector_entry_point", max_episode_steps=limit
    )
    singles = [gym.make(env_id, max_episode_steps=limit) for _ in range(n)]
    rng = np.random.default_rng(0)
    obs, _ = vector.reset(seed=11)
    assert np.array_equal(obs, [env.reset(seed=11 + i)[0] for i, env in enumerate(singles)])
    seen = np.zeros(2, dtype=int)
    for t in range(300):
        if env_id == CONTINUOUS:
            actions = rng.uniform(-1.5, 1.5, size=(n, 1)).astype(np.float32)
        else:
            actions = rng.integers(0, 3, size=n)
        got = vector.step(actions)[:4]
        want = [np.array(x) for x in zip(*(e.step(a)[:4] for e, a in zip(singles, actions)))]
        for g, w in zip(got, want):
            assert np.array_equal(g, w) and g.dtype == w.dtype, t
        done = got[2] | got[3]
        seen += got[2].sum(), got[3].sum()
        if done.any():
            seeds = [100 + t if i == 0 and t > 150 else None for i in range(n)]  # copy 0 reseeded
            obs, _ = vector.reset(seed=seeds, options={"reset_mask": done})
            for i in np.flatnonzero(done):
                assert np.array_equal(obs[i], singles[i].reset(seed=seeds[i])[0])
            assert np.array_equal(obs[~done], got[0][~done])  # the others keep going
    assert (seen > 0).all()  # failures and time limits both happened
    vector.close()


def test_make_env_rollouts_equal_on_both_vectorizations():
    """TorchRL's partial resets (reset_mask) of the batched env restart what the sync one does."""

    def rollout(vectorization: str) -> torch.Tensor:
        cfg = EnvConfig(id=CONTINUOUS, num_envs=4, max_episode_steps=30)
        env = make_env(cfg, seed=5, vectorization=vectorization)
        push = torch.tensor([[0.3], [1.0], [-0.2], [2.0]])

        def policy(td):
            td["action"] = (td["observation"][:, 2:3] * 5 + push).clamp(-1, 1)
            return td

        return env.rollout(200, policy, break_when_any_done=False)

    vector, sync = rollout("vector"), rollout("sync")
    assert (vector["next", "done"].sum() > 4).item()
    assert (vector == sync).all()
