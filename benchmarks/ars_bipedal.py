"""ARS on BipedalWalker-v3: the long run of ``+experiment=ars_bipedal`` and its learning curve.

Trains the preset (greedy evaluation of ``eval_episodes`` episodes every ``eval_every`` frames;
the preset's 100 episodes make every row a 100-episode mean) and prints eval return against
frames, training minutes (evaluation excluded) and wall minutes (evaluation included), and the
first evaluation reaching the target. The run directory (metrics, checkpoints) is kept.

    nohup python benchmarks/ars_bipedal.py --append BENCHMARKS.md > ars_bipedal.log 2>&1 &
    python benchmarks/ars_bipedal.py total_frames=200000 eval_every=100000 eval_episodes=4  # smoke
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from common import (
    compose_run,
    load_span,
    parser,
    publish_section,
    read_scalar,
    section_head,
    table,
)

from rlpipe.pipeline import train

TARGET = 300.0


def learning_curve(overrides: list[str], run_dir: Path) -> tuple[list[list[object]], object]:
    """Train ``python -m rlpipe <overrides>`` into ``run_dir``; one row per evaluation."""
    cfg = compose_run(*overrides)
    result = train(cfg, run_dir)
    means = read_scalar(run_dir, "eval/return_mean")
    stds = read_scalar(run_dir, "eval/return_std")
    train_seconds = read_scalar(run_dir, "time/train_seconds")
    eval_seconds = read_scalar(run_dir, "time/eval_seconds")
    rows, evaluated = [], 0.0
    for (frames, mean), (_, std), (_, trained), (_, spent) in zip(
        means, stds, train_seconds, eval_seconds
    ):
        evaluated += spent
        rows.append([frames, mean, std, trained, trained + evaluated])
    return rows, result


def curve_report(rows: list[list[object]], target: float, note: str) -> list[str]:
    """One run's part of the section: what ran, its learning-curve table and the first
    evaluation reaching ``target``."""
    hit = next((row for row in rows if row[1] >= target), None)
    reached = (
        f"first eval ≥ {target:g}: {hit[0]:,} frames, {hit[3]:.1f} s training, {hit[4]:.1f} s wall"
        if hit
        else f"eval mean never reached {target:g}"
    )
    cells = [[f"{f:,}", f"{m:.1f}", f"{s:.1f}", f"{t:.1f}", f"{w:.1f}"] for f, m, s, t, w in rows]
    headers = ["frames", "eval mean", "eval std", "train s", "wall s"]
    return [note, "", table(headers, cells), "", reached, ""]


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("overrides", nargs="*", help="extra Hydra overrides, e.g. total_frames=1e6")
    p.add_argument("--run-dir", type=Path, help="default: outputs/ars_bipedal/<time>")
    p.set_defaults(seeds=[1])
    args = p.parse_args()
    start, parts = os.getloadavg(), []
    for seed in args.seeds:
        run_dir = args.run_dir or Path("outputs/ars_bipedal") / time.strftime("%Y-%m-%d_%H-%M-%S")
        overrides = ["+experiment=ars_bipedal", f"seed={seed}", "progress=false", *args.overrides]
        rows, result = learning_curve(overrides, run_dir)
        note = (
            f"**seed {seed}**: `python -m rlpipe {' '.join(overrides)}` · final "
            f"{result.eval_mean:.1f} ± {result.eval_std:.1f} over {result.eval_episodes} "
            f"episodes · {result.frames:,} frames · {result.wall_time / 60:.1f} min · run dir "
            f"{run_dir}"
        )
        parts += curve_report(rows, TARGET, note)
    head = section_head(
        "ARS on BipedalWalker-v3 (`+experiment=ars_bipedal`)",
        ["torch", "torchrl", "gymnasium"],
        load_span(start, os.getloadavg()),
    )
    publish_section("\n".join(head + parts), args.append)


if __name__ == "__main__":
    main()
