"""BipedalWalker-v3's baselines through ``python -m rlpipe.evaluate``: a random policy, the
agent-templates notebook's naive controller and the hand-written gait, each over 100 episodes on
rlpipe's lock-step env copies and over 100 episodes one after another on one env (``copies=1``).

Each evaluation's JSON summary is kept under ``--out`` and read back, so a call with the same
arguments continues where an interrupted one stopped.

    python benchmarks/baselines.py [--episodes 100] [--policies random naive heuristic]
        [--out benchmarks/results/baselines] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from common import evaluated, load_span, publish_section, script, section_head, table

from rlpipe.episodes import eval_envs

STEPS = 1600  # BipedalWalker-v3's time limit: an episode that ends sooner fell
NAMES = {
    "random": "`random`",
    "naive": "`naive` (the agent-templates notebook's controller)",
    "heuristic": "`heuristic` (`rlpipe.heuristic.WalkerGait`)",
}


def summary(policy: str, copies: int, args: argparse.Namespace) -> tuple[dict, bool]:
    """One evaluation's JSON summary, and whether it was read back from an earlier call."""
    out = args.out / f"{policy}-{args.episodes}-copies{copies}-seed{args.seed}.json"
    read_back = out.exists()
    keys = [f"policy={policy}", "env=bipedal", f"episodes={args.episodes}", f"copies={copies}"]
    s = evaluated(out, *keys, f"seed={args.seed}", f"backend={args.backend}")
    if not read_back:
        print(f"baselines: {policy} on {copies} copies: {s['return_mean']:.2f}", file=sys.stderr)
    return s, read_back


def row(policy: str, copies: int, s: dict) -> list[str]:
    """One table row: who, on what, the returns and the falls."""
    on = "one env, one after another" if copies == 1 else f"{copies} copies in lock-step"
    return [
        NAMES[policy],
        on,
        f"{s['return_mean']:.2f} ± {s['return_std']:.2f}",
        f"{s['return_min']:.2f}",
        f"{s['return_max']:.2f}",
        str(sum(r > 0 for r in s["returns"])),
        str(sum(n < STEPS for n in s["lengths"])),
        f"{s['length_mean']:.1f}",
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--policies", nargs="+", choices=list(NAMES), default=list(NAMES))
    p.add_argument("--seed", type=int, default=0, help="the evaluations' seed (evaluate's default)")
    p.add_argument("--backend", default="gymnasium", choices=["gymnasium", "envpool"])
    p.add_argument("--out", type=Path, default=Path("benchmarks/results/baselines"))
    p.add_argument("--append", type=Path, help="put the section into this Markdown file")
    args = p.parse_args()
    start = os.getloadavg()
    rows, read_back = [], 0
    for policy in args.policies:
        for copies in (eval_envs(args.episodes), 1):
            s, old = summary(policy, copies, args)
            rows.append(row(policy, copies, s))
            read_back += old
    headers = ["policy", "episodes on", "return mean ± std", "min", "max", "episodes above 0"]
    headers += [f"falls (ended before {STEPS:,} steps)", "mean length"]
    head = section_head(
        "BipedalWalker-v3 baselines",
        ["torch", "torchrl", "gymnasium", "envpool", "Box2D"],
        f"{load_span(start, os.getloadavg())} of this call; {read_back} of {len(rows)} "
        f"evaluations read back from {args.out} (returns, which the load does not change)",
        f"{args.episodes} greedy episodes each way, seed {args.seed}, env.backend={args.backend}; "
        "each evaluation is `python -m rlpipe.evaluate policy=<policy> env=bipedal "
        f"episodes={args.episodes} copies=<copies> seed={args.seed} backend={args.backend}`",
    )
    publish_section("\n".join([*head, table(headers, rows)]), args.append)


if __name__ == "__main__":
    script(main)
