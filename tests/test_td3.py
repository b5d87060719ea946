"""examples/td3.py's own maths: the delayed actor and target updates, the warm-up and
exploration noise in half action ranges, greedy actions in bounds, an exact state round trip."""

from __future__ import annotations

import importlib
from functools import partial
from pathlib import Path
from types import ModuleType

import pytest
import torch

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PENDULUM = EnvConfig(id="Pendulum-v1", num_envs=2, backend="gymnasium")
SMALL = dict(batch_size=16, buffer_size=512, learning_starts=16, frames_per_batch=8)


@pytest.fixture
def td3(registry, monkeypatch) -> ModuleType:
    """``examples/td3.py``, imported (registering ``td3`` until the test ends)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    return importlib.import_module("td3")


def build(td3: ModuleType, **overrides: object):
    torch.manual_seed(0)
    cfg = td3.TD3Config(**{**SMALL, "hidden_sizes": [16], **overrides})
    return td3.TD3(partial(make_env, PENDULUM, seed=0), cfg)


def test_the_actor_and_the_targets_move_on_every_policy_delay_th_step(td3):
    algo = build(td3, policy_delay=2)
    loss = algo.loss
    parts = ("actor_network_params", "qvalue_network_params")
    start = {
        name: getattr(loss, name).clone() for name in (*parts, *(f"target_{p}" for p in parts))
    }

    def moved(name: str) -> bool:
        return bool((getattr(loss, name) != start[name]).any())

    metrics = {}
    while algo.updates == 0:
        metrics = algo.train_step()
    assert algo.updates == 1 and "train/actor_loss" not in metrics
    assert moved("qvalue_network_params")  # the critics learn on every step ...
    assert not any(map(moved, ("actor_network_params", *(f"target_{p}" for p in parts))))
    metrics = algo.train_step()  # ... the actor and the targets on every second one
    assert algo.updates == 2 and "train/actor_loss" in metrics
    assert all(map(moved, start))
    algo.close()


def test_warm_up_is_uniform_then_noise_is_in_half_action_ranges(td3):
    warming = [True]
    explore = td3.Exploration(torch.tensor([-2.0]), torch.tensor([2.0]), 0.1, lambda: warming[0])
    actor = torch.full((20_000, 1), 0.5)
    uniform = explore(actor)
    assert (
        uniform.min() > -2 and uniform.max() < 2 and abs(float(uniform.std()) - 4 / 12**0.5) < 0.03
    )
    warming[0] = False
    noisy = explore(actor)
    assert abs(float(noisy.mean()) - 0.5) < 0.01 and abs(float(noisy.std()) - 0.2) < 0.01
    assert explore(torch.full((100, 1), 1.99)).max() == 2.0  # clipped to the bounds


def test_collected_actions_are_random_for_learning_starts_frames(td3):
    algo = build(td3, learning_starts=64, updates_per_batch=0)  # no updates: the actor stays
    while algo.frames < 128:
        algo.train_step()
    stored = algo.buffer[:]  # in the order collected: the first 64 rows are the warm-up's
    greedy = algo.policy(stored.select("observation").clone())["action"]
    offset = (stored["action"] - greedy).squeeze(-1)
    assert offset[:64].std() > 0.8 and 0.15 < offset[64:].std() < 0.25  # uniform, then ~0.2
    algo.close()


def test_greedy_actions_are_in_bounds_and_a_state_round_trip_is_exact(td3):
    algo = build(td3)
    for _ in range(3):
        algo.train_step()
    env = make_env(PENDULUM, seed=1)
    observation = env.reset()
    env.close()
    first, second = algo.policy(observation.clone())["action"], algo.policy(observation)["action"]
    assert torch.equal(first, second) and first.abs().max() <= 2.0
    twin = build(td3)
    twin.load_state_dict(algo.state_dict())
    assert twin.updates == algo.updates == 2  # at 16 and 24 frames: where the delay stands
    ours, theirs = algo.loss.state_dict(), twin.loss.state_dict()
    assert all(torch.equal(ours[key], theirs[key]) for key in ours)
    algo.close()
    twin.close()
