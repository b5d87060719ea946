"""Shared pieces of the benchmark scripts: machine facts, Markdown tables, composing presets."""

from __future__ import annotations

import argparse
import csv
import json
import os
import platform
import re
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from datetime import date
from functools import partial
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type

from rlpipe.algos import make_algorithm
from rlpipe.cli import compose_run
from rlpipe.console import console_may_close
from rlpipe.envs import make_env
from rlpipe.episodes import evaluate
from rlpipe.errors import RlpipeError, check
from rlpipe.files import write_atomic
from rlpipe.pipeline import LoadedRun, load_run
from rlpipe.runtime import seed_everything


def script(main: Callable[[], None]) -> None:
    """Run a benchmark script's ``main``: a console that closes under it (``| head``) ends
    nothing, so its table still reaches ``--append``; an error of rlpipe's (a run dir that is not
    there, a bad argument) ends it in one line, ``<script>: <what is wrong>``, and exit status 1."""
    try:
        with console_may_close():
            main()
    except RlpipeError as error:
        sys.exit(f"{Path(sys.argv[0]).stem}: {error}")


@contextmanager
def busy(on: bool):
    """A CPU-bound competitor process while the block runs (``on``)."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if on else None
    try:
        yield
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()


def parser(description: str, seeds: str = "0 1 2") -> argparse.ArgumentParser:
    """Arguments every benchmark takes: seeds (``seeds``: the default, in words where not
    ``0 1 2``) and an optional Markdown file to publish to."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help=f"default: {seeds}")
    p.add_argument(
        "--append", type=Path, help="put the section into this Markdown file (replacing its own)"
    )
    return p


def runs_parser(description: str) -> argparse.ArgumentParser:
    """Arguments of a benchmark that evaluates trained runs: the run dirs, ``--episodes``, the
    evaluations' ``--seed`` and an optional Markdown file to publish to."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("runs", type=Path, nargs="+", help="trained run dirs")
    p.add_argument("--episodes", type=int, default=100)
    p.add_argument("--seed", type=int, default=7, help="the evaluations' seed")
    p.add_argument("--append", type=Path, help="put the section into this Markdown file")
    return p


def kept_figures(run: Path, kept: str) -> Path:
    """Where :func:`run_figures` keeps a run's figures."""
    return run / "evaluation" / kept


def run_figures(run: Path, kept: str, compute: Callable[[Path, LoadedRun], dict]) -> dict:
    """A trained run's figures: read back from ``<run>/evaluation/<kept>`` where an earlier call
    kept them, else ``compute(run, loaded)`` on the loaded run (closed after) and kept there."""
    out = kept_figures(run, kept)
    if out.exists():
        return json.loads(out.read_text())
    loaded = load_run(run)
    try:
        figures = compute(run, loaded)
    finally:
        loaded.algo.close()
    out.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(out, (json.dumps(figures, indent=2) + "\n").encode())
    return figures


def run_rows(
    runs: Sequence[Path],
    kept: str,
    compute: Callable[[Path, LoadedRun], dict],
    row: Callable[[Path, dict], list[str]],
    what: str,
) -> tuple[list[list[str]], str]:
    """A row per trained run from its figures (:func:`run_figures`), and the section's load
    line, which says how many were read back: their ``what``, which the load does not change."""
    start = os.getloadavg()
    read_back = sum(kept_figures(run, kept).exists() for run in runs)
    rows = [row(run, run_figures(run.resolve(), kept, compute)) for run in runs]
    return rows, (
        f"{load_span(start, os.getloadavg())} of this call; {read_back} of {len(runs)} runs read "
        f"back from earlier calls ({what}, which the load does not change)"
    )


@torch.no_grad()
def greedy_episodes(policy: TensorDictModuleBase, env: EnvBase, quota: list[int]) -> list[dict]:
    """Greedy episodes of ``policy`` on ``env``'s copies in lock-step, copy ``i`` running
    ``quota[i]`` of them: each episode's copy, order on that copy (0, 1, ...), return, steps,
    whether it was truncated, and its last reward."""
    copies, done_eps, episodes = env.batch_size.numel(), [0] * len(quota), []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        while any(d < q for d, q in zip(done_eps, quota)):
            td, nxt = env.step_and_maybe_reset(policy(td))
            step = td["next"]
            ended = step["done"].reshape(copies).tolist()
            if any(ended):
                keys = ("episode_reward", "step_count", "truncated", "reward")
                ret, steps, truncated, last = (step[k].reshape(copies).tolist() for k in keys)
            for i in (i for i, e in enumerate(ended) if e and done_eps[i] < quota[i]):
                episodes.append(
                    {
                        "copy": i,
                        "order": done_eps[i],
                        "return": float(ret[i]),
                        "steps": int(steps[i]),
                        "truncated": bool(truncated[i]),
                        "last_reward": float(last[i]),
                    }
                )
                done_eps[i] += 1
            td = nxt
    return episodes


def run_name(run: Path) -> str:
    """A run dir's name in a table: its path from here, less ``benchmarks/results/`` and a last
    ``run`` folder (presets.py's layout, ``<preset>/seed<N>/run``)."""
    return os.path.relpath(run.parent if run.name == "run" else run).removeprefix(
        "benchmarks/results/"
    )


def evaluated(out: Path, *keys: str) -> dict:
    """The JSON summary of ``python -m rlpipe.evaluate <keys> out=<out>``, run only while ``out``
    is not there (a later call reads it back); a failure raises its command and stderr."""
    if not out.exists():
        proc = subprocess.run(
            [sys.executable, "-m", "rlpipe.evaluate", *keys, f"out={out}"],
            capture_output=True,
            text=True,
        )
        failed = f"rlpipe.evaluate {' '.join(keys)} failed: {proc.stderr.strip()}"
        check(proc.returncode == 0, failed)
    return json.loads(out.read_text())


def budget_parser(description: str, frames: int, eval_every: int) -> argparse.ArgumentParser:
    """:func:`parser` plus a frame budget and the greedy-evaluation cadence."""
    p = parser(description)
    p.add_argument("--frames", type=int, default=frames)
    p.add_argument("--eval-every", type=int, default=eval_every)
    p.add_argument("--eval-episodes", type=int, default=20)
    return p


def cpu_model(cpuinfo: str | None = None) -> str:
    """The CPU by name, family and model, and the widest vector instructions it has (from
    ``cpuinfo``, the text of Linux's /proc/cpuinfo, read when not given; where there is none,
    what ``platform`` knows): torch's kernels, and so a run's rounding, follow them, so the
    same seed can take another path on another CPU."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return platform.processor() or platform.machine()
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    flags = set(fields.get("flags", "").split())
    vector = next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), "")
    model = fields.get("model")
    details = [f"family {fields.get('cpu family', '?')}, model {model}"] if model else []
    details += [vector.removesuffix("f")] if vector else []
    name = fields.get("model name", platform.processor() or platform.machine())
    return f"{name} ({', '.join(details)})" if details else name


def machine(packages: Sequence[str]) -> str:
    """One line naming the machine (its CPU: :func:`cpu_model`) and the versions that matter."""
    versions = []
    for name in packages:
        try:
            versions.append(f"{name} {version(name)}")
        except PackageNotFoundError:
            versions.append(f"{name} (not installed)")
    return (
        f"{date.today()} · {platform.system()} {platform.machine()}, {cpu_model()}, "
        f"{os.cpu_count()} cores · "
        f"Python {platform.python_version()} · " + ", ".join(versions)
    )


def ratio_cell(ratios: Sequence[float]) -> str:
    """A ratio's median over rounds with its range, e.g. ``1.85× (1.74–1.90)`` (one round: no
    range)."""
    middle = f"{statistics.median(ratios):.2f}×"
    return middle + (f" ({min(ratios):.2f}–{max(ratios):.2f})" if len(ratios) > 1 else "")


def table(headers: Sequence[str], rows: Sequence[Sequence[object]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def train_with_evals(
    overrides: list[str],
    seed: int,
    episodes: int,
    max_steps: int,
    target: float | None = None,
    *,
    eval_every: int = 0,
    max_frames: int | None = None,
) -> list[dict]:
    """Train step by step with a greedy eval after each (or, with ``eval_every``, after the first
    step at or past each multiple of that many frames); one row per eval (stops at ``target``,
    or after the eval at ``max_frames``). Training seconds exclude evaluation."""
    cfg = compose_run(*overrides, f"seed={seed}")
    seed_everything(seed)
    eval_env = make_env(cfg.env, num_envs=min(episodes, 32), seed=seed + 10_000)
    algo = make_algorithm(partial(make_env, cfg.env, seed=seed), cfg.algo)
    rows, seconds, episode_frames, next_eval = [], 0.0, 0, eval_every
    try:
        for step in range(max_steps):
            start = time.perf_counter()
            metrics = algo.train_step()
            seconds += time.perf_counter() - start
            episode_frames += int(sum(metrics.get("train/episode_length", [])))
            capped = max_frames is not None and algo.frames >= max_frames
            if eval_every and algo.frames < next_eval and not capped:
                continue
            next_eval = (algo.frames // max(eval_every, 1) + 1) * eval_every
            mean = evaluate(algo.policy, eval_env, episodes).mean
            rows.append(
                {
                    "epoch": step + 1,
                    "eval": mean,
                    "frames": algo.frames,
                    "episode_frames": episode_frames,
                    "seconds": seconds,
                }
            )
            if capped or (target is not None and mean >= target):
                break
    finally:
        algo.close()
        eval_env.close()
    return rows


def first_hit(rows: list[dict], target: float) -> dict | None:
    return next((r for r in rows if r["eval"] >= target - 1e-6), None)


def hit_cells(hit: dict | None, unit: str) -> list[str]:
    if hit is None:
        return ["not reached", "–"]
    return [f"{hit[unit]:,}", f"{hit['seconds']:.1f}"]


def read_scalar(run_dir: Path, name: str) -> list[tuple[int, float]]:
    """(frames, value) rows of one metric written by the CSV logger."""
    path = run_dir / "metrics" / "scalars" / f"{name}.csv"
    with open(path) as f:
        return [(int(step), float(value)) for step, value in csv.reader(f)]


def replace_section(path: str | Path, text: str) -> None:
    """Put ``text`` (a Markdown section starting with its ``## `` heading) into ``path``: in place
    of the section(s) with the same heading, or at the end; the rest of the file is kept, one
    blank line between sections."""
    path = Path(path)
    heading = text.splitlines()[0]
    old = path.read_text() if path.is_file() else ""
    sections = [s.rstrip("\n") for s in re.split(r"(?m)^(?=## )", old) if s.strip()]
    same = [i for i, s in enumerate(sections) if s.splitlines()[0] == heading]
    kept = [s for i, s in enumerate(sections) if i not in same]
    kept.insert(same[0] if same else len(kept), text.rstrip("\n"))
    path.write_text("\n\n".join(kept) + "\n")


def publish_section(text: str, append: str | Path | None) -> None:
    """Print a benchmark's section and, with ``append``, put it in that Markdown file in place of
    its previous version (:func:`replace_section`)."""
    print(text)
    if append:
        replace_section(append, text)


def section_head(title: str, packages: Sequence[str], load: str, *facts: str) -> list[str]:
    """The top of a benchmark's section of BENCHMARKS.md: ``## <title> (benchmarks/<script>)``,
    then the machine and versions, the load, the exact command and ``facts``, a line each."""
    script = f"benchmarks/{Path(sys.argv[0]).name}"
    command = shlex.join(["python", script, *sys.argv[1:]])
    head = [f"## {title} ({script})", "", f"- machine: {machine(packages)}", f"- load: {load}"]
    return [*head, f"- command: `{command}`", *(f"- {fact}" for fact in facts), ""]


def load_span(start: Sequence[float], end: Sequence[float]) -> str:
    """The 1/5/15-min load averages at a measurement's start and end, in words."""
    at = [", ".join(f"{x:.2f}" for x in load) for load in (start, end)]
    return f"1/5/15-min load average {at[0]} at the start, {at[1]} at the end"


def time_ars(seed: int, iterations: int, *overrides: str) -> dict:
    """``iterations`` ARS iterations on BipedalWalker-v3 with the notebook's settings
    (``algo=ars env=bipedal ~tuned``, not the tuned preset the main job picks) plus
    ``overrides``: env steps, wall seconds, rollout CPU seconds, start-up seconds, final θ."""
    cfg = compose_run("algo=ars", "env=bipedal", "~tuned", f"seed={seed}", *overrides)
    seed_everything(seed)
    start = time.perf_counter()
    algo = make_algorithm(partial(make_env, cfg.env, seed=seed), cfg.algo)
    algo.search.start()  # workers (processes, Ray actors) start here, not in the first iteration
    startup = time.perf_counter() - start
    try:
        start, cpu = time.perf_counter(), 0.0
        for _ in range(iterations):
            cpu += algo.train_step()["time/rollout_cpu_seconds"]
        return {
            "steps": algo.frames,
            "seconds": time.perf_counter() - start,
            "cpu": cpu,
            "startup": startup,
            "theta": algo.search.theta,
        }
    finally:
        algo.close()
