"""The env factory: batched GymWrapper envs with the standard transforms."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from rlpipe.config import EnvConfig
from rlpipe.envs import is_discrete, make_env, num_actions, observation_size, sub_envs
from rlpipe.errors import RlpipeError


@pytest.mark.parametrize(
    "env_id, obs, discrete",
    [("CartPole-v1", 4, True), ("Pendulum-v1", 3, False), ("BipedalWalker-v3", 24, False)],
)
def test_specs_and_shapes(env_id, obs, discrete):
    env = make_env(EnvConfig(id=env_id, num_envs=3), seed=0)
    check_env_specs(env)
    assert env.batch_size == torch.Size([3])
    assert observation_size(env) == obs
    assert is_discrete(env) is discrete
    td = env.rollout(5, break_when_any_done=False)
    assert td["next", "observation"].shape == (3, 5, obs)
    assert td["next", "observation"].dtype == torch.float32
    assert td["next", "step_count"][:, -1].flatten().tolist() == [5, 5, 5]
    assert ("next", "episode_reward") in td.keys(True)
    env.close()


def test_discrete_actions_are_indices():
    env = make_env(EnvConfig(id="MountainCar-v0"))
    assert num_actions(env) == 3
    assert env.action_spec.shape == torch.Size([1])


def test_finished_envs_reset_on_their_own():
    """Autoreset is disabled: only the finished copy restarts, with a fresh observation."""
    env = make_env(EnvConfig(id="CartPole-v1", num_envs=4, max_episode_steps=7), seed=1)
    td = env.rollout(20, break_when_any_done=False)
    counts = td["next", "step_count"].squeeze(-1)
    assert counts.max() == 7
    # after the 7th step every copy restarts from step 1 with a near-zero observation
    assert (counts[:, 7] == 1).all()
    assert td["observation"][:, 7].abs().max() <= 0.05


def test_seeding_is_reproducible():
    def first_obs(seed):
        return make_env(EnvConfig(num_envs=2), seed=seed).reset()["observation"]

    assert torch.equal(first_obs(3), first_obs(3))
    assert not torch.equal(first_obs(3), first_obs(4))


def test_unknown_id_is_a_clear_error():
    with pytest.raises(RlpipeError, match="NoSuchEnv-v0"):
        make_env(EnvConfig(id="NoSuchEnv-v0"))


def test_bad_kwargs_are_a_clear_error():
    with pytest.raises(RlpipeError, match="env.kwargs"):
        make_env(EnvConfig(id="CartPole-v1", kwargs={"no_such_option": 1}))


def test_non_flat_observation_is_rejected(image_env_id):
    env = make_env(EnvConfig(id=image_env_id))
    with pytest.raises(RlpipeError, match="flat vector observations"):
        observation_size(env)


@pytest.mark.parametrize(
    "env_id, vectorization, render_mode, batched",
    [
        ("rlpipe/CartPoleContinuous-v0", "auto", None, True),
        ("rlpipe/CartPoleContinuous-v0", "auto", "rgb_array", False),
        ("rlpipe/CartPoleNoop-v0", "vector", None, True),
        ("rlpipe/CartPoleNoop-v0", "sync", None, False),
        ("CartPole-v1", "auto", None, False),  # its vector env cannot disable autoreset
    ],
)
def test_vectorization_choice(env_id, vectorization, render_mode, batched):
    cfg = EnvConfig(id=env_id, num_envs=2, max_episode_steps=9, kwargs={}, backend="gymnasium")
    env = make_env(cfg, render_mode=render_mode, vectorization=vectorization)
    assert isinstance(env.base_env._env, gym.vector.SyncVectorEnv) is not batched
    if batched:
        with pytest.raises(RlpipeError, match="SyncVectorEnv"):
            sub_envs(env)
    else:
        assert len(sub_envs(env)) == 2
    env.close()


def test_bad_vectorization_is_a_clear_error():
    with pytest.raises(RlpipeError, match="no vector implementation"):
        make_env(EnvConfig(id="CartPole-v1", backend="gymnasium"), vectorization="vector")
    with pytest.raises(RlpipeError, match="auto, sync or vector"):
        make_env(EnvConfig(id="CartPole-v1"), vectorization="async")
