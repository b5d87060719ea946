"""DQN on CartPole-v1: rlpipe's tuned preset vs Stable-Baselines3 with RL Zoo's tuned settings.

Both run in this process, on the same seeds, with the same evaluation: every ``--eval-every``
frames, ``--eval-episodes`` greedy episodes on separate env copies; evaluation time is excluded
from both clocks. Reported per seed: frames and training seconds until the eval mean first
reaches 500, the final eval, and the wall ratio rlpipe / SB3.

    pip install -e ".[dev,bench]"
    python benchmarks/dqn_cartpole.py --append BENCHMARKS.md
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
from common import budget_parser, compose_config, machine, publish, read_scalar, table

from rlpipe.config import RUN_KEYS
from rlpipe.pipeline import train

TARGET = 500.0
RL_ZOO_CARTPOLE = dict(  # rl-baselines3-zoo hyperparams/dqn.yml, CartPole-v1
    learning_rate=2.3e-3,
    batch_size=64,
    buffer_size=100_000,
    learning_starts=1000,
    gamma=0.99,
    target_update_interval=10,
    train_freq=256,
    gradient_steps=128,
    exploration_fraction=0.16,
    exploration_final_eps=0.04,
    policy_kwargs=dict(net_arch=[256, 256]),
)


def first_hit(evals: list[tuple[int, float, float]]) -> tuple[int, float] | None:
    """(frames, train seconds) of the first evaluation reaching the target."""
    return next(((f, s) for f, mean, s in evals if mean >= TARGET), None)


def run_rlpipe(seed: int, frames: int, eval_every: int, episodes: int) -> dict:
    cfg = compose_config(
        "+experiment=dqn_cartpole",
        f"seed={seed}",
        f"total_frames={frames}",
        f"eval_every={eval_every}",
        f"eval_episodes={episodes}",
        "checkpoint_every=0",
        "progress=false",
    )
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp)
        result = train(cfg, run_dir)
        means = read_scalar(run_dir, "eval/return_mean")
        seconds = read_scalar(run_dir, "time/train_seconds")
    evals = [(f, m, s) for (f, m), (_, s) in zip(means, seconds)]
    return {"hit": first_hit(evals), "final": result.eval_mean, "config": cfg}


def run_sb3(seed: int, frames: int, eval_every: int, episodes: int) -> dict:
    from stable_baselines3 import DQN
    from stable_baselines3.common.callbacks import BaseCallback

    class GreedyEval(BaseCallback):
        def __init__(self) -> None:
            super().__init__()
            self.envs = gym.make_vec("CartPole-v1", num_envs=episodes)
            self.evals: list[tuple[int, float, float]] = []
            self.eval_seconds = 0.0
            self.start = time.perf_counter()

        def evaluate(self) -> float:
            obs, _ = self.envs.reset(seed=seed + 10_000 + len(self.evals))
            returns, alive = np.zeros(episodes), np.ones(episodes, dtype=bool)
            while alive.any():
                action, _ = self.model.predict(obs, deterministic=True)
                obs, reward, terminated, truncated, _ = self.envs.step(action)
                returns += reward * alive
                alive &= ~(terminated | truncated)
            return float(returns.mean())

        def _on_step(self) -> bool:
            if self.num_timesteps % eval_every == 0:
                t0 = time.perf_counter()
                train_seconds = t0 - self.start - self.eval_seconds
                self.evals.append((self.num_timesteps, self.evaluate(), train_seconds))
                self.eval_seconds += time.perf_counter() - t0
            return True

    model = DQN("MlpPolicy", "CartPole-v1", seed=seed, device="cpu", **RL_ZOO_CARTPOLE)
    callback = GreedyEval()
    model.learn(frames, callback=callback)
    return {"hit": first_hit(callback.evals), "final": callback.evals[-1][1]}


def fmt_hit(hit: tuple[int, float] | None) -> tuple[str, str]:
    return ("not reached", "–") if hit is None else (f"{hit[0]:,}", f"{hit[1]:.1f}")


def main() -> None:
    p = budget_parser(__doc__.splitlines()[0], frames=50_000, eval_every=2_000)
    args = p.parse_args()
    rows, ratios, hits = [], [], 0
    for seed in args.seeds:
        ours = run_rlpipe(seed, args.frames, args.eval_every, args.eval_episodes)
        sb3 = run_sb3(seed, args.frames, args.eval_every, args.eval_episodes)
        hits += ours["hit"] is not None
        ratio = "–"
        if ours["hit"] and sb3["hit"]:
            ratios.append(ours["hit"][1] / sb3["hit"][1])
            ratio = f"{ratios[-1]:.2f}"
        rows.append(
            [
                seed,
                *fmt_hit(ours["hit"]),
                f"{ours['final']:.1f}",
                *fmt_hit(sb3["hit"]),
                f"{sb3['final']:.1f}",
                ratio,
            ]
        )
        print(rows[-1], flush=True)
    algo = dataclasses.asdict(ours["config"].algo)
    report = "\n".join(
        [
            "### DQN on CartPole-v1: rlpipe `+experiment=dqn_cartpole` vs SB3 + RL Zoo",
            "",
            machine(["torch", "torchrl", "tensordict", "gymnasium", "stable_baselines3"]),
            "",
            f"{args.frames:,} frames per run; greedy eval of {args.eval_episodes} episodes every "
            f"{args.eval_every:,} frames (eval time excluded from both clocks). Seconds = training "
            "wall time until the eval mean first reaches 500.",
            "",
            table(
                [
                    "seed",
                    "rlpipe frames to 500",
                    "rlpipe s",
                    "rlpipe final",
                    "SB3 frames to 500",
                    "SB3 s",
                    "SB3 final",
                    "wall ratio rlpipe/SB3",
                ],
                rows,
            ),
            "",
            f"rlpipe reached 500 on {hits}/{len(args.seeds)} seeds; mean wall ratio "
            + (f"{np.mean(ratios):.2f}" if ratios else "–")
            + " over the seeds both reached. rlpipe preset: "
            + f"num_envs={ours['config'].env.num_envs}, "
            + ", ".join(f"{k}={v}" for k, v in algo.items() if k not in ("name", *RUN_KEYS)),
        ]
    )
    publish(report, args.append)


if __name__ == "__main__":
    main()
