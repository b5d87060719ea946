"""REINFORCE on the notebook's continuous CartPole: rlpipe vs the notebook's loop, plus
REINFORCE on CartPole-v1 and ARS on the continuous CartPole.

Everything runs in this process, one run after the other, with ``torch.set_num_threads(1)``
(the networks are tiny; on a shared 2-core machine more threads only contend).

1. Continuous CartPole, 50-step horizon, the notebook's hyper-parameters: rlpipe's
   ``algo=reinforce env=cartpole_continuous`` and ``reference_reinforce.py`` (a faithful port of
   the notebook's loop), each for ``--epochs`` epochs; after every epoch ``--eval-episodes``
   greedy episodes. Reported per seed: the first epoch whose eval mean is 50 (the horizon) and
   the training seconds to it, the training seconds of all epochs, the wall ratio, and the
   training seconds per frame of the training episodes (rlpipe's idle copies, stepped until
   the batch's longest episode ends, cost time but add no episode frames).
2. ``algo=reinforce env=cartpole`` (CartPole-v1) with ``--discrete`` overrides: frames and
   training seconds until the greedy eval mean first reaches 475 (eval after every epoch).
3. ``algo=ars env=cartpole_continuous`` (when the ARS algorithm is registered): frames and
   training seconds until the greedy eval mean first reaches 50 (eval after every iteration).

Evaluation time is excluded from every clock.

    python benchmarks/reinforce_cartpole.py --append BENCHMARKS.md
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from common import compose_config, machine, parser, publish, table
from reference_reinforce import run as run_reference

from rlpipe.algos import ALGORITHMS, make_algorithm
from rlpipe.envs import make_env
from rlpipe.evaluation import evaluate
from rlpipe.train import seed_everything

HORIZON = 50.0
DISCRETE_TARGET = 475.0
DISCRETE = [
    "env.num_envs=16",
    "algo.hidden_sizes=[64]",
    "algo.episodes_per_epoch=32",
    "algo.lr=3e-3",
]


def train_with_evals(
    overrides: list[str], seed: int, episodes: int, max_steps: int, target: float | None = None
) -> list[dict]:
    """Train step by step with a greedy eval after each; one row per step (stops at ``target``)."""
    cfg = compose_config(*overrides, f"seed={seed}")
    seed_everything(seed)
    env = make_env(cfg.env, seed=seed)
    eval_env = make_env(cfg.env, num_envs=min(episodes, 32), seed=seed + 10_000)
    algo = make_algorithm(env, cfg.algo)
    rows, seconds, episode_frames = [], 0.0, 0
    try:
        for step in range(max_steps):
            start = time.perf_counter()
            metrics = algo.train_step()
            seconds += time.perf_counter() - start
            episode_frames += int(sum(metrics.get("train/episode_length", [])))
            mean = evaluate(algo.policy, eval_env, episodes).mean
            rows.append(
                {
                    "epoch": step + 1,
                    "eval": mean,
                    "frames": algo.frames,
                    "episode_frames": episode_frames,
                    "seconds": seconds,
                }
            )
            if target is not None and mean >= target:
                break
    finally:
        algo.close()
        eval_env.close()
    return rows


def first_hit(rows: list[dict], target: float) -> dict | None:
    return next((r for r in rows if r["eval"] >= target - 1e-6), None)


def hit_cells(hit: dict | None, unit: str) -> list[str]:
    if hit is None:
        return ["not reached", "–"]
    return [f"{hit[unit]:,}", f"{hit['seconds']:.1f}"]


def rows_to_target(
    overrides: list[str], args: argparse.Namespace, iterations: int, target: float
) -> list[list[object]]:
    """Per seed: frames and seconds until the greedy eval reaches ``target``, and the last eval."""
    rows = []
    for seed in args.seeds:
        runs = train_with_evals(overrides, seed, args.eval_episodes, iterations, target)
        rows.append(
            [seed, *hit_cells(first_hit(runs, target), "frames"), f"{runs[-1]['eval']:.1f}"]
        )
        print(rows[-1], flush=True)
    return rows


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--discrete-epochs", type=int, default=150, help="cap for CartPole-v1")
    p.add_argument("--ars-iterations", type=int, default=300, help="cap for ARS")
    args = p.parse_args()
    torch.set_num_threads(1)
    continuous = ["algo=reinforce", "env=cartpole_continuous"]
    rows, ratios, cost_ratios = [], [], []
    for seed in args.seeds:
        ours = train_with_evals(continuous, seed, args.eval_episodes, args.epochs)
        ref = run_reference(seed, epochs=args.epochs, test_episodes=args.eval_episodes)
        ratios.append(ours[-1]["seconds"] / ref[-1]["seconds"])
        # the reference's frames are its episodes' frames: it never steps past an episode's end
        cost = [
            ours[-1]["seconds"] / ours[-1]["episode_frames"],
            ref[-1]["seconds"] / ref[-1]["frames"],
        ]
        cost_ratios.append(cost[0] / cost[1])
        rows.append(
            [
                seed,
                *hit_cells(first_hit(ours, HORIZON), "epoch"),
                f"{ours[-1]['eval']:.1f}",
                f"{ours[-1]['seconds']:.1f}",
                *hit_cells(first_hit(ref, HORIZON), "epoch"),
                f"{ref[-1]['eval']:.1f}",
                f"{ref[-1]['seconds']:.1f}",
                f"{ratios[-1]:.2f}",
                f"{cost[0] * 1e6:.0f} / {cost[1] * 1e6:.0f} = {cost_ratios[-1]:.2f}",
            ]
        )
        print(rows[-1], flush=True)
    discrete_rows = rows_to_target(
        ["algo=reinforce", "env=cartpole", *DISCRETE], args, args.discrete_epochs, DISCRETE_TARGET
    )
    ars_rows = []
    if "ars" in ALGORITHMS:
        ars_rows = rows_to_target(
            ["algo=ars", "env=cartpole_continuous"], args, args.ars_iterations, HORIZON
        )
    cfg = compose_config(*continuous)
    report = [
        "### REINFORCE on the notebook's continuous CartPole: rlpipe vs the notebook's loop",
        "",
        machine(["torch", "torchrl", "tensordict", "gymnasium"]),
        "",
        f"`python -m rlpipe algo=reinforce env=cartpole_continuous` settings (num_envs="
        f"{cfg.env.num_envs}, horizon {cfg.env.max_episode_steps}) and "
        "`benchmarks/reference_reinforce.py`, same seeds, "
        f"{args.epochs} epochs of {cfg.algo.episodes_per_epoch} episodes, "
        f"{args.eval_episodes} greedy eval episodes after each epoch (eval time excluded). "
        "One torch thread.",
        "",
        table(
            [
                "seed",
                "rlpipe epoch to 50",
                "rlpipe s to 50",
                f"rlpipe eval @{args.epochs}",
                f"rlpipe s / {args.epochs} epochs",
                "notebook epoch to 50",
                "notebook s to 50",
                f"notebook eval @{args.epochs}",
                f"notebook s / {args.epochs} epochs",
                "wall ratio rlpipe/notebook",
                "µs per episode frame rlpipe / notebook",
            ],
            rows,
        ),
        "",
        f"Mean wall ratio over {args.epochs} epochs: {np.mean(ratios):.2f}; mean cost ratio per "
        f"episode frame: {np.mean(cost_ratios):.2f} (training seconds / frames of the training "
        "episodes; the wall time of a fixed number of epochs grows with the episodes' length).",
        "",
        f"REINFORCE on CartPole-v1 (`algo=reinforce env=cartpole {' '.join(DISCRETE)}`), greedy "
        f"eval after every epoch, at most {args.discrete_epochs} epochs:",
        "",
        table(["seed", "frames to 475", "s to 475", "last eval"], discrete_rows),
    ]
    if ars_rows:
        report += [
            "",
            "ARS on the continuous CartPole (`algo=ars env=cartpole_continuous`, its defaults), "
            f"greedy eval after every iteration, at most {args.ars_iterations} iterations:",
            "",
            table(["seed", "frames to 50", "s to 50", "last eval"], ars_rows),
        ]
    publish("\n".join(report), args.append)


if __name__ == "__main__":
    main()
