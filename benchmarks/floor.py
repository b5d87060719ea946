"""rlpipe's training time against the floor: a hand-written PyTorch loop doing the same work
(``benchmarks/floor_loops.py``), per preset, interleaved in one run, quiet and beside a busy
process.

Each measurement is a fresh process training ``--frames`` frames of the preset on seed 0, one
torch thread: the floor's loop, or ``rlpipe.train`` (``eval_every=0``: its training seconds
exclude the final evaluation, as ``time/train_seconds`` records them). Rounds alternate the order
(floor, rlpipe / rlpipe, floor); the table gives medians, their ratio, the ratio within each
round (the machine's drift between rounds cancels), the work each did (env steps, gradient
steps, minibatch rows) and each process's peak RSS. ``--learn`` also trains each floor for the
preset's whole budget and evaluates it greedily: the floor's maths is no stub.
``--compile`` also times rlpipe with ``compile=true`` in the same rounds (its seconds include
compiling) and reports the seconds torch spent compiling.

    python benchmarks/floor.py [--presets dqn_cartpole sac_pendulum ppo_cartpole] [--rounds 3]
        [--learn] [--compile] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import busy, machine, publish_section, script, table

# frames timed per preset (the preset's own budget is its learning check's)
FRAMES = {"dqn_cartpole": 20_000, "sac_pendulum": 5_000, "ppo_cartpole": 20_480}
BUDGETS = {"dqn_cartpole": 50_000, "sac_pendulum": 20_000, "ppo_cartpole": 100_000}
TARGETS = {"dqn_cartpole": 475.0, "sac_pendulum": -157.0, "ppo_cartpole": 475.0}
BATCH = {"dqn_cartpole": 256, "sac_pendulum": 256, "ppo_cartpole": 512}  # rows per step


def child(kind: str, preset: str, frames: int, seed: int, learn: bool) -> dict:
    """One measurement in this process: seconds of training, the work done, peak RSS."""
    import torch

    torch.set_num_threads(1)
    if kind == "floor":
        from floor_loops import LOOPS, greedy_return

        start = time.perf_counter()
        work = LOOPS[preset](frames, seed)
        out = {
            "seconds": time.perf_counter() - start,
            "env_steps": work.env_steps,
            "gradient_steps": work.gradient_steps,
            "samples": work.samples,
        }
        if learn:
            out["greedy"] = greedy_return(preset, work.policy, 20, seed + 10_000)
    else:
        out = _rlpipe(preset, frames, seed, compiled=kind == "compiled")
    out["rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def _rlpipe(preset: str, frames: int, seed: int, compiled: bool) -> dict:
    from torch._dynamo.utils import compilation_time_metrics

    from rlpipe import RunDir, compose_run, train

    with tempfile.TemporaryDirectory() as tmp:
        cfg = compose_run(
            f"+experiment={preset}",
            f"total_frames={frames}",
            f"seed={seed}",
            "eval_every=0",
            "eval_episodes=1",
            "checkpoint_every=0",
            "progress=false",
            f"compile={str(compiled).lower()}",
        )
        train(cfg, tmp)
        run = RunDir(tmp)
        seconds = float(run.metric("time/train_seconds")[1][-1])
        state = run.read_checkpoint().state["algo"]["optimizer"]["state"]
        steps = int(max(float(s["step"]) for s in state.values()))
    return {
        "seconds": seconds,
        "env_steps": frames,
        "gradient_steps": steps,
        "samples": steps * BATCH[preset],
        # dynamo's frames, each with what it hands to AOTAutograd and inductor
        "compile_seconds": sum(compilation_time_metrics.get("_compile.compile_inner", [])),
    }


def measure(kind: str, preset: str, frames: int, learn: bool = False) -> dict:
    args = ["--child", kind, "--preset", preset, "--frames", str(frames)]
    proc = subprocess.run(
        [sys.executable, __file__, *args, *(["--learn"] if learn else [])],
        capture_output=True,
        text=True,
        check=True,
        env={
            **os.environ,
            "PYTHONPATH": os.pathsep.join(
                filter(None, [str(Path(__file__).parent), os.environ.get("PYTHONPATH")])
            ),
        },
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def rounds(presets: list[str], count: int, competitor: bool, kinds: tuple[str, ...]) -> dict:
    """``{(preset, kind): [results]}`` over ``count`` interleaved rounds (``kinds`` in turn,
    reversed every other round)."""
    results: dict[tuple[str, str], list[dict]] = {}
    with busy(competitor):
        for r in range(count):
            for preset in presets:
                for kind in kinds if r % 2 == 0 else kinds[::-1]:
                    results.setdefault((preset, kind), []).append(
                        measure(kind, preset, FRAMES[preset])
                    )
    return results


def rows(presets: list[str], results: dict, compiled: bool) -> list[list[str]]:
    out = []
    for preset in presets:
        floor, ours = results[preset, "floor"], results[preset, "rlpipe"]
        f = statistics.median(r["seconds"] for r in floor)
        o = statistics.median(r["seconds"] for r in ours)
        paired = [b["seconds"] / a["seconds"] for a, b in zip(floor, ours, strict=True)]

        def work(rs: list[dict]) -> str:
            r = rs[0]
            return f"{r['env_steps']:,} / {r['gradient_steps']:,} / {r['samples']:,}"

        out.append(
            [
                f"`{preset}`",
                f"{FRAMES[preset]:,}",
                f"{f:.2f}",
                f"{o:.2f}",
                f"**{o / f:.2f}**",
                f"{statistics.median(paired):.2f} ({min(paired):.2f}–{max(paired):.2f})",
                work(floor),
                work(ours),
                f"{max(r['rss_mb'] for r in floor):.0f}",
                f"{max(r['rss_mb'] for r in ours):.0f}",
            ]
        )
        if compiled:
            comp = results[preset, "compiled"]
            c = statistics.median(r["seconds"] for r in comp)
            spent = statistics.median(r["compile_seconds"] for r in comp)
            out[-1] += [f"{c:.2f}", f"{spent:.1f}", f"**{c / f:.2f}**"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(FRAMES), choices=list(FRAMES))
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--learn", action="store_true", help="also check each floor learns")
    parser.add_argument("--append", type=Path, help="replace this section of a Markdown file")
    parser.add_argument("--compile", action="store_true", help="also time rlpipe with compile=true")
    parser.add_argument("--child", choices=("floor", "rlpipe", "compiled"), help=argparse.SUPPRESS)
    parser.add_argument("--preset", help=argparse.SUPPRESS)
    parser.add_argument("--frames", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.preset, args.frames, 0, args.learn)))
        return
    load = os.getloadavg()[0]
    headers = [
        "preset",
        "frames",
        "floor s",
        "rlpipe s",
        "rlpipe / floor",
        "rlpipe / floor, round by round: median (range)",
        "floor: env steps / gradient steps / rows",
        "rlpipe: env steps / gradient steps / rows",
        "floor peak RSS MB",
        "rlpipe peak RSS MB",
    ]
    kinds = ("floor", "rlpipe")
    if args.compile:
        kinds += ("compiled",)
        headers += ["rlpipe compile=true s", "of which compiling s", "compiled / floor"]
    lines = [
        "## rlpipe against the hand-written floor (benchmarks/floor.py)",
        "",
        f"- machine: {machine(['torch', 'torchrl', 'tensordict', 'gymnasium'])}",
        f"- load before: {load:.2f}; command: `python benchmarks/floor.py --presets "
        f"{' '.join(args.presets)} --rounds {args.rounds}{' --learn' if args.learn else ''}"
        f"{' --compile' if args.compile else ''}`",
        "- seconds: training only (no evaluation), seed 0, one torch thread, median of "
        f"{args.rounds} interleaved rounds, each a fresh process",
    ]
    for competitor in (False, True):
        results = rounds(args.presets, args.rounds, competitor, kinds)
        lines += ["", f"**{'beside a busy process' if competitor else 'quiet'}**", ""]
        lines.append(table(headers, rows(args.presets, results, args.compile)))
    if args.learn:
        learned = []
        for preset in args.presets:
            r = measure("floor", preset, BUDGETS[preset], learn=True)
            mark = "✓" if r["greedy"] >= TARGETS[preset] else "✗"
            learned.append(
                [
                    f"`{preset}`",
                    f"{BUDGETS[preset]:,}",
                    f"{r['greedy']:.1f}",
                    f"{TARGETS[preset]} {mark}",
                ]
            )
        lines += ["", "**the floor learns** (seed 0, the preset's budget, 20 greedy episodes)", ""]
        lines.append(table(["preset", "frames", "greedy mean", "target"], learned))
    publish_section("\n".join(lines), args.append)


if __name__ == "__main__":
    script(main)
