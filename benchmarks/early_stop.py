"""A screen's arm stopped once solved, replayed from runs made to their whole budget.

For each finished run of ``SRC`` (``benchmarks/presets.py --out SRC``, run with a checkpoint kept
at every eval: ``--override keep_checkpoints=<evals + 1>``), the stop is the first greedy eval at
which the mean of the last ``--window`` evals reaches the preset's target (SB3's
StopTrainingOnRewardThreshold, over a window). The derived record in ``DST`` holds the evals up to
the stop, the final greedy eval of the checkpoint there (``python -m rlpipe.evaluate
checkpoint=<frames>``, the preset's final episodes and the seed the final eval uses) and the wall
seconds to that eval's end; a run that never met the stop keeps its own record. ``DST`` is an arm
for ``benchmarks/screen.py``; a call continues where an earlier one stopped, and ends with how many
stopped runs fell back (an eval below the preset's fell-below) in the full run after their stop.

    python benchmarks/early_stop.py --preset ars_bipedal SRC DST [--window 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from common import evaluated, read_scalar
from presets_table import PRESETS

from rlpipe.episodes import FINAL, episodes_seed
from rlpipe.errors import RlpipeError, check
from rlpipe.files import write_atomic


def stop_index(means: list[float], target: float, window: int) -> int | None:
    """The first eval at which the mean of the last ``window`` evals reaches ``target``."""
    for i in range(window - 1, len(means)):
        if sum(means[i - window + 1 : i + 1]) / window >= target:
            return i
    return None


def stopped_record(saved: dict, run: Path, seed: int, i: int, episodes: int, out: Path) -> dict:
    """``saved`` (a record of ``run``) as if the run had stopped after its ``i``-th eval."""
    frames = int(saved["evals"][i][0])
    final = out / f"final-{frames}.json"
    check(
        final.exists() or run.is_dir(),
        f"{run} is gone: its stop at {frames:,} frames cannot be evaluated",
    )
    keys = [f"run_dir={run}", f"checkpoint={frames}", f"episodes={episodes}"]
    summary = evaluated(final, *keys, "allow_env_import=true", f"seed={episodes_seed(seed, FINAL)}")
    elapsed = dict(read_scalar(run, "time/elapsed"))
    seconds = dict(read_scalar(run, "time/eval_seconds"))
    return {
        **saved,
        "evals": saved["evals"][: i + 1],
        "final": summary["return_mean"],
        "wall": elapsed[frames] + seconds[frames],  # to the end of the eval that stopped it
        "stopped_at": frames,
        "ran_to": saved["evals"][-1][0],
        "final_at_end": saved["final"],
    }


def lowest_after(saved: dict, stopped_at: int) -> float | None:
    """The lowest of the full run's evals after its stop (None: it stopped at its last eval)."""
    return min((m for f, m, _ in saved["evals"] if f > stopped_at), default=None)


def derive(src: Path, dst: Path, preset: str, window: int) -> list[str]:
    """Derive ``dst``'s records from ``src``'s finished runs: a line per new record, then how many
    stopped runs (new or derived before) fell back in the full run after their stop."""
    p, lines, lows = PRESETS[preset], [], {}
    for meta in sorted((src / preset).glob("seed*/rlpipe.json")):
        saved = json.loads(meta.read_text())
        if "evals" not in saved:
            continue
        seed, target = int(meta.parent.name.removeprefix("seed")), dst / preset / meta.parent.name
        new = not (target / "rlpipe.json").exists()
        if not new:
            record = json.loads((target / "rlpipe.json").read_text())
        else:
            target.mkdir(parents=True, exist_ok=True)  # the record and a stop's final eval
            i = stop_index([m for _, m, _ in saved["evals"]], p.target, window)
            record = (
                saved
                if i is None
                else stopped_record(saved, meta.parent / "run", seed, i, p.final_episodes, target)
            )
        if "stopped_at" in record:
            lows[seed] = lowest_after(saved, record["stopped_at"])
        if not new:
            continue
        write_atomic(target / "rlpipe.json", (json.dumps(record, indent=1) + "\n").encode())
        line = "never met the stop: its own record"
        if seed in lows:
            low = lows[seed]
            line = (
                f"stopped at {record['stopped_at']:,} of {record['ran_to']:,} frames, final "
                f"{record['final']:.1f} (at the end {record['final_at_end']:.1f}), "
                f"{record['wall']:.0f} s of {saved['wall']:.0f}, lowest eval after it "
                + ("none" if low is None else f"{low:.1f}")
            )
        lines.append(f"early_stop: {preset} seed {seed}: {line}")
    fell = [s for s, low in lows.items() if low is not None and low < p.fell_below]
    if lows:
        lines.append(
            f"early_stop: {preset}: {len(fell)} of {len(lows)} stopped runs fell below "
            f"{p.fell_below:g} in the full run's evals after the stop"
            + (f" (seeds {', '.join(map(str, fell))})" if fell else "")
        )
    return lines


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", required=True, choices=PRESETS, metavar="NAME")
    p.add_argument("--window", type=int, default=3, help="evals whose mean must reach the target")
    p.add_argument("src", type=Path, help="benchmarks/presets.py --out of the runs made in full")
    p.add_argument("dst", type=Path, help="where the stopped arm's records go")
    args = p.parse_args()
    try:
        check(args.window >= 1, f"--window must be >= 1, got {args.window}")
        check((args.src / args.preset).is_dir(), f"{args.src}: no {args.preset} runs in it")
        for line in derive(args.src, args.dst, args.preset, args.window):
            print(line)
    except RlpipeError as error:
        sys.exit(f"early_stop: {error}")


if __name__ == "__main__":
    main()
