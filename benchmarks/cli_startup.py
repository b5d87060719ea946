"""How fast the command line answers before any training: ``--help``, config errors (an unknown
option, an unknown key, a wrong type, a bad value), ``--cfg job``, against the floor
``python -c "import hydra"``, quiet and beside a busy process.

Each command runs in a fresh process, interleaved with the floor and (``--before DIR``) with the
same command on another checkout of rlpipe (put first on ``PYTHONPATH``), round after round;
the table gives medians and each one's ratio to the floor measured in the same rounds.

    python benchmarks/cli_startup.py [--rounds 7] [--before OLD_CHECKOUT] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import busy, machine, publish_section, script, table

COMMANDS = {
    "--help": ["-m", "rlpipe", "--help"],
    "algo=nope": ["-m", "rlpipe", "algo=nope"],
    "algo.lrr=1": ["-m", "rlpipe", "algo.lrr=1"],
    "seed=abc": ["-m", "rlpipe", "seed=abc"],
    "algo.lr=-1": ["-m", "rlpipe", "algo.lr=-1"],
    "algo=ars env=bipedal --cfg job": ["-m", "rlpipe", "algo=ars", "env=bipedal", "--cfg", "job"],
}
FLOOR = ["-c", "import hydra"]
NEUTRAL = tempfile.mkdtemp(prefix="cli-startup-")


def seconds(args: list[str], pythonpath: str | None) -> float:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    start = time.perf_counter()  # from a neutral directory: -m puts the working one first
    subprocess.run([sys.executable, *args], env=env, capture_output=True, cwd=NEUTRAL)
    return time.perf_counter() - start


def measure(rounds: int, before: str | None, competitor: bool) -> list[list[str]]:
    trees = {"now": None, **({"before": before} if before else {})}
    times: dict[tuple[str, str], list[float]] = {}
    with busy(competitor):
        for _ in range(rounds):
            times.setdefault(("floor", ""), []).append(seconds(FLOOR, None))
            for label, args in COMMANDS.items():
                for tree, path in trees.items():
                    times.setdefault((label, tree), []).append(seconds(args, path))
    floor = statistics.median(times["floor", ""])
    rows = [['`python -c "import hydra"` (floor)', "–", f"{floor:.2f}", "1.00"]]
    for label in COMMANDS:
        for tree in trees:
            median = statistics.median(times[label, tree])
            rows.append(
                [f"`python -m rlpipe {label}`", tree, f"{median:.2f}", f"{median / floor:.2f}"]
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--before", help="another rlpipe checkout to time the same commands on")
    parser.add_argument("--before-label", default="", help="what --before is (e.g. a commit)")
    parser.add_argument("--append", type=Path, help="replace this section of a Markdown file")
    args = parser.parse_args()
    lines = [
        "## Command-line start-up (benchmarks/cli_startup.py)",
        "",
        f"- machine: {machine(['hydra-core', 'torch', 'torchrl'])}",
        f"- load before: {os.getloadavg()[0]:.2f}; command: `python benchmarks/cli_startup.py "
        f"--rounds {args.rounds}{' --before <checkout>' if args.before else ''}`"
        + (f" (before: {args.before_label})" if args.before_label else ""),
        f"- median wall seconds of {args.rounds} interleaved rounds, each process fresh; ratio: "
        "to the floor of the same rounds",
    ]
    headers = ["command", "tree", "seconds", "× floor"]
    for competitor in (False, True):
        rows = measure(args.rounds, args.before, competitor)
        lines += ["", f"**{'beside a busy process' if competitor else 'quiet'}**", ""]
        lines.append(table(headers, rows))
    publish_section("\n".join(lines), args.append)


if __name__ == "__main__":
    script(main)
