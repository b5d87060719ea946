"""Sample efficiency of model-based RL: env frames and training seconds until the greedy eval
reaches a target, MBRL side by side with ARS and REINFORCE on the same envs and seeds.

- Pendulum-v1, target: mean return >= -250 over ``--eval-episodes`` (10) greedy episodes.
  MBRL: ``+experiment=mbrl_pendulum`` (the algo defaults), evaluated every ``--pendulum-eval``
  frames up to ``--pendulum-frames``; ARS (``algo.workers=1``) and REINFORCE
  (``env.num_envs=10``: 10 episodes stepped as one batch) with their defaults (``~tuned``: not
  the presets an algo x env pair picks by itself), evaluated after
  every iteration/epoch up to ``--baseline-frames``.
- The notebook's continuous CartPole (50-step horizon), target 50: MBRL
  ``+experiment=mbrl_cartpole`` evaluated every ``--cartpole-eval`` frames up to
  ``--cartpole-frames``; ARS and REINFORCE with their defaults (as ``reinforce_cartpole.py``).

Everything runs in this process, one run after the other, with ``torch.set_num_threads(1)``.
Seconds are training seconds (evaluation excluded: MBRL's greedy eval plans at every step and
costs far more than its training; its mean eval seconds are reported separately).

    python benchmarks/mbrl_sample_efficiency.py --append BENCHMARKS.md
"""

from __future__ import annotations

import os
import time

import common
import torch
from common import first_hit, hit_cells, parser, script, table, train_with_evals

PENDULUM_TARGET = -250.0
CARTPOLE_TARGET = 50.0
NO_CAP = 10**9  # train steps: the frame caps end the runs


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--pendulum-frames", type=int, default=15_000)
    p.add_argument("--pendulum-eval", type=int, default=1_000)
    p.add_argument("--cartpole-frames", type=int, default=5_000)
    p.add_argument("--cartpole-eval", type=int, default=250)
    p.add_argument("--baseline-frames", type=int, default=200_000)
    args = p.parse_args()
    torch.set_num_threads(1)
    load_before = os.getloadavg()
    runs = [
        # (env, target, algorithm label, overrides, eval_every, max_frames)
        ("Pendulum-v1", PENDULUM_TARGET, "MBRL (CEM)", ["+experiment=mbrl_pendulum"],
         args.pendulum_eval, args.pendulum_frames),
        ("Pendulum-v1", PENDULUM_TARGET, "ARS",
         ["algo=ars", "env=pendulum", "~tuned", "algo.workers=1"], 0, args.baseline_frames),
        ("Pendulum-v1", PENDULUM_TARGET, "REINFORCE",
         ["algo=reinforce", "env=pendulum", "~tuned", "env.num_envs=10"], 0, args.baseline_frames),
        ("continuous CartPole", CARTPOLE_TARGET, "MBRL (CEM)", ["+experiment=mbrl_cartpole"],
         args.cartpole_eval, args.cartpole_frames),
        ("continuous CartPole", CARTPOLE_TARGET, "ARS",
         ["algo=ars", "env=cartpole_continuous", "~tuned", "algo.workers=1"],
         0, args.baseline_frames),
        ("continuous CartPole", CARTPOLE_TARGET, "REINFORCE",
         ["algo=reinforce", "env=cartpole_continuous", "~tuned"], 0, args.baseline_frames),
    ]  # fmt: skip
    rows = []
    for env_name, target, label, overrides, eval_every, max_frames in runs:
        for seed in args.seeds:
            start = time.perf_counter()
            evals = train_with_evals(
                overrides,
                seed,
                args.eval_episodes,
                NO_CAP,
                target,
                eval_every=eval_every,
                max_frames=max_frames,
            )
            wall = time.perf_counter() - start
            eval_seconds = (wall - evals[-1]["seconds"]) / len(evals)
            rows.append(
                [
                    env_name,
                    label,
                    seed,
                    *hit_cells(first_hit(evals, target), "frames"),
                    f"{evals[-1]['eval']:.1f}",
                    f"{evals[-1]['frames']:,}",
                    f"{eval_seconds:.1f}",
                ]
            )
            print(rows[-1], flush=True)
    head = common.section_head(
        "MBRL sample efficiency: frames and seconds to a target, vs ARS and REINFORCE",
        ["torch", "torchrl", "tensordict", "gymnasium"],
        common.load_span(load_before, os.getloadavg()),
    )
    report = [
        *head,
        f"Targets Pendulum-v1 >= {PENDULUM_TARGET:.0f} and continuous CartPole (50-step "
        f"horizon) {CARTPOLE_TARGET:.0f}, mean of {args.eval_episodes} greedy episodes. MBRL is "
        f"evaluated every {args.pendulum_eval:,} (Pendulum) / {args.cartpole_eval:,} (CartPole) "
        "frames, ARS and REINFORCE after every iteration/epoch; runs stop at the target or the "
        f"frame cap (MBRL {args.pendulum_frames:,} / {args.cartpole_frames:,}, others "
        f"{args.baseline_frames:,}). Seconds: training only, one torch thread.",
        "",
        table(
            [
                "env",
                "algorithm",
                "seed",
                "frames to target",
                "train s to target",
                "last eval",
                "frames run",
                "s per eval",
            ],
            rows,
        ),
    ]
    common.publish_section("\n".join(report), args.append)


if __name__ == "__main__":
    script(main)
