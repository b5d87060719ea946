"""Dict and image observations: make_env's DictObservation and image transforms, the encoders
picked from the observation, DQN/PPO/SAC on each kind, and the one-line refusals."""

from __future__ import annotations

import importlib.util
import json
from functools import partial
from pathlib import Path

import gymnasium as gym
import numpy as np
import obs_envs  # noqa: F401  (registers rlpipe-test/*)
import pytest
import torch
from conftest import TINY, run_module
from tensordict import TensorDict
from torchrl.envs import CatFrames, ToTensorImage
from torchrl.modules import ConvNet

from rlpipe.algos import ARS, DQN, PPO, SAC, ARSConfig, DQNConfig, PPOConfig, SACConfig
from rlpipe.algos.configs import ReinforceConfig
from rlpipe.algos.reinforce import Reinforce
from rlpipe.config import EnvConfig
from rlpipe.encoders import KeyEncoder, encoder
from rlpipe.envs import env_copies, make_env, observation_of
from rlpipe.envs.observations import DictObservation
from rlpipe.episodes import evaluate
from rlpipe.errors import RlpipeError
from rlpipe.greedy import greedy_policy

TESTS = Path(__file__).parent
OFF = dict(batch_size=8, buffer_size=64, learning_starts=8, frames_per_batch=8, updates_per_batch=2)
ALGOS = {
    "dqn": (DQN, DQNConfig, OFF, ""),
    "ppo": (PPO, PPOConfig, dict(frames_per_batch=32, minibatch_size=16, epochs=2), ""),
    "sac": (SAC, SACConfig, OFF, "Continuous"),
}


def test_a_dict_observation_becomes_one_vector_in_sorted_key_order_without_text():
    wrapped = DictObservation(gym.make("rlpipe-test/Dict-v0"))
    observation, _ = wrapped.reset(seed=1)
    layout = {part.key: (part.start, part.shape, part.image) for part in wrapped.layout}
    assert layout == {
        "flag": (0, (3,), False),  # Discrete(3): one-hot
        "pixels": (3, (8, 8, 3), True),
        "side": (195, (2,), False),
    }
    assert observation.shape == wrapped.observation_space.shape == (197,)
    side = int(observation[195:].argmax())
    assert observation[:3].tolist() == [float(i == side) for i in range(3)]
    assert observation[3:195].max() == 255.0  # an image key's raw values


@pytest.mark.parametrize("mode", ["flatten", "keys"])
def test_make_env_gives_dict_envs_one_observation_on_the_lean_path(mode):
    env = make_env(EnvConfig(id="rlpipe-test/Dict-v0", num_envs=2, dict_obs=mode), seed=0)
    assert env.observation_spec["observation"].shape == (2, 197)
    assert env_copies(env) is not None  # a flat vector: rlpipe's lean collection
    observation = observation_of(env)
    assert observation.flat == (mode == "flatten")
    assert (observation.layout is None) == (mode == "flatten")
    env.close()


@pytest.mark.parametrize(
    ("options", "shape"),
    [
        ({}, (12, 16, 16)),
        ({"grayscale": True, "frame_stack": 2}, (2, 16, 16)),
    ],
)
def test_images_become_stacked_chw_floats_in_0_1(options, shape):
    env = make_env(EnvConfig(id="rlpipe-test/Image-v0", num_envs=2, **options), seed=0)
    assert observation_of(env).image and observation_of(env).shape == shape
    assert env_copies(env) is None  # extra transforms: TorchRL's collector steps it
    data = env.rollout(3, break_when_any_done=False)
    seen = data["observation"]
    assert seen.shape == (2, 3, *shape) and seen.dtype == torch.float32
    assert seen.min() == 0.0 and seen.max() == pytest.approx(1.0, abs=1e-3)
    types = [type(t) for t in env.transform]
    assert ToTensorImage in types and (CatFrames in types) == (shape[0] not in (3,))
    env.close()


def test_resize_needs_torchvision_or_says_so():
    cfg = EnvConfig(id="rlpipe-test/Image-v0", resize=[8, 10], frame_stack=1)
    if importlib.util.find_spec("torchvision") is None:
        with pytest.raises(RlpipeError, match="env.resize uses TorchRL's Resize, which needs"):
            make_env(cfg)
        return
    assert observation_of(make_env(cfg)).shape == (3, 8, 10)


def test_frame_stack_on_vectors_concatenates_the_last_steps():
    env = make_env(EnvConfig(id="CartPole-v1", frame_stack=3), seed=0)
    data = env.rollout(2)
    assert data["observation"].shape == (1, 2, 12)
    first = data["observation"][0, 0]
    assert torch.equal(first[:4], first[8:])  # after a reset: the first frame repeated
    env.close()


def test_the_encoder_is_picked_from_the_observation():
    image = observation_of(make_env(EnvConfig(id="rlpipe-test/Image-v0"), seed=0))
    cnn, features = encoder(image)
    assert isinstance(cnn[0], ConvNet) and cnn(torch.zeros(5, *image.shape)).shape == (5, features)
    keys = observation_of(make_env(EnvConfig(id="rlpipe-test/Dict-v0", dict_obs="keys")))
    per_key, features = encoder(keys)
    assert isinstance(per_key, KeyEncoder) and features == 256 + 64 + 64
    assert per_key(torch.zeros(4, 7, 197)).shape == (4, 7, features)
    flat = observation_of(make_env(EnvConfig(id="rlpipe-test/Dict-v0")))
    assert encoder(flat) == (None, 197)


@pytest.mark.parametrize("name", ALGOS)
@pytest.mark.parametrize("env_id", ["Image", "Dict-keys", "Dict-flatten"])
def test_dqn_ppo_and_sac_train_and_evaluate_on_images_and_dicts(name, env_id):
    algo_class, config, small, suffix = ALGOS[name]
    kind, _, mode = env_id.partition("-")
    cfg = EnvConfig(id=f"rlpipe-test/{kind}{suffix}-v0", num_envs=2, dict_obs=mode or "flatten")
    algo = algo_class(partial(make_env, cfg, seed=0), config(**small))
    convs = [m for m in algo.policy.modules() if isinstance(m, ConvNet)]
    assert len(convs) == (0 if mode == "flatten" else 1)
    for _ in range(3):
        metrics = algo.train_step()
    assert np.isfinite(metrics["train/loss"])
    env = make_env(cfg, seed=1)
    assert len(evaluate(algo.policy, env, 2).returns) == 2
    env.close()
    algo.close()


def test_an_image_run_trains_evaluates_and_resumes_through_the_cli(tmp_path):
    run = tmp_path / "run"
    args = [
        *TINY,
        "algo=ppo",
        "env=gym",
        "env.id=obs_envs:rlpipe-test/Image-v0",
        "env.num_envs=2",
        "algo.frames_per_batch=64",
        "algo.minibatch_size=32",
        "algo.epochs=1",
    ]
    cli = partial(run_module, "rlpipe", cwd=tmp_path, pythonpath=TESTS)
    proc = cli(*args, f"hydra.run.dir={run}")
    assert proc.returncode == 0, proc.stderr
    assert "final eval" in proc.stdout + proc.stderr
    more = [arg for arg in args if not arg.startswith("total_frames")]
    proc = cli(*more, "total_frames=320", f"resume={run}", f"hydra.run.dir={run}")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((run / "summary.json").read_text())["frames"] == 320


@pytest.mark.parametrize(
    ("build", "message"),
    [
        (lambda f: Reinforce(f, ReinforceConfig()), "REINFORCE takes flat vector observations"),
        (lambda f: ARS(f, ARSConfig(workers=1)), "ARS takes flat vector observations"),
        (lambda f: PPO(f, PPOConfig(normalize_observations=True)), "normalize_observations=false"),
    ],
    ids=["reinforce", "ars", "ppo-normalize"],
)
def test_what_cannot_take_images_says_so_in_one_line(build, message):
    with pytest.raises(RlpipeError, match=message) as info:
        build(partial(make_env, EnvConfig(id="rlpipe-test/Image-v0"), seed=0))
    assert "\n" not in str(info.value)


def test_mbrl_refuses_images_in_one_line():
    from rlpipe.algos.mbrl import MBRL, MBRLConfig

    factory = partial(make_env, EnvConfig(id="rlpipe-test/ImageContinuous-v0"), seed=0)
    with pytest.raises(RlpipeError, match="MBRL takes flat vector observations"):
        MBRL(factory, MBRLConfig())


def test_a_tuple_observation_and_image_options_on_vectors_are_refused():
    with pytest.raises(RlpipeError, match="Tuple observation space"):
        make_env(EnvConfig(id="rlpipe-test/Tuple-v0"))
    with pytest.raises(RlpipeError, match="env.grayscale and env.resize apply to images"):
        make_env(EnvConfig(id="CartPole-v1", resize=[8, 8]))
    with pytest.raises(RlpipeError, match="env.resize must be"):
        EnvConfig(resize=[8])


def test_an_image_policy_is_refused_by_export_and_a_dict_policy_exports():
    image = DQN(partial(make_env, EnvConfig(id="rlpipe-test/Image-v0"), seed=0), DQNConfig(**OFF))
    with pytest.raises(RlpipeError, match="cannot export this dqn policy: it sees images"):
        greedy_policy(image)
    factory = partial(make_env, EnvConfig(id="rlpipe-test/Dict-v0", dict_obs="keys"), seed=0)
    keys = DQN(factory, DQNConfig(**OFF))
    observations = torch.rand(3, 197) * 255
    values = keys.policy(TensorDict(observation=observations, batch_size=[3]))["action_value"]
    assert torch.equal(greedy_policy(keys)(observations), values.argmax(-1))


def test_the_random_baseline_acts_once_per_copy_on_images():
    """policy=random on an image env (a stack of frames): one action per env copy, and episodes."""
    from rlpipe.episodes import evaluate
    from rlpipe.heuristic import random_policy

    env = make_env(EnvConfig(id="rlpipe-test/Image-v0", num_envs=3), seed=0)
    policy = random_policy(env)
    assert policy(env.reset())["action"].shape == env.action_spec.shape
    assert len(evaluate(policy, env, 4).returns) == 4
