"""Arms of a tuning screen, seed by seed: solves, the seeds one arm alone solved, a sign test.

A screen runs a preset and its variants on the same tuning seeds (``benchmarks/presets.py --tune
--seeds ... --out DIR [--override k=v]``, one ``--out`` per arm). This reads the arms' records
(``DIR/<preset>/seed<N>/rlpipe.json``, or ``DIR/seed<N>/rlpipe.json`` as kept in
``benchmarks/results/presets-more``), keeps the seeds every arm finished, and prints per arm: the
seeds solved (the protocol's test: the last three evals' mean and the final eval both ≥ the
target), the seeds it alone solved against the first arm, the one-sided sign test of those
(exact binomial: the chance of at least that many wins if either arm were as likely to win each
such seed), runs that fell back (an eval below ``--fell-below`` after one reached the target),
frames and training seconds to the target, wall seconds a seed, and each miss's last three /
final. The first arm is the reference (the preset as it stands). Decide by a rule written before
the runs; this only counts.

    python benchmarks/screen.py --preset dqn_cartpole A=/tmp/screen/A Q=/tmp/screen/Q
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from math import comb
from pathlib import Path

from common import table
from presets_report import seed_text
from presets_runs import Run, record_run
from presets_table import PRESETS

from rlpipe.errors import RlpipeError, check


def sign_test(wins: int, losses: int) -> float:
    """One-sided exact sign test: P(at least ``wins`` of ``wins + losses`` fair coin flips)."""
    n = wins + losses
    return sum(comb(n, k) for k in range(wins, n + 1)) / 2**n if n else 1.0


def read_arm(folder: Path, preset: str) -> dict[int, Run]:
    """The finished runs of one arm, by seed."""
    files = sorted((folder / preset).glob("seed*/rlpipe.json")) or sorted(
        folder.glob("seed*/rlpipe.json")
    )
    runs = {}
    for path in files:
        saved = json.loads(path.read_text())
        if "evals" in saved:
            seed = int(path.parent.name.removeprefix("seed"))
            runs[seed] = record_run(preset, seed, saved)
    check(bool(runs), f"{folder}: no finished {preset} records (seed<N>/rlpipe.json) in it")
    return runs


def fell_back(run: Run, target: float, below: float) -> bool:
    """Whether an eval after the first one at the target fell below ``below``."""
    reached = [i for i, (_, mean, _) in enumerate(run.evals) if mean >= target - 1e-6]
    return bool(reached) and any(m < below for _, m, _ in run.evals[reached[0] + 1 :])


def median_text(values: list[float], fmt: str) -> str:
    return format(statistics.median(values), fmt) if values else "–"


def report(preset: str, arms: dict[str, dict[int, Run]], below: float | None = None) -> str:
    """The screen's Markdown: what the arms share, a row per arm, and each arm's misses."""
    p = PRESETS[preset]
    below = p.fell_below if below is None else below
    seeds = sorted(set.intersection(*(set(runs) for runs in arms.values())))
    check(bool(seeds), "the arms share no finished seed: compare arms run on the same seeds")
    (first, base), rows, misses = next(iter(arms.items())), [], []
    for name, runs in arms.items():
        shared = [runs[s] for s in seeds]
        hits = [r.hit(p.target) for r in shared]
        wins = sum(runs[s].solved(p.target) and not base[s].solved(p.target) for s in seeds)
        losses = sum(base[s].solved(p.target) and not runs[s].solved(p.target) for s in seeds)
        rows.append(
            [
                name,
                f"{sum(r.solved(p.target) for r in shared)} of {len(seeds)}",
                "–" if runs is base else f"{wins} / {losses}, p = {sign_test(wins, losses):.3f}",
                sum(fell_back(r, p.target, below) for r in shared),
                f"{sum(h is not None for h in hits)} of {len(seeds)}",
                median_text([h[0] for h in hits if h], ",.0f"),
                median_text([h[1] for h in hits if h], ".1f"),
                median_text([r.wall for r in shared if r.wall is not None], ".1f"),
            ]
        )
        missed = [
            f"{r.seed}: {r.last_three:.1f} / {r.final:.1f}"
            for r in shared
            if not r.solved(p.target) and r.final is not None
        ]
        misses.append(f"- {name} misses (last three / final): {'; '.join(missed) or 'none'}")
    machines = sorted({runs[s].machine for runs in arms.values() for s in seeds})
    head = [
        f"Screen of `{preset}` (target {p.target:g}) on seeds {seed_text(seeds)}, "
        f"{len(seeds)} finished by every arm; reference arm: {first}",
        "",
        *(f"- machine: {m}" for m in machines),
        "",
    ]
    headers = [
        "arm",
        "solved",
        "alone: this / reference, sign test",
        f"fell below {below:g}",
        "reached",
        "median frames to target",
        "median train s to target",
        "median wall s a seed",
    ]
    return "\n".join([*head, table(headers, rows), "", *misses]) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", required=True, choices=PRESETS, metavar="NAME")
    p.add_argument("arms", nargs="+", metavar="NAME=DIR", help="the reference arm first")
    p.add_argument(
        "--fell-below", type=float, help="default: the target less a tenth of target - floor"
    )
    args = p.parse_args()
    try:
        check(
            len(args.arms) >= 2 and all("=" in a for a in args.arms),
            "give two or more arms as NAME=DIR, the reference arm first",
        )
        pairs = (a.split("=", 1) for a in args.arms)
        arms = {name: read_arm(Path(folder), args.preset) for name, folder in pairs}
        print(report(args.preset, arms, args.fell_below), end="")
    except RlpipeError as error:
        sys.exit(f"screen: {error}")


if __name__ == "__main__":
    main()
