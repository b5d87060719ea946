"""The REINFORCE/ARS notebook's REINFORCE loop, ported faithfully: the reference for benchmarks.

One env stepped one frame at a time, a linear Gaussian policy (mean, sigmoid std), discounted
returns normalised per episode, ``updates`` Adam steps on random minibatches per epoch, then
``test_episodes`` greedy episodes. The only changes from the notebook: the env is rlpipe's
continuous CartPole (the notebook's physics; actions clipped to [-1, 1], reward 0 on the failing
step as in the notebook), gymnasium's ``reset``/``step`` API, states stacked through
``np.array`` (the notebook's ``as_tensor`` of a list of arrays is the same, only slower), and
per-epoch eval results returned instead of printed.

The loss is the notebook's, shape for shape. A suspected broadcasting quirk (``log_prob`` of
``[B, 1]`` actions under a ``[B]`` distribution would give a ``[B, B]`` matrix) does not happen:
the notebook's ``torch.as_tensor(list of one-element tensors)`` turns each action into a
scalar, so its actions are ``[N]`` and ``log_prob`` is ``[B]``, the per-sample REINFORCE
objective (checked with torch 2.13: the notebook's line and this port's ``torch.cat`` give
equal ``[N]`` tensors). rlpipe's ``baseline=none`` objective is the same.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from torch import distributions

from rlpipe.envs.cartpole import ContinuousCartPoleEnv


class Agent:
    """The notebook's linear agent: ``net(state) -> (mean, raw std)``."""

    def __init__(self) -> None:
        self.net = torch.nn.Linear(4, 2)

    def __call__(self, state: np.ndarray, deterministic: bool = False) -> torch.Tensor:
        params = self.net(torch.as_tensor(state).view(1, -1))[0]
        if deterministic:
            return params[0].view(1)
        return distributions.Normal(params[0], torch.sigmoid(params[1])).sample(sample_shape=(1,))


def run(
    seed: int,
    epochs: int = 20,
    episodes_per_epoch: int = 100,
    max_episode_len: int = 50,
    batch_size: int = 128,
    policy_updates_per_epoch: int = 50,
    gamma: float = 0.99,
    test_episodes: int = 20,
) -> list[dict]:
    """Train like the notebook; one row per epoch: eval mean, frames and seconds so far.

    ``seconds`` is training wall time (collection and updates); the per-epoch evaluation is
    timed separately, as rlpipe's runner does.
    """
    torch.manual_seed(seed)
    env = ContinuousCartPoleEnv()
    env.reset(seed=seed)
    agent = Agent()
    optim = torch.optim.Adam(agent.net.parameters(), lr=1e-3, weight_decay=1e-4)
    rows, frames, train_seconds = [], 0, 0.0
    for epoch in range(epochs):
        start = time.perf_counter()
        states, actions, rewards = [], [], []
        for _ in range(episodes_per_epoch):
            state, _ = env.reset()
            done, steps = False, 0
            ep_rewards, ep_states, ep_actions = [], [], []
            while not done:
                action = agent(state, deterministic=False)
                ep_states.append(state)
                ep_actions.append(action)
                state, reward, done, _, _ = env.step(action.numpy())
                ep_rewards.append(reward)
                steps += 1
                if steps >= max_episode_len:
                    done = True
            frames += steps
            rs, ret = [], 0.0
            for r in ep_rewards[::-1]:
                ret = r + gamma * ret
                rs.insert(0, ret)
            rs = torch.as_tensor(rs)
            rewards.append((rs - rs.mean()) / (rs.std() + np.finfo(np.float32).eps.item()))
            states.append(ep_states)
            actions.append(ep_actions)
        flat_states, flat_actions, flat_rewards = [], [], []
        for i in range(episodes_per_epoch):
            for j in range(len(states[i])):
                flat_states.append(states[i][j])
                flat_actions.append(actions[i][j])
                flat_rewards.append(rewards[i][j].item())
        states = torch.as_tensor(np.array(flat_states))
        actions = torch.cat(flat_actions)  # the notebook's as_tensor(list of 1-element tensors)
        rewards = torch.as_tensor(flat_rewards)
        for _ in range(policy_updates_per_epoch):
            idx = torch.randint(0, len(rewards), (batch_size,))
            outputs = agent.net(states[idx])
            distr = distributions.Normal(outputs[:, 0], torch.sigmoid(outputs[:, 1]))
            expected_log_return = (distr.log_prob(actions[idx]) * rewards[idx]).mean()
            optim.zero_grad()
            (-expected_log_return).backward()
            optim.step()
        train_seconds += time.perf_counter() - start
        ep_returns = []
        with torch.no_grad():
            for _ in range(test_episodes):
                state, _ = env.reset()
                done, steps, ep_return = False, 0, 0.0
                while not done:
                    state, reward, done, _, _ = env.step(agent(state, deterministic=True).numpy())
                    ep_return += reward
                    steps += 1
                    if steps >= max_episode_len:
                        done = True
                ep_returns.append(ep_return)
        rows.append(
            {
                "epoch": epoch + 1,
                "eval": float(np.mean(ep_returns)),
                "frames": frames,
                "seconds": train_seconds,
            }
        )
    return rows
