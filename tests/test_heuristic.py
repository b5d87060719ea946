"""The hand-written BipedalWalker baselines: the gait's state machine, batching and walking."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch

from rlpipe.heuristic import PLACE, PUSH, SWING, NotebookWalker, WalkerGait


def walk(gait: WalkerGait, seed: int, steps: int) -> tuple[list[np.ndarray], float, bool]:
    """``gait`` alone on BipedalWalker-v3: its actions, the hull's x advance, whether it fell."""
    env = gym.make("BipedalWalker-v3")
    obs, _ = env.reset(seed=seed)
    start, actions, fell = float(env.unwrapped.hull.position[0]), [], False
    for t in range(steps):
        action = gait(torch.as_tensor(obs)[None], torch.tensor([[t]]))[0].numpy()
        actions.append(action)
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            fell = terminated
            break
    advance = float(env.unwrapped.hull.position[0]) - start
    env.close()
    return actions, advance, fell


def test_gait_walks_forward_without_falling():
    _, advance, fell = walk(WalkerGait(), seed=3, steps=400)
    assert not fell and advance > 5.0  # a standing or falling walker covers < 1


def test_gait_goes_through_its_phases_and_swaps_legs():
    gait, seen = WalkerGait(), set()
    env = gym.make("BipedalWalker-v3")
    obs, _ = env.reset(seed=3)
    for t in range(300):
        action = gait(torch.as_tensor(obs)[None], torch.tensor([[t]]))[0].numpy()
        seen.add((int(gait.phase[0]), int(gait.support[0])))
        obs, *_ = env.step(action)
    env.close()
    assert {phase for phase, _ in seen} == {SWING, PLACE, PUSH}
    assert {support for _, support in seen} == {0, 1}


def test_gait_rows_are_independent_and_restart_with_each_episode():
    """A batch of copies acts as each copy alone; step_count 0 restarts a copy's state."""
    steps = 100  # copy 0 is then placing its leg 0, supported by leg 1
    alone = [walk(WalkerGait(), seed, steps + 1)[0] for seed in (3, 4)]
    gait = WalkerGait()
    envs = [gym.make("BipedalWalker-v3") for _ in range(2)]
    obs = [env.reset(seed=seed)[0] for env, seed in zip(envs, (3, 4))]
    for t in range(steps):
        actions = gait(torch.as_tensor(np.stack(obs)), torch.full((2, 1), t)).numpy()
        for i, env in enumerate(envs):
            np.testing.assert_allclose(actions[i], alone[i][t], atol=1e-6)
            obs[i] = env.step(actions[i])[0]
    # copy 0 starts an episode here: it acts as a fresh gait; copy 1 carries on
    now = torch.as_tensor(np.stack(obs))
    actions = gait(now, torch.tensor([[0], [steps]])).numpy()
    fresh = WalkerGait()(now[:1], torch.tensor([[0]]))[0].numpy()
    assert not np.allclose(fresh, alone[0][steps], atol=1e-3)  # the restart changes the action
    np.testing.assert_allclose(actions[0], fresh, atol=1e-6)
    np.testing.assert_allclose(actions[1], alone[1][steps], atol=1e-6)


def test_notebook_controller_eases_a_folding_leg_back():
    obs = torch.zeros(2, 24)
    obs[0, 7] = -1.0  # leg 1's knee folds fast, no foot on the ground
    obs[1, 8] = obs[1, 13] = 1.0  # both feet down: random torques
    action = NotebookWalker()(obs)
    torch.testing.assert_close(action[0], torch.tensor([-0.05, -0.2, 0.0, 0.0]))
    assert action.shape == (2, 4) and bool((action[1].abs() <= 1).all())
