"""Hand-built runs against the command line: the same preset for the same frames, each timed in a
fresh process, so a run built piece by piece (docs/api.md) trains as fast as ``python -m rlpipe``.

Variants, taking turns within every round (A B C D E A B C D E ...), the rounds alone and then
beside a CPU-bound competitor (``python -c "while True: pass"``):

- command line: ``python -m rlpipe +experiment=dqn_cartpole total_frames=F eval_every=0
  checkpoint_every=0 logger=none progress=false`` (``summary.json``'s ``wall_time``);
- hand-built Runner: the preset's config (``compose_run``), ``DQN(partial(make_env, ...),
  cfg.algo)``, an eval env and a ``Runner`` with no config (the algorithm's record: ``threads``
  auto), as docs/api.md builds one; its ratio is to the command line's;
- command line, resume=: a copy of a finished F-frame run of the preset (trained once, before the
  rounds) extended to 2F frames (``resume=<copy> total_frames=2F``), its last F frames timed;
- load_run + Runner: the same finished run loaded with ``load_run`` (on the run's env copies)
  and trained F frames more by a ``Runner`` in a new dir, as issue 38 fine-tuned by hand: the
  work of the resumed run (a full replay buffer: gradient steps from its first batch), so its
  ratio is to that one's;
- torch's default threads: the hand-built Runner with torch's default threads set back once it
  is built, i.e. what a hand-built run did before the Runner applied ``threads``; its ratio is to
  the command line's (``--no-before`` leaves it out).

Reported: each run's own wall seconds (training and the final evaluation, not the process's
start-up), the median over rounds, and each variant's ratio to its command-line counterpart (the
median of the rounds' ratios). The orchestrating process leaves torch's threads alone: they are
what is measured, in the fresh processes.

    python benchmarks/handbuilt.py --frames 4096 --rounds 3 --append BENCHMARKS.md
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from functools import partial
from pathlib import Path

import torch
from common import busy, machine, publish_section, script, table

from rlpipe import DQN, RunDir, Runner, compose_run, load_run, make_env, seed_everything
from rlpipe.episodes import eval_envs
from rlpipe.runtime import TORCH_THREADS

PRESET = "+experiment=dqn_cartpole"
QUIET = ["eval_every=0", "checkpoint_every=0", "logger=none", "progress=false", "seed=0"]
# variant -> (its name in the table, the command-line variant its ratio is to)
VARIANTS = {
    "cli": ("command line", "cli"),
    "handbuilt": ("hand-built Runner", "cli"),
    "resume": ("command line, resume= (F frames more)", "resume"),
    "load_run": ("load_run + Runner (F frames more)", "resume"),
    "before": ("hand-built Runner, torch's default threads (as before)", "cli"),
}
CONDITIONS = {"alone": False, "beside a busy core": True}


def command_line(frames: int, run_dir: Path, *extra: str) -> float:
    """Wall seconds of ``python -m rlpipe <preset>`` for ``frames`` frames in ``run_dir`` (a
    resumed run's: those after its start)."""
    summary = run_dir / "summary.json"
    before = json.loads(summary.read_text())["wall_time"] if summary.exists() else 0.0
    command = [sys.executable, "-m", "rlpipe", PRESET, f"total_frames={frames}", *QUIET, *extra]
    subprocess.run([*command, f"hydra.run.dir={run_dir}"], check=True, capture_output=True)
    return json.loads(summary.read_text())["wall_time"] - before


def measure(variant: str, frames: int, parent: Path) -> float:
    """In this (fresh) process: build ``variant`` by hand, train ``frames`` frames; its seconds."""
    cfg = compose_run(PRESET, f"total_frames={frames}", *QUIET[:2]).resolved()
    if variant == "load_run":
        loaded = load_run(parent, num_envs=cfg.env.num_envs)
        algo, total = loaded.algo, loaded.algo.frames + frames
    else:
        seed_everything(0)
        algo, total = DQN(partial(make_env, cfg.env, seed=0), cfg.algo), frames
    eval_env = make_env(cfg.env, num_envs=eval_envs(cfg.eval_episodes), seed=10_000)
    with tempfile.TemporaryDirectory() as tmp:
        runner = Runner(
            algo,
            eval_env,
            RunDir(tmp),
            total_frames=total,
            eval_every=0,
            eval_episodes=cfg.eval_episodes,
            checkpoint_every=0,
            progress=False,
        )
        if variant == "before":
            torch.set_num_threads(TORCH_THREADS)
        seconds = runner.run().wall_time
    algo.close()
    eval_env.close()
    return seconds


def run_variant(variant: str, frames: int, parent: Path, scratch: Path) -> float:
    """One timed run of ``variant`` in a fresh process."""
    if variant in ("cli", "resume"):
        with tempfile.TemporaryDirectory(dir=scratch) as tmp:
            if variant == "cli":
                return command_line(frames, Path(tmp) / "run")
            copy = shutil.copytree(parent, Path(tmp) / "run")
            return command_line(2 * frames, copy, f"resume={copy}")
    command = [sys.executable, __file__, "--measure", variant, "--frames", str(frames)]
    done = subprocess.run([*command, "--parent", str(parent)], check=True, capture_output=True)
    return float(done.stdout.decode().strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=4096)
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds per condition")
    p.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    p.add_argument("--no-before", action="store_true", help="leave the default-threads run out")
    p.add_argument("--append", type=Path, help="put the section into this Markdown file")
    p.add_argument("--measure", choices=VARIANTS, help=argparse.SUPPRESS)  # one timed run
    p.add_argument("--parent", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.measure:
        print(measure(args.measure, args.frames, args.parent))
        return
    variants = [v for v in VARIANTS if not (args.no_before and v == "before")]
    walls: dict[tuple[str, str], list[float]] = {}
    loads: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        scratch = Path(tmp)
        command_line(args.frames, scratch / "parent")  # the run load_run continues
        for condition in args.conditions:
            loads[condition] = [os.getloadavg()[0]]
            with busy(CONDITIONS[condition]):
                for _ in range(args.rounds):
                    for variant in variants:
                        seconds = run_variant(variant, args.frames, scratch / "parent", scratch)
                        walls.setdefault((condition, variant), []).append(seconds)
            loads[condition].append(os.getloadavg()[0])
    rows = []
    for condition in args.conditions:
        for variant in variants:
            name, counterpart = VARIANTS[variant]
            own = walls[condition, variant]
            ratio = statistics.median(a / b for a, b in zip(own, walls[condition, counterpart]))
            rounds = ", ".join(f"{w:.1f}" for w in own)
            name = name.replace("F frames", f"{args.frames:,} frames")
            rows.append([condition, name, f"{statistics.median(own):.1f}", rounds, f"{ratio:.2f}"])
    load_text = "; ".join(f"{c}: {a:.2f} before, {b:.2f} after" for c, (a, b) in loads.items())
    text = "\n".join(
        [
            "## Hand-built runs against the command line (benchmarks/handbuilt.py)",
            "",
            f"- machine: {machine(['torch', 'torchrl', 'envpool'])}",
            f"- command: `python benchmarks/handbuilt.py --frames {args.frames} --rounds "
            f"{args.rounds}`; 1-min load average {load_text}",
            f"- `{PRESET}` for {args.frames:,} frames (`{' '.join(QUIET[:4])}`), every run in a "
            "fresh process, the variants taking turns within each round; seconds: the run's own "
            "(training and the final evaluation), median over rounds; ratio: the median of the "
            "rounds' ratios to the command line doing the same work (a fresh run; for load_run "
            "+ Runner, a finished run extended with resume=, whose replay buffer is full too)",
            "",
            table(["condition", "variant", "seconds", "each round", "÷ command line"], rows),
        ]
    )
    publish_section(text, args.append)


if __name__ == "__main__":
    script(main)
