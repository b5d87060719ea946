"""The main job as typed, ``python -m rlpipe algo=ars env=bipedal``, alone and beside a busy
process, in one run: minutes, frames and the final 100-episode greedy mean per seed.

Each run is the command a user types (plus ``seed=<s>``, ``progress=false`` and a run dir of its
own), in a subprocess; the competitor is ``python -c 'while True: pass'``, spinning one of the
machine's cores for the whole run. The two conditions take turns (the busy one first on every
other seed), so slow phases of the machine hit them alike. Per run: the process's wall time
(start-up included), the run's own (``summary.json``), the frames, and the final greedy mean of
``python -m rlpipe.evaluate run_dir=<dir> episodes=100`` on the starts benchmarks/presets.py's
final evals meet (not timed), against the job's target of 300.

    python benchmarks/main_job.py --seeds 100 --append BENCHMARKS.md
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import busy, evaluated, load_span, parser, publish_section, script, section_head, table

from rlpipe.episodes import FINAL, episodes_seed

COMMAND = ["-m", "rlpipe", "algo=ars", "env=bipedal"]
CONDITIONS = ("alone", "beside a busy process")
TARGET = 300.0  # BipedalWalker-v3's "solved", on the final 100-episode greedy mean


def run_job(seed: int, run_dir: Path, overrides: list[str], episodes: int) -> dict:
    """One main job in a subprocess, then its final greedy eval: the process's seconds, the
    run's summary (``wall_time``, ``frames``), its first console line and the final mean."""
    command = [sys.executable, *COMMAND, f"seed={seed}", "progress=false"]
    command += [f"hydra.run.dir={run_dir}", *overrides]
    start = time.perf_counter()
    proc = subprocess.run(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    process_s = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"main_job: `{' '.join(command[1:])}` failed: {proc.stdout.strip()}")
    summary = json.loads((run_dir / "summary.json").read_text())
    keys = [f"run_dir={run_dir}", f"episodes={episodes}", f"seed={episodes_seed(seed, FINAL)}"]
    final = evaluated(run_dir / "final.json", *keys)["return_mean"]
    first = next(line for line in proc.stdout.splitlines() if line.startswith("rlpipe:"))
    return {**summary, "process_s": process_s, "final": final, "first_line": first}


def rows_of(results: dict[tuple[int, str], dict]) -> list[list[str]]:
    """A row per seed and condition, with its process time over the lone run's (1.00× for
    the lone run itself)."""
    rows = []
    for (seed, condition), r in sorted(results.items()):
        alone = results.get((seed, CONDITIONS[0]))
        ratio = f"{r['process_s'] / alone['process_s']:.2f}×" if alone else "–"
        solved = "✓" if r["final"] >= TARGET else "✗"
        rows.append(
            [
                str(seed),
                condition,
                f"{r['process_s'] / 60:.1f}",
                f"{r['wall_time'] / 60:.1f}",
                f"{r['frames']:,}",
                f"{r['final']:.1f} {solved}",
                ratio,
            ]
        )
    return rows


def main() -> None:
    p = parser(__doc__.splitlines()[0], seeds="100")
    p.set_defaults(seeds=[100])
    p.add_argument("--episodes", type=int, default=100, help="the final greedy eval's episodes")
    p.add_argument("--override", nargs="*", default=[], help="added to every run (tests: budgets)")
    args = p.parse_args()
    load_before = os.getloadavg()
    results: dict[tuple[int, str], dict] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for i, seed in enumerate(args.seeds):
            for condition in CONDITIONS[:: 1 if i % 2 == 0 else -1]:
                run_dir = Path(tmp) / f"seed{seed}-{CONDITIONS.index(condition)}"
                with busy(condition != CONDITIONS[0]):
                    results[seed, condition] = run_job(seed, run_dir, args.override, args.episodes)
                print(f"main_job: seed {seed}, {condition}: done", file=sys.stderr)
    first = next(iter(results.values()))["first_line"]
    typed = " ".join(["python", *COMMAND, *args.override])
    head = section_head(
        "The main job as typed, alone and beside a busy process",
        ["torch", "torchrl", "gymnasium", "envpool"],
        load_span(load_before, os.getloadavg()),
        f"each run: `{typed} seed=<s> progress=false hydra.run.dir=<tmp>`; its first line: "
        f"`{first}`",
        "the competitor: `python -c 'while True: pass'`, started before the run, killed after",
        f"final: `python -m rlpipe.evaluate run_dir=<run> episodes={args.episodes}` "
        f"(not timed); ✓: at least {TARGET:g}",
    )
    headers = ["seed", "condition", "process min", "run min", "frames", "final", "vs alone"]
    report = "\n".join([*head, table(headers, rows_of(results))])
    publish_section(report, args.append)


if __name__ == "__main__":
    script(main)
