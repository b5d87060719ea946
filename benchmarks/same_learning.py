"""The same learning before and after a change: each preset's final evals over seeds, on this
checkout and on an older one, each run as a user runs it: one section of BENCHMARKS.md.

``--before-python`` is a Python whose ``rlpipe`` is the older checkout (a venv with it installed:
``python -m venv --system-site-packages V && V/bin/pip install --no-deps OLD_CHECKOUT``). Both
sides run ``python -m rlpipe +experiment=<preset> seed=<s>`` on gymnasium's envs (this checkout
with ``env.backend=gymnasium``: ``auto`` would take EnvPool for CartPole, other random streams),
torch's threads as the preset sets them. Runs finished in ``--out`` are read, not run again.

    python benchmarks/same_learning.py --before-python V/bin/python --before-label afe9178 \
        [--presets dqn_cartpole sac_pendulum ppo_cartpole] [--seeds 0 1 2 3 4] [--jobs 2] \
        [--out runs/same_learning] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from common import load_span, parser, publish_section, read_scalar, script, section_head, table

PRESETS = ["dqn_cartpole", "sac_pendulum", "ppo_cartpole"]


def run(python: str, extra: list[str], preset: str, seed: int, out: Path) -> dict:
    """One run's final eval and training seconds (read back if ``out`` has it already)."""
    summary = out / "summary.json"
    ran = not summary.is_file()
    if ran:
        command = [python, "-m", "rlpipe", f"+experiment={preset}", f"seed={seed}", *extra]
        command += ["progress=false", f"hydra.run.dir={out}"]
        subprocess.run(command, check=True, capture_output=True, cwd=out.parent.parent)
    summary = json.loads(summary.read_text())
    seconds = read_scalar(out, "time/train_seconds")[-1][1]
    late = [r for f, r in read_scalar(out, "train/episode_return") if f > 0.8 * summary["frames"]]
    return {**summary, "train_seconds": seconds, "late_return": statistics.mean(late), "ran": ran}


def ran_note(results: dict) -> str:
    """How many of the runs this call ran, and whether the rest came back from ``--out``."""
    ran = sum(r["ran"] for r in results.values())
    read = "; the others were read back from --out" if ran < len(results) else ""
    return f"{ran} of {len(results)} runs ran in this call{read}"


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.set_defaults(seeds=[0, 1, 2, 3, 4])
    p.add_argument("--before-python", required=True, help="a Python with the older rlpipe")
    p.add_argument("--before-label", default="before", help="what the older checkout is")
    p.add_argument("--presets", nargs="+", default=PRESETS)
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path("runs/same_learning"))
    args = p.parse_args()
    sides = {
        args.before_label: (args.before_python, []),
        "now": (sys.executable, ["env.backend=gymnasium"]),
    }
    start = os.getloadavg()
    jobs = {}
    with ThreadPoolExecutor(args.jobs) as pool:
        for preset in args.presets:
            for seed in args.seeds:
                for side, (python, extra) in sides.items():  # the sides interleaved
                    out = (args.out / side / preset / str(seed)).resolve()
                    out.parent.mkdir(parents=True, exist_ok=True)
                    jobs[preset, seed, side] = pool.submit(run, python, extra, preset, seed, out)
    results = {key: job.result() for key, job in jobs.items()}
    head = section_head(
        "The same learning before and after",
        ["torch", "torchrl", "tensordict", "gymnasium"],
        load_span(start, os.getloadavg()) + f" ({ran_note(results)})",
        f"before: {args.before_label}; both sides on gymnasium's envs, {args.jobs} runs at once",
        "final eval: the mean return of the run's final greedy evaluation (summary.json); "
        "late training return: the mean return of its training episodes that ended in the last "
        "20% of its frames (the exploring policy; no evaluation seeding involved); train s: its "
        "training seconds",
    )
    rows = []
    for preset in args.presets:
        of = {
            key: {s: [results[preset, seed, s][key] for seed in args.seeds] for s in sides}
            for key in ("eval_mean", "late_return", "train_seconds")
        }
        for i, seed in enumerate(args.seeds):
            cells = [f"{of[key][s][i]:.1f}" for key in of for s in sides]
            rows.append([f"`{preset}`", seed, *cells])
        spread = [
            f"**{statistics.mean(v):.1f} ± {statistics.stdev(v):.1f}**"
            for key in ("eval_mean", "late_return")
            for v in of[key].values()
        ]
        medians = [f"**{statistics.median(v):.1f}** (median)" for v in of["train_seconds"].values()]
        rows.append([f"**`{preset}`**", "mean ± std", *spread, *medians])
    headers = ["preset", "seed"]
    for what in ("final eval", "late training return", "train s"):
        headers += [f"{s} {what}" for s in sides]
    publish_section("\n".join([*head, table(headers, rows)]), args.append)


if __name__ == "__main__":
    script(main)
