"""Subnormal floats and MBRL's planner: a trained run's planning time with torch flushing
subnormals to zero (what rlpipe sets) and without, interleaved, alone and beside a busy core.

Weight decay shrinks the weights of dead ReLU units towards zero; Adam's coupled decay keeps
them shrinking geometrically until they fall below float32's smallest normal number (1.2e-38),
where x86 CPUs compute in microcode, many times slower. For each ``--run-dir`` (an MBRL run:
``python -m rlpipe +experiment=mbrl_pendulum seed=90`` leaves one) this loads the newest
checkpoint as ``python -m rlpipe.evaluate`` does (one torch thread), counts its subnormal
parameters, and times ``Planner.plan`` for one observation (a training step) and for 32 (an
evaluation step: 32 env copies in lock-step), ``--rounds`` rounds each, the two settings
taking turns. The same observations and generator seed both ways give the largest difference
in the planned actions, and ``--episodes`` greedy episodes (one env copy each, seed 0) the
returns both ways.

``--whole-run SEED``: ``python -m rlpipe +experiment=mbrl_pendulum seed=SEED`` from scratch, once
as rlpipe runs it and once with subnormals kept (rlpipe has no switch for that: the kept run's
process replaces ``torch.set_flush_denormal`` with a call that turns flushing off), one after
the other: the run's wall, training and evaluation seconds, its evals both ways, and the
subnormal parameters its last checkpoint holds.

    python benchmarks/denormals.py --run-dir RUN [RUN ...] --whole-run 93 --append BENCHMARKS.md
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from common import busy, load_span, publish_section, read_scalar, script, section_head, table

from rlpipe.envs import make_env
from rlpipe.episodes import evaluate
from rlpipe.pipeline import load_run

FLUSH = (True, False)  # subnormals flushed (rlpipe's setting), then kept
CONDITIONS = {"alone": False, "beside a CPU-bound process": True}
BATCHES = (1, 32)
KEEP = (  # run rlpipe's command line with rlpipe's set_flush_denormal(True) turned into False
    "import sys, torch; flush = torch.set_flush_denormal; "
    "torch.set_flush_denormal = lambda on: flush(False); "
    "sys.argv[0] = 'rlpipe'; from rlpipe.__main__ import main; main()"
)


def subnormals(model: torch.nn.Module) -> tuple[int, int]:
    """(subnormal, all) float32 parameter entries of ``model``, read from their bits (with
    subnormals flushed, the CPU compares them as zeros): exponent 0, mantissa not 0."""
    count = total = 0
    for p in model.parameters():
        bits = p.detach().view(torch.int32)
        count += int(((bits & 0x7F800000) == 0).logical_and(bits & 0x007FFFFF != 0).sum())
        total += p.numel()
    return count, total


def plan_seconds(planner, observation: torch.Tensor, flush: bool) -> float:
    """Seconds of one ``plan`` call with subnormals flushed or kept."""
    torch.set_flush_denormal(flush)
    generator = torch.Generator().manual_seed(0)
    start = time.perf_counter()
    planner.plan(observation, generator)
    return time.perf_counter() - start


def actions_gap(planner, observation: torch.Tensor) -> float:
    """Largest difference between the actions planned with and without flushing (same seed)."""
    actions = []
    for flush in FLUSH:
        torch.set_flush_denormal(flush)
        actions.append(planner.plan(observation, torch.Generator().manual_seed(0)))
    return float((actions[0] - actions[1]).abs().max())


def returns(loaded, episodes: int) -> dict[bool, list[float]]:
    """Greedy returns of ``episodes`` episodes (seed 0) with and without flushing."""
    out = {}
    for flush in FLUSH:
        torch.set_flush_denormal(flush)
        env = make_env(loaded.cfg.env, num_envs=episodes, seed=0)
        try:
            out[flush] = evaluate(loaded.algo.policy, env, episodes).returns
        finally:
            env.close()
    return out


def measure(run_dir: Path, rounds: int, episodes: int) -> tuple[list[list[object]], str]:
    """Table rows for one run dir, and a line on its actions and returns both ways."""
    loaded = load_run(str(run_dir), None, device=torch.device("cpu"))
    try:
        planner = loaded.algo.mpc.planner
        count, total = subnormals(loaded.algo.model)
        obs_size = loaded.algo.model.obs_norm.mean.numel()
        observations = {b: torch.randn(b, obs_size, generator=torch.Generator().manual_seed(b))
                        for b in BATCHES}  # fmt: skip
        times: dict[tuple[str, int, bool], list[float]] = {}
        for condition, competitor in CONDITIONS.items():
            with busy(competitor):
                for _ in range(rounds):
                    for batch, observation in observations.items():
                        for flush in FLUSH:
                            seconds = plan_seconds(planner, observation, flush)
                            times.setdefault((condition, batch, flush), []).append(seconds)
        gap = actions_gap(planner, observations[32])
        got = returns(loaded, episodes) if episodes else {}
    finally:
        torch.set_flush_denormal(True)
        loaded.algo.close()
    name = run_dir.as_posix()
    rows = []
    for condition in CONDITIONS:
        for batch in BATCHES:
            ms = {f: 1e3 * statistics.median(times[condition, batch, f]) for f in FLUSH}
            rows.append([name, f"{count:,} of {total:,}", condition, batch, f"{ms[True]:.0f}",
                         f"{ms[False]:.0f}", f"{ms[False] / ms[True]:.2f}×"])  # fmt: skip
    line = (
        f"{name} ({loaded.checkpoint.name}): the actions planned for 32 observations differ by "
        f"at most {gap:.2g}"
    )
    if got:
        both = [", ".join(f"{r:.1f}" for r in got[f]) for f in FLUSH]
        line += f"; greedy returns of {episodes} episodes, flushed: {both[0]}; kept: {both[1]}"
    return rows, line


def whole_run(seed: int) -> tuple[list[list[object]], str]:
    """Table rows for ``mbrl_pendulum`` trained with subnormals flushed, then kept, and a line
    comparing their evals."""
    rows, evals, seconds = [], {}, []
    with tempfile.TemporaryDirectory() as tmp:
        for flush in FLUSH:
            run_dir = Path(tmp) / ("flushed" if flush else "kept")
            head = [sys.executable, "-m", "rlpipe"] if flush else [sys.executable, "-c", KEEP]
            args = ["+experiment=mbrl_pendulum", f"seed={seed}", "progress=false",
                    f"hydra.run.dir={run_dir}"]  # fmt: skip
            subprocess.run([*head, *args], check=True, capture_output=True)
            summary = json.loads((run_dir / "summary.json").read_text())
            train = read_scalar(run_dir, "time/train_seconds")[-1][1]
            evaluating = sum(v for _, v in read_scalar(run_dir, "time/eval_seconds"))
            evals[flush] = read_scalar(run_dir, "eval/return_mean")
            seconds.append((summary["wall_time"], train, evaluating))
            loaded = load_run(str(run_dir), None, device=torch.device("cpu"))
            count, total = subnormals(loaded.algo.model)
            loaded.algo.close()
            rows.append([seed, "flushed (rlpipe)" if flush else "kept", f"{summary['frames']:,}",
                          f"{summary['wall_time']:.0f}", f"{train:.0f}", f"{evaluating:.0f}",
                          f"{count:,} of {total:,}"])  # fmt: skip
    for i, (flushed, kept) in enumerate(zip(*seconds), start=3):  # wall, train, eval
        rows[1][i] += f" ({kept / flushed:.2f}×)"
    gap = max(abs(a[1] - b[1]) for a, b in zip(evals[True], evals[False]))
    last = f"{evals[True][-1][1]:.1f} and {evals[False][-1][1]:.1f}"
    line = (
        f"seed {seed}: {len(evals[True])} evals each; their returns differ by at most {gap:.2f} "
        f"(the last: {last}); Adam's updates flush in one run and keep in the other, so the "
        "weights part by tiny amounts"
    )
    return rows, line


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run-dir", type=Path, nargs="*", default=[], help="MBRL run dirs")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds per condition")
    p.add_argument("--episodes", type=int, default=4, help="greedy episodes both ways (0: none)")
    p.add_argument(
        "--whole-run", type=int, nargs="*", default=[], metavar="SEED",
        help="train mbrl_pendulum from scratch with this seed, flushed and kept",
    )  # fmt: skip
    p.add_argument("--append", type=Path, help="put the section into this Markdown file")
    args = p.parse_args()
    if not args.run_dir and not args.whole_run:
        p.error("give --run-dir RUN [RUN ...] and/or --whole-run SEED")
    load_before = os.getloadavg()
    rows, lines, runs, run_lines = [], [], [], []
    for run_dir in args.run_dir:
        got, line = measure(run_dir, args.rounds, args.episodes)
        rows += got
        lines.append(line)
    for seed in args.whole_run:
        got, line = whole_run(seed)
        runs += got
        run_lines.append(line)
    head = section_head(
        "Subnormal floats: MBRL's planner with them flushed and kept",
        ["torch", "torchrl"],
        load_span(load_before, os.getloadavg()),
    )
    report = [*head]
    if rows:
        report += [
            "One `Planner.plan` call on a trained run's newest checkpoint, one torch thread, "
            f"median of {args.rounds} interleaved rounds; batch 1 is a training step, 32 an "
            "evaluation step. The competitor is `python -c 'while True: pass'`.",
            "",
            table(["run", "subnormal parameters", "condition", "batch", "flushed ms", "kept ms",
                   "kept / flushed"], rows),
            "",
            *[f"- {line}" for line in lines],
            "",
        ]  # fmt: skip
    if runs:
        report += [
            "Whole runs, `python -m rlpipe +experiment=mbrl_pendulum seed=S` (15,000 frames, a "
            "10-episode eval every 2,000 and at the end), flushed then kept, one after the other "
            "(seconds: the run's own; in brackets kept / flushed):",
            "",
            table(["seed", "subnormals", "frames", "wall s", "train s", "eval s",
                   "subnormal parameters at the end"], runs),
            "",
            *[f"- {line}" for line in run_lines],
        ]  # fmt: skip
    publish_section("\n".join(report).rstrip("\n") + "\n", args.append)


if __name__ == "__main__":
    script(main)
