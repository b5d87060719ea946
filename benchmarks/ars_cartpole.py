"""ARS on CartPole-v1 with the notebook's defaults (``algo=ars env=cartpole``): frames and
seconds until the greedy eval reaches 500.

    python benchmarks/ars_cartpole.py --append BENCHMARKS.md
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from ars_bipedal import curve_report, learning_curve
from common import budget_parser, publish


def main() -> None:
    p = budget_parser(__doc__.splitlines()[0], frames=200_000, eval_every=10_000)
    args = p.parse_args()
    for seed in args.seeds:
        overrides = [
            "algo=ars",
            "env=cartpole",
            f"seed={seed}",
            f"total_frames={args.frames}",
            f"eval_every={args.eval_every}",
            f"eval_episodes={args.eval_episodes}",
            "checkpoint_every=0",
            "progress=false",
        ]
        with tempfile.TemporaryDirectory() as tmp:
            rows, result = learning_curve(overrides, Path(tmp))
        note = (
            f"`python -m rlpipe {' '.join(overrides)}` · final {result.eval_mean:.1f} · "
            f"greedy eval of {args.eval_episodes} episodes every {args.eval_every:,} frames"
        )
        title = f"### ARS on CartPole-v1 (notebook defaults, seed {seed})"
        publish(curve_report(title, rows, 500.0, note), args.append)


if __name__ == "__main__":
    main()
