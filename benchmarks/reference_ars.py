"""The workshop notebook's ARS loop, ported to gymnasium 1.x: the reference for rlpipe's ARS.

A faithful single-process NumPy port of ``HP``, ``Normalizer``, ``Policy`` and
``ARSTrainer`` (the notebook's cell-by-cell logic: the normaliser observes every state before
normalising it, rewards are clipped to [-1, 1], σ is the std of all 2N returns, one evaluation
episode per iteration). Changes: gymnasium's 5-tuple API (``terminated or truncated`` ends an
episode), ``spec.max_episode_steps`` for the removed ``spec.timestep_limit``, BipedalWalker-v3,
no video recording, and counters for the env steps taken.

    python benchmarks/reference_ars.py --iterations 5
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np


class HP:
    """Hyperparameters (the notebook's defaults)."""

    def __init__(
        self,
        nb_steps: int = 1000,
        episode_length: int = 2000,
        learning_rate: float = 0.02,
        num_deltas: int = 16,
        num_best_deltas: int = 16,
        noise: float = 0.03,
        seed: int = 1,
        env_name: str = "BipedalWalker-v3",
    ) -> None:
        self.nb_steps = nb_steps
        self.episode_length = episode_length
        self.learning_rate = learning_rate
        self.num_deltas = num_deltas
        self.num_best_deltas = num_best_deltas
        assert self.num_best_deltas <= self.num_deltas
        self.noise = noise
        self.seed = seed
        self.env_name = env_name


class Normalizer:
    """Normalizes the inputs with a running mean and variance (clipped at 1e-2)."""

    def __init__(self, nb_inputs: int) -> None:
        self.n = np.zeros(nb_inputs)
        self.mean = np.zeros(nb_inputs)
        self.mean_diff = np.zeros(nb_inputs)
        self.var = np.zeros(nb_inputs)

    def observe(self, x: np.ndarray) -> None:
        self.n += 1.0
        last_mean = self.mean.copy()
        self.mean += (x - self.mean) / self.n
        self.mean_diff += (x - last_mean) * (x - self.mean)
        self.var = (self.mean_diff / self.n).clip(min=1e-2)

    def normalize(self, inputs: np.ndarray) -> np.ndarray:
        obs_mean = self.mean
        obs_std = np.sqrt(self.var)
        return (inputs - obs_mean) / obs_std


class Policy:
    """The linear policy θ (zero-initialised) and the ARS update."""

    def __init__(self, input_size: int, output_size: int, hp: HP) -> None:
        self.theta = np.zeros((output_size, input_size))
        self.hp = hp

    def evaluate(self, input, delta=None, direction=None):
        if direction is None:
            return self.theta.dot(input)
        elif direction == "+":
            return (self.theta + self.hp.noise * delta).dot(input)
        elif direction == "-":
            return (self.theta - self.hp.noise * delta).dot(input)

    def sample_deltas(self):
        return [np.random.randn(*self.theta.shape) for _ in range(self.hp.num_deltas)]

    def update(self, rollouts, sigma_rewards):
        step = np.zeros(self.theta.shape)
        for r_pos, r_neg, delta in rollouts:
            step += (r_pos - r_neg) * delta
        self.theta += self.hp.learning_rate / (self.hp.num_best_deltas * sigma_rewards) * step


class ARSTrainer:
    """Explore ±δ for every direction, update θ, play one evaluation episode; per iteration."""

    def __init__(self, hp: HP | None = None) -> None:
        self.hp = hp or HP()
        np.random.seed(self.hp.seed)
        self.env = gym.make(self.hp.env_name)
        self.env.reset(seed=self.hp.seed)
        self.hp.episode_length = self.env.spec.max_episode_steps or self.hp.episode_length
        self.input_size = self.env.observation_space.shape[0]
        self.output_size = self.env.action_space.shape[0]
        self.normalizer = Normalizer(self.input_size)
        self.policy = Policy(self.input_size, self.output_size, self.hp)
        self.env_steps = 0  # added: every env step, exploration and evaluation
        self.explore_steps = 0  # added: env steps of the perturbed rollouts only

    def explore(self, direction=None, delta=None) -> float:
        state, _ = self.env.reset()
        done = False
        num_plays = 0.0
        sum_rewards = 0.0
        while not done and num_plays < self.hp.episode_length:
            self.normalizer.observe(state)
            state = self.normalizer.normalize(state)
            action = self.policy.evaluate(state, delta, direction)
            state, reward, terminated, truncated, _ = self.env.step(action)
            done = terminated or truncated
            reward = max(min(reward, 1), -1)
            sum_rewards += reward
            num_plays += 1
        self.env_steps += int(num_plays)
        if direction is not None:
            self.explore_steps += int(num_plays)
        return sum_rewards

    def train_step(self, step: int) -> float:
        """One iteration of the notebook's ``train`` loop; returns the evaluation reward."""
        deltas = self.policy.sample_deltas()
        positive_rewards = [0] * self.hp.num_deltas
        negative_rewards = [0] * self.hp.num_deltas
        for k in range(self.hp.num_deltas):
            positive_rewards[k] = self.explore(direction="+", delta=deltas[k])
            negative_rewards[k] = self.explore(direction="-", delta=deltas[k])
        sigma_rewards = np.array(positive_rewards + negative_rewards).std()
        scores = {
            k: max(r_pos, r_neg)
            for k, (r_pos, r_neg) in enumerate(zip(positive_rewards, negative_rewards))
        }
        order = sorted(scores.keys(), key=lambda x: scores[x], reverse=True)
        order = order[: self.hp.num_best_deltas]
        rollouts = [(positive_rewards[k], negative_rewards[k], deltas[k]) for k in order]
        self.policy.update(rollouts, sigma_rewards)
        return self.explore()

    def train(self) -> None:
        for step in range(self.hp.nb_steps):
            print("Step: ", step, "Reward: ", self.train_step(step))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=5)
    args = p.parse_args()
    trainer = ARSTrainer(HP(nb_steps=args.iterations))
    start = time.perf_counter()
    trainer.train()
    seconds = time.perf_counter() - start
    print(f"{trainer.env_steps} env steps in {seconds:.1f} s: {trainer.env_steps / seconds:,.0f}/s")


if __name__ == "__main__":
    main()
