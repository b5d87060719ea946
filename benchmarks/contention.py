"""Thread contention: the default ``python -m rlpipe`` run against ``threads=1`` and ``threads=2``,
each alone and beside a CPU-bound competitor process, in one run.

Every run is a real ``python -m rlpipe`` subprocess (the default DQN on CartPole-v1, a short
frame budget, no logger, no checkpoints); the competitor is another Python process spinning one
core. Settings take turns within each round, so slow phases of the machine hit them alike.
Reported: the run's own wall seconds (training and the final evaluation; ``summary.json``),
median over rounds, and each setting's ratio to the fastest setting in the same condition.

    python benchmarks/contention.py --frames 4000 --rounds 2 --append BENCHMARKS.md
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from common import busy, load_span, publish_section, script, section_head, table

SETTINGS = {"default (threads=auto)": [], "threads=1": ["threads=1"], "threads=2": ["threads=2"]}
CONDITIONS = ("alone", "beside a CPU-bound process")
TARGET = 1.15  # the default within this factor of the best setting, in both conditions


def run_once(frames: int, overrides: list[str]) -> float:
    """Wall seconds of one default run (``summary.json``'s ``wall_time``)."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            sys.executable,
            "-m",
            "rlpipe",
            f"total_frames={frames}",
            "eval_every=0",
            "checkpoint_every=0",
            "logger=none",
            "progress=false",
            f"hydra.run.dir={tmp}",
            *overrides,
        ]
        subprocess.run(command, check=True, capture_output=True, env=os.environ.copy())
        return json.loads((Path(tmp) / "summary.json").read_text())["wall_time"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=4000)
    p.add_argument("--rounds", type=int, default=2, help="interleaved rounds per condition")
    p.add_argument("--append", type=Path, help="put the section into this Markdown file")
    args = p.parse_args()
    walls: dict[tuple[str, str], list[float]] = {}
    load_before = os.getloadavg()
    for condition in CONDITIONS:
        with busy(condition != "alone"):
            for _ in range(args.rounds):
                for name, overrides in SETTINGS.items():
                    walls.setdefault((condition, name), []).append(run_once(args.frames, overrides))
    rows, verdicts = [], []
    for condition in CONDITIONS:
        medians = {name: statistics.median(walls[condition, name]) for name in SETTINGS}
        best = min(medians.values())
        for name, median in medians.items():
            runs = ", ".join(f"{w:.1f}" for w in walls[condition, name])
            rows.append([condition, name, f"{median:.1f}", runs, f"{median / best:.2f}×"])
        ratio = medians["default (threads=auto)"] / best
        verdicts.append(f"{condition}: default / best = {ratio:.2f} (target ≤ {TARGET})")
    head = section_head(
        "Thread contention: the default run beside a busy core",
        ["torch", "torchrl"],
        load_span(load_before, os.getloadavg()),
    )
    report = "\n".join(
        [
            *head,
            f"`python -m rlpipe total_frames={args.frames} eval_every=0 checkpoint_every=0 "
            f"logger=none progress=false [threads=N]` (DQN on CartPole-v1), {args.rounds} "
            "interleaved round(s) per condition; the competitor is `python -c 'while True: "
            "pass'`. Wall = the run's own seconds (training and the final evaluation), median "
            "over rounds.",
            "",
            table(["condition", "setting", "wall s", "each round", "vs best"], rows),
            "",
            *[f"- {line}" for line in verdicts],
        ]
    )
    publish_section(report, args.append)


if __name__ == "__main__":
    script(main)
