"""Where a preset's training time goes, by part of the loop, sampled with py-spy: one section.

Each preset trains ``--frames`` frames (seed 0, no evaluation) under ``py-spy record`` as a user
runs it; with ``--before-python`` (a Python whose ``rlpipe`` is an older checkout, see
``same_learning.py``) the older code does the same beside it. Every sample inside the training
step is put in the first part its stack meets from the innermost frame out (:data:`PARTS`): the
env's own stepping, the collection around it (policy, wrappers, TensorDicts), n-step returns,
the replay buffer's extend and sample, value estimates (GAE, TD targets), loss forward,
backward, optimizer, target update; the rest of the step is "loop". Per part: seconds (the
run's training seconds times its share of the step's samples) and share; "train s" is the run's
``time/train_seconds``. py-spy samples the process from outside, at ``--rate`` Hz.

    pip install py-spy
    python benchmarks/breakdown.py [--before-python V/bin/python --before-label afe9178] \
        [--presets dqn_cartpole sac_pendulum ppo_cartpole] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

from common import load_span, parser, publish_section, read_scalar, script, section_head, table

FRAMES = {"dqn_cartpole": 20_000, "sac_pendulum": 5_000, "ppo_cartpole": 20_480}
# (part, substrings of a frame "function (file:line)", or after a ^ its start with the function's
# class left out (py-spy 0.4 writes "Class.method"): any one matches), the innermost match wins
PARTS = [
    ("env step", ["gymnasium/envs/", "gymnasium/vector/", "envpool/"]),
    ("n-step", ["torchrl/data/postprocs", "n_step_transitions ("]),
    ("buffer extend", ["extend (torchrl/data/", "set (torchrl/data/replay_buffers"]),
    ("buffer sample", ["sample (torchrl/data/", "get (torchrl/data/replay_buffers"]),
    ("value estimator", ["torchrl/objectives/value/", "td0_target ("]),
    ("optimizer", ["torch/optim/"]),
    ("backward", ["torch/autograd/", "backward (torch/_tensor.py"]),
    ("target update", ["^step (torchrl/objectives/utils.py", "^step (rlpipe/algos/offpolicy.py"]),
    ("loss forward", ["torchrl/objectives/", "rlpipe/algos/direct.py", "loss_of ("]),
    ("collection", ["torchrl/collectors/", "rlpipe/algos/collectors.py", "torchrl/envs/"]),
]
LOOP = "train_step ("  # the training step's frame: samples outside it are start-up and the rest


def own(frame: str) -> str:
    """A frame without its function's class: ``"step (f.py:1)"`` of ``"Soft.step (f.py:1)"``."""
    name, sep, where = frame.partition(" (")
    return name.rpartition(".")[2] + sep + where


def part(stack: list[str]) -> str | None:
    """The part of the loop a sampled stack (outermost first) is in; None outside a step."""
    if not any(LOOP in frame for frame in stack):
        return None
    for frame in reversed(stack):
        for name, marks in PARTS:
            if any(own(frame).startswith(m[1:]) if m[0] == "^" else m in frame for m in marks):
                return name
        if LOOP in frame:
            return "loop"
    return "loop"


def profile(python: str, extra: list[str], preset: str, rate: int) -> tuple[Counter, float]:
    """Samples per part of one run of ``preset``, and its training seconds."""
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "raw.txt"
        command = [python, "-m", "rlpipe", f"+experiment={preset}", *extra]
        command += [f"total_frames={FRAMES[preset]}", "eval_every=0", "eval_episodes=1"]
        command += ["checkpoint_every=0", "progress=false", f"hydra.run.dir={tmp}/run"]
        spy = ["py-spy", "record", "--nonblocking", "-r", str(rate), "-f", "raw", "-o", str(raw)]
        spy.append("--")
        # py-spy 0.4 may exit 1 ("No child process") once its child has exited, and now and
        # then panics reading a running process: the run's summary and the samples tell
        for _ in range(3):
            spied = subprocess.run(spy + command, capture_output=True, text=True, cwd=tmp)
            if (Path(tmp) / "run" / "summary.json").is_file() and raw.is_file():
                break
            shutil.rmtree(Path(tmp) / "run", ignore_errors=True)
        else:
            raise RuntimeError(f"{' '.join(command)} failed:\n{spied.stderr}")
        counts: Counter = Counter()
        for line in raw.read_text(errors="replace").splitlines():
            stack, _, count = line.rpartition(" ")
            name = part(stack.split(";"))
            if name is not None:
                counts[name] += int(count)
        return counts, read_scalar(Path(tmp) / "run", "time/train_seconds")[-1][1]


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--before-python", help="a Python whose rlpipe is an older checkout")
    p.add_argument("--before-label", default="before", help="what the older checkout is")
    p.add_argument("--presets", nargs="+", default=list(FRAMES), choices=list(FRAMES))
    p.add_argument("--rate", type=int, default=200, help="py-spy's samples per second")
    args = p.parse_args()
    sides = {"now": (sys.executable, ["env.backend=gymnasium", "threads=1"])}
    if args.before_python:
        sides = {args.before_label: (args.before_python, ["threads=1"]), **sides}
    start = os.getloadavg()
    results = {
        (preset, s): profile(*sides[s], preset, args.rate) for preset in args.presets for s in sides
    }
    names = [name for name, _ in PARTS] + ["loop"]
    rows = []
    for (preset, side), (counts, seconds) in results.items():
        total = sum(counts.values())
        shares = [
            f"{seconds * counts[n] / total:.2f} ({100 * counts[n] / total:.0f}%)" for n in names
        ]
        rows.append([f"`{preset}`", side, f"{seconds:.1f}", *shares])
    head = section_head(
        "Where the training time goes",
        ["torch", "torchrl", "tensordict", "gymnasium"],
        load_span(start, os.getloadavg()),
        "seed 0, each checkout's default env backend (env.backend=auto, where a checkout has it: "
        "EnvPool for CartPole-v1, gymnasium for Pendulum-v1), one torch thread, no evaluation; "
        "per part, seconds (and share) "
        f"of the training step by its py-spy samples ({args.rate} Hz, not pausing the process); "
        "train s: time/train_seconds under sampling",
        f"frames: {', '.join(f'{k} {v:,}' for k, v in FRAMES.items() if k in args.presets)}",
    )
    text = "\n".join([*head, table(["preset", "code", "train s", *names], rows)])
    publish_section(text, args.append)


if __name__ == "__main__":
    script(main)
