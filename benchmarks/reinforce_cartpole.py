"""REINFORCE on the notebook's continuous CartPole: rlpipe vs the notebook's loop, plus
REINFORCE on CartPole-v1 and ARS on the continuous CartPole.

Everything runs in this process, one run after the other, with ``torch.set_num_threads(1)``
(the networks are tiny; on a shared 2-core machine more threads only contend).

1. Continuous CartPole, 50-step horizon: ``reference_reinforce.py`` (a faithful port of the
   notebook's loop) and two rlpipe settings, ``algo=reinforce env=cartpole_continuous ~tuned``
   (the notebook's hyper-parameters, not the preset the pair picks by itself) and
   ``+experiment=reinforce_cartpole`` (the tuned preset: a learned value baseline), each for
   ``--epochs`` epochs; after every epoch ``--eval-episodes`` greedy episodes. Reported per
   setting and seed, each against the reference run of that seed: the first epoch whose eval
   mean is 50 (the horizon) and the training seconds to it, the training seconds of all epochs,
   the wall ratio, the time-to-50 ratio (rlpipe's seconds to 50 over the reference's, or over
   all of the reference's seconds when it never reaches 50), and the training seconds per frame
   of the training episodes (rlpipe's idle copies, stepped until the batch's longest episode
   ends, cost time but add no episode frames).
2. ``algo=reinforce env=cartpole`` (CartPole-v1) with ``--discrete`` overrides: frames and
   training seconds until the greedy eval mean first reaches 475 (eval after every epoch).
3. ``algo=ars env=cartpole_continuous`` (when the ARS algorithm is registered): frames and
   training seconds until the greedy eval mean first reaches 50 (eval after every iteration).

Evaluation time is excluded from every clock.

    python benchmarks/reinforce_cartpole.py --append BENCHMARKS.md
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import torch
from common import (
    compose_run,
    first_hit,
    hit_cells,
    load_span,
    parser,
    publish_section,
    script,
    section_head,
    table,
    train_with_evals,
)
from reference_reinforce import run as run_reference

from rlpipe.algos import ALGORITHMS

HORIZON = 50.0
CONTINUOUS = {
    "notebook defaults": ["algo=reinforce", "env=cartpole_continuous", "~tuned"],
    "preset": ["+experiment=reinforce_cartpole"],
}
DISCRETE_TARGET = 475.0
DISCRETE = [
    "env.num_envs=16",
    "algo.hidden_sizes=[64]",
    "algo.episodes_per_epoch=32",
    "algo.lr=3e-3",
]


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


def time_to_50_ratio(ours: list[dict], ref: list[dict]) -> float | None:
    """rlpipe's seconds to 50 over the reference's (all its seconds if it never gets there)."""
    hit, ref_hit = first_hit(ours, HORIZON), first_hit(ref, HORIZON)
    if hit is None:
        return None
    return hit["seconds"] / (ref_hit or ref[-1])["seconds"]


def continuous_row(setting: str, seed: int, ours: list[dict], ref: list[dict]) -> list[object]:
    """One table row: an rlpipe run against the reference run of the same seed."""
    # the reference's frames are its episodes' frames: it never steps past an episode's end
    cost = [
        ours[-1]["seconds"] / ours[-1]["episode_frames"],
        ref[-1]["seconds"] / ref[-1]["frames"],
    ]
    to_50 = time_to_50_ratio(ours, ref)
    return [
        setting,
        seed,
        *hit_cells(first_hit(ours, HORIZON), "epoch"),
        f"{ours[-1]['eval']:.1f}",
        f"{ours[-1]['seconds']:.1f}",
        *hit_cells(first_hit(ref, HORIZON), "epoch"),
        f"{ref[-1]['eval']:.1f}",
        f"{ref[-1]['seconds']:.1f}",
        f"{ours[-1]['seconds'] / ref[-1]['seconds']:.2f}",
        "–" if to_50 is None else f"{to_50:.2f}",
        f"{cost[0] * 1e6:.0f} / {cost[1] * 1e6:.0f} = {cost[0] / cost[1]:.2f}",
    ]


def summary(setting: str, runs: list[list[dict]], refs: list[list[dict]]) -> str:
    """How many seeds reached the horizon, the mean wall ratio and the worst time-to-50 ratio
    of one rlpipe setting."""
    reached = sum(first_hit(ours, HORIZON) is not None for ours in runs)
    ratio = np.mean([ours[-1]["seconds"] / ref[-1]["seconds"] for ours, ref in zip(runs, refs)])
    to_50 = [time_to_50_ratio(ours, ref) for ours, ref in zip(runs, refs)]
    worst = "–" if None in to_50 else f"{max(to_50):.2f}"
    return (
        f"- {setting}: reached 50 within the epochs on {reached}/{len(runs)} seeds; mean wall "
        f"ratio rlpipe/notebook {ratio:.2f}; worst time-to-50 ratio {worst}."
    )


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--epochs", type=int, default=20)
    p.add_argument("--eval-episodes", type=int, default=20)
    p.add_argument("--discrete-epochs", type=int, default=150, help="cap for CartPole-v1")
    p.add_argument("--ars-iterations", type=int, default=300, help="cap for ARS")
    args = p.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    refs = [
        run_reference(seed, epochs=args.epochs, test_episodes=args.eval_episodes)
        for seed in args.seeds
    ]
    rows, summaries = [], []
    for setting, overrides in CONTINUOUS.items():
        runs = [
            train_with_evals(overrides, seed, args.eval_episodes, args.epochs)
            for seed in args.seeds
        ]
        for seed, ours, ref in zip(args.seeds, runs, refs):
            rows.append(continuous_row(setting, seed, ours, ref))
            print(rows[-1], flush=True)
        summaries.append(summary(setting, runs, refs))
    discrete_rows = rows_to_target(
        ["algo=reinforce", "env=cartpole", *DISCRETE], args, args.discrete_epochs, DISCRETE_TARGET
    )
    ars_rows = []
    if "ars" in ALGORITHMS:
        ars_rows = rows_to_target(
            ["algo=ars", "env=cartpole_continuous"], args, args.ars_iterations, HORIZON
        )
    cfg = compose_run(*CONTINUOUS["notebook defaults"])
    preset = compose_run(*CONTINUOUS["preset"]).algo
    head = section_head(
        "REINFORCE on the notebook's continuous CartPole: rlpipe vs the notebook's loop",
        ["torch", "torchrl", "tensordict", "gymnasium"],
        load_span(load_before, os.getloadavg()),
    )
    report = [
        *head,
        f"`benchmarks/reference_reinforce.py` and `python -m rlpipe algo=reinforce "
        f"env=cartpole_continuous ~tuned` (notebook defaults; num_envs={cfg.env.num_envs}, horizon "
        f"{cfg.env.max_episode_steps}) or `+experiment=reinforce_cartpole` (preset: "
        f"baseline={preset.baseline}, lr={preset.lr}, value_lr={preset.value_lr}, "
        f"value_hidden_sizes={preset.value_hidden_sizes}), same seeds, {args.epochs} epochs of "
        f"{cfg.algo.episodes_per_epoch} episodes, {args.eval_episodes} greedy eval episodes "
        "after each epoch (eval time excluded); each rlpipe row against the reference run of "
        "its seed. One torch thread.",
        "",
        table(
            [
                "rlpipe setting",
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
                "time-to-50 ratio rlpipe/notebook",
                "µs per episode frame rlpipe / notebook",
            ],
            rows,
        ),
        "",
        *summaries,
        "",
        "The wall time of a fixed number of epochs grows with the episodes' length; rlpipe "
        "steps all copies until the epoch's longest episode ends.",
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
    publish_section("\n".join(report), args.append)


if __name__ == "__main__":
    script(main)
