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

from common import load_span, parser, publish_section, read_scalar, section_head, table

PRESETS = ["dqn_cartpole", "sac_pendulum", "ppo_cartpole"]


def run(python: str, extra: list[str], preset: str, seed: int, out: Path) -> dict:
    """One run's final eval and training seconds (read back if ``out`` has it already)."""
    summary = out / "summary.json"
    if not summary.is_file():
        command = [python, "-m", "rlpipe", f"+experiment={preset}", f"seed={seed}", *extra]
        command += ["progress=false", f"hydra.run.dir={out}"]
        subprocess.run(command, check=True, capture_output=True, cwd=out.parent.parent)
    seconds = read_scalar(out, "time/train_seconds")[-1][1]
    return {**json.loads(summary.read_text()), "train_seconds": seconds}


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
        "The same learning before and after (benchmarks/same_learning.py)",
        ["torch", "torchrl", "tensordict", "gymnasium"],
        load_span(start, os.getloadavg()),
        f"before: {args.before_label}; both sides on gymnasium's envs, {args.jobs} runs at once",
        "final eval: the mean return of the run's final greedy evaluation (summary.json); "
        "train s: its training seconds",
    )
    rows = []
    for preset in args.presets:
        finals = {s: [results[preset, seed, s]["eval_mean"] for seed in args.seeds] for s in sides}
        secs = {
            s: [results[preset, seed, s]["train_seconds"] for seed in args.seeds] for s in sides
        }
        for i, seed in enumerate(args.seeds):
            rows.append(
                [f"`{preset}`", seed]
                + [f"{finals[s][i]:.1f}" for s in sides]
                + [f"{secs[s][i]:.1f}" for s in sides]
            )
        rows.append(
            [f"**`{preset}`**", "mean ± std"]
            + [f"**{statistics.mean(v):.1f} ± {statistics.stdev(v):.1f}**" for v in finals.values()]
            + [f"**{statistics.median(v):.1f}** (median)" for v in secs.values()]
        )
    labels = list(sides)
    headers = ["preset", "seed", *(f"{s} final eval" for s in labels)]
    headers += [f"{s} train s" for s in labels]
    publish_section("\n".join([*head, table(headers, rows)]), args.append)


if __name__ == "__main__":
    main()
