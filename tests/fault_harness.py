"""The fault-injection harness of tests/test_faults*.py: the kill matrix's tiny run per algorithm
and its fault chains, subprocess runs tagged so that none outlives its test, the checks that a
run dir is intact, and the reference runs each kill is compared with.

Faults are injected with ``RLPIPE_FAULT=<point>[@<n>][:<SIGNAL>]`` (:mod:`rlpipe.faults`). The
DQN share runs in CI; every other algorithm's share is marked ``faults`` (``pytest -m faults``).
Every subprocess carries a unique ``RLPIPE_TEST_TAG`` (a forked run, tests/warm.py, also its own
session) so that no process of a run (ARS workers included) may outlive it unnoticed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from unittest import mock

import pytest
import warm
from conftest import run_module, start_module
from warm import TAG_VAR

from rlpipe.checkpoint import load_checkpoint
from rlpipe.rundir import RunDir

FAULTS = pytest.mark.faults
RUN_TIMEOUT = 900  # seconds for one subprocess run (2 shared cores: runs can crawl)
IGNORED = {".lock", "rlpipe.log"}  # the last PID, Hydra's job log: may change on a refusal
# several training episodes may end in one step: these rows share frames, every other metric's
# frames are strictly increasing (one row per logging event)
EPISODE_METRICS = {"train/episode_return", "train/episode_length"}

# the kill matrix's runs, one tiny config per algorithm
ALGOS = {
    # 20 frames (2 envs x 10 steps) per iteration: 60 iterations (4 frames: 300, 4x slower)
    "dqn": [
        "total_frames=1200",
        "eval_every=400",
        "checkpoint_every=400",
        "eval_episodes=2",
        "algo.learning_starts=64",
        "algo.batch_size=32",
        "algo.frames_per_batch=20",
        "env.num_envs=2",
    ],
    # eval_every/checkpoint_every are frame cadences; 1 frame: after every epoch (iteration)
    "reinforce": [
        "algo=reinforce",
        "env=cartpole_continuous",
        "algo.epochs=4",
        "algo.episodes_per_epoch=4",
        "algo.updates_per_epoch=2",
        "eval_every=1",
        "checkpoint_every=1",
        "eval_episodes=2",
    ],
    "ars": [
        "algo=ars",
        "env=pendulum",
        "algo.iterations=4",
        "algo.num_directions=2",
        "algo.num_best=2",
        "algo.episode_length=50",
        "algo.workers=2",
        "eval_every=1",
        "checkpoint_every=1",
        "eval_episodes=2",
    ],
    "mbrl": [
        "algo=mbrl",
        "env=pendulum",
        "total_frames=600",
        "algo.frames_per_batch=100",
        "algo.warmup_frames=200",
        "algo.fit_steps=5",
        "algo.num_candidates=20",
        "algo.horizon=5",
        "algo.cem_iterations=2",
        "eval_every=200",
        "checkpoint_every=200",
        "eval_episodes=1",
        "env.max_episode_steps=50",
    ],
    "ppo": [
        "algo=ppo",
        "env=pendulum",
        "total_frames=600",
        "algo.frames_per_batch=100",
        "algo.minibatch_size=50",
        "algo.epochs=2",
        "algo.anneal_lr=true",
        "algo.normalize_observations=true",
        "eval_every=200",
        "checkpoint_every=200",
        "eval_episodes=1",
        "env.max_episode_steps=50",
    ],
    "sac": [
        "algo=sac",
        "env=pendulum",
        "total_frames=300",
        "algo.learning_starts=50",
        "algo.batch_size=32",
        "algo.frames_per_batch=10",
        "algo.updates_per_batch=5",
        "eval_every=100",
        "checkpoint_every=100",
        "eval_episodes=1",
        "env.max_episode_steps=50",
    ],
}
# the algorithms' own defaults: the tuned settings of a pair (conf/tuned/) are not these runs'
ALGOS = {name: ["~tuned", *args] for name, args in ALGOS.items()}
# The kill matrix covers every fault point in chains of runs in one run dir: each run resumes the
# dir the previous one's fault left (the same command, the next fault), the last runs clean. A
# point's kill is followed by the resume the contract describes, in the code path it names, and
# a run dir takes 3-4 runs instead of 2-3 per point.
CHAINS = {
    # killed before the first checkpoint; the resume starts at zero and is killed after its
    # final checkpoint, before summary.json; the clean resume only writes summary.json
    "train_step+final_checkpoint": ["train_step@1", "final_checkpoint"],
    # killed in the first evaluation (before the first checkpoint); the resume starts at zero
    # and gets SIGTERM in its first evaluation: it checkpoints with the evaluation pending
    "eval_sigkill+eval_sigterm": ["eval@1", "eval@1:SIGTERM"],
    # killed writing the second checkpoint (rows past the first one are in the CSVs); the resume
    # is killed trimming them; the next one finishes and is killed with summary.json's temp file
    # written, not renamed; the clean resume writes it
    "checkpoint_write+truncate+summary": ["checkpoint_write@2", "truncate", "summary"],
    # killed writing the first best-eval checkpoint (before any checkpoint): the resume starts
    # at zero, its temporary file goes, and the run ends with one best checkpoint
    "best_write+final_checkpoint": ["best_write@1", "final_checkpoint"],
}


@dataclass(frozen=True)
class Reference:
    """What an uninterrupted run of a config ends with."""

    frames: int  # the final frames
    eval_frames: tuple[int, ...]  # frames of every eval/return_mean row
    rows: dict[str, list[int]] = field(default_factory=dict)  # every metric's frames
    run_dir: Path | None = None  # the uninterrupted run's dir


def with_frames(args: list[str], total_frames: int) -> list[str]:
    """``args`` with ``total_frames`` replaced."""
    return [a for a in args if not a.startswith("total_frames=")] + [f"total_frames={total_frames}"]


# ---------------------------------------------------------------------------------------------
# helpers


@contextmanager
def environment(tag: str, fault: str | None) -> Iterator[None]:
    """``os.environ`` for a subprocess of the run tagged ``tag`` (with ``RLPIPE_FAULT=fault``)."""
    with mock.patch.dict(os.environ, {TAG_VAR: tag}):
        os.environ.pop("RLPIPE_FAULT", None)
        if fault:
            os.environ["RLPIPE_FAULT"] = fault
        yield


def rlpipe(
    *args: str, cwd: Path, tag: str | None = None, fault: str | None = None
) -> subprocess.CompletedProcess:
    """``python -m rlpipe args...`` (conftest's ``run_module``), tagged (``tag`` None: a tag of
    its own), with ``fault`` injected."""
    with environment(tag or uuid.uuid4().hex, fault):
        return run_module("rlpipe", *args, cwd=cwd, timeout=RUN_TIMEOUT)


def popen(*args: str, cwd: Path, tag: str, fault: str | None = None) -> subprocess.Popen:
    """``python -m rlpipe args...`` started in the background (``run_module``'s environment)."""
    with environment(tag, fault):
        return start_module("rlpipe", *args, cwd=cwd)


def live_processes(tag: str) -> list[int]:
    """PIDs of live processes (zombies have no environment) whose environment holds ``tag``,
    or in the session of a forked run tagged ``tag`` (tests/warm.py)."""
    needle = f"{TAG_VAR}={tag}".encode()
    sessions = set(warm.SESSIONS.get(tag, ()))
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            environ = (entry / "environ").read_bytes()
            stat = (entry / "stat").read_text()
        except OSError:  # gone, or not ours to read
            continue
        session = int(stat.rpartition(")")[2].split()[3])  # state, ppid, pgrp, session
        if needle in environ.split(b"\0") or (session in sessions and environ):
            found.append(int(entry.name))
    return found


def assert_no_live_processes(tag: str, grace: float = 5.0) -> None:
    """No process of the run tagged ``tag`` is alive ``grace`` seconds from now, at the latest."""
    deadline = time.monotonic() + grace
    while (pids := live_processes(tag)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not pids, f"processes of the run outlived it: {pids}"


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every file under ``directory`` (but the lock file and Hydra's job log): path -> bytes."""
    return {
        str(path.relative_to(directory)): path.read_bytes()
        for path in sorted(directory.rglob("*"))
        if path.is_file() and path.name not in IGNORED
    }


def csv_frames(path: Path) -> list[int]:
    """The frames column of a metric CSV, which must hold only whole ``<frames>,<value>\\n`` rows
    (no torn line, no NUL bytes)."""
    data = path.read_bytes()
    assert data.endswith(b"\n") or not data, f"{path}: torn last line {data[-40:]!r}"
    frames = []
    for line in data.split(b"\n")[:-1]:
        step, comma, value = line.partition(b",")
        assert comma and step.isdigit() and b"," not in value, f"{path}: bad row {line!r}"
        float(value)  # raises on garbage
        frames.append(int(step))
    return frames


def metric_rows(run_dir: Path) -> dict[str, list[int]]:
    """Every metric of ``run_dir`` (``eval/return_mean``, ...) -> its frames column."""
    scalars = run_dir / "metrics" / "scalars"
    return {
        str(path.relative_to(scalars).with_suffix("")): csv_frames(path)
        for path in sorted(scalars.rglob("*.csv"))
    }


def assert_rows_once(run_dir: Path, end: int | None = None) -> dict[str, list[int]]:
    """Every metric row of ``run_dir`` whole and logged once: frames non-decreasing, strictly
    increasing but for episode metrics, none past ``end``; returns the rows' frames."""
    rows = metric_rows(run_dir)
    for name, frames in rows.items():
        assert frames == sorted(frames), f"{name}: frames go back: {frames}"
        if name not in EPISODE_METRICS:
            assert len(set(frames)) == len(frames), f"{name}: a row logged twice: {frames}"
        if end is not None and frames:
            assert frames[-1] <= end, f"{name}: rows past the end: {frames}"
    return rows


def assert_run_intact(run_dir: Path, reference: Reference, *, tag: str | None = None) -> None:
    """``run_dir`` holds a whole run that ended like ``reference``: ``summary.json`` and the newest
    loadable checkpoint at its final frames, every metric row logged exactly once (frames
    non-decreasing; strictly increasing but for episode metrics; none past the end), the
    evaluations at the reference's frames, no temporary file, and no process of the run alive."""
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["frames"] == reference.frames, summary
    rows = assert_rows_once(run_dir, reference.frames)
    assert tuple(rows["eval/return_mean"]) == reference.eval_frames
    temporary = [str(p) for p in run_dir.rglob("*.tmp")]
    assert not temporary, f"temporary files left: {temporary}"
    newest = RunDir(run_dir).read_checkpoint()
    path, state = newest.path, newest.state
    assert state["frames"] == reference.frames, path
    (best,) = RunDir(run_dir).bests()  # one best-eval checkpoint, of this run
    assert load_checkpoint(best)["frames"] <= reference.frames
    if tag is not None:
        assert_no_live_processes(tag)


def metric_files(run_dir: Path) -> dict[str, bytes]:
    """Every metric CSV of a run dir but the clocks (``time/``), by ``metrics/<group>/<name>``."""
    scalars = run_dir / "metrics" / "scalars"
    return {
        f"metrics/{path.relative_to(scalars)}": path.read_bytes()
        for path in sorted(scalars.rglob("*.csv"))
        if path.relative_to(scalars).parts[0] != "time"
    }


def same_run_files(run_dir: Path) -> dict[str, bytes]:
    """What a run dir must hold byte for byte like the uninterrupted run's (docs/resuming.md):
    every metric CSV but the clocks (``time/``), ``config.yaml``, ``summary.json`` but its
    ``wall_time`` and ``run_dir``, and the names of the checkpoints and videos kept."""
    files = metric_files(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    del summary["wall_time"], summary["run_dir"]
    files["summary.json"] = json.dumps(summary, sort_keys=True).encode()
    files["config.yaml"] = (run_dir / "config.yaml").read_bytes()
    for folder in ("checkpoints", "videos"):
        names = sorted(p.name for p in (run_dir / folder).glob("*") if p.is_file())
        files[f"{folder}/"] = "\n".join(names).encode()
    return files


def assert_same_run(run_dir: Path, reference: Path) -> None:
    """``run_dir`` ends as the uninterrupted ``reference`` run did (:func:`same_run_files`)."""
    ours, theirs = same_run_files(run_dir), same_run_files(reference)
    assert ours.keys() == theirs.keys(), sorted(ours.keys() ^ theirs.keys())
    different = [name for name in ours if ours[name] != theirs[name]]
    assert not different, {name: (ours[name][-120:], theirs[name][-120:]) for name in different}


def error_line(result: subprocess.CompletedProcess) -> str:
    """The one ``rlpipe: error:`` line a refused command printed (exit code 2, nothing else)."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: "), result.stderr
    return lines[0]


def expected_returncode(fault: str) -> int:
    """A run killed by ``fault``'s signal: -N for SIGKILL, 128 + N for a handled signal."""
    name = fault.partition(":")[2] or "SIGKILL"
    number = signal.Signals[name]
    return -number if number == signal.SIGKILL else 128 + number


def csv_bytes(run_dir: Path) -> dict[Path, bytes]:
    """Every metric CSV of ``run_dir``, as bytes."""
    return {p: p.read_bytes() for p in (run_dir / "metrics" / "scalars").rglob("*.csv")}


def cut_rows(data: bytes, frames: int) -> bytes:
    """A metric CSV's rows logged at ``frames`` or before."""
    lines = data.split(b"\n")[:-1]
    return b"".join(line + b"\n" for line in lines if int(line.partition(b",")[0]) <= frames)


def reference_runs(tmp_path_factory) -> Callable[[str], Reference]:
    """The reference of an algorithm's kill-matrix config: one uninterrupted run each (made on
    first use); conftest's session-scoped ``reference`` fixture."""
    cache: dict[str, Reference] = {}

    def get(algo: str) -> Reference:
        if algo not in cache:
            run_dir = tmp_path_factory.mktemp(f"reference-{algo}") / "run"
            tag = uuid.uuid4().hex
            args = ["progress=false", *ALGOS[algo], f"hydra.run.dir={run_dir}"]
            result = rlpipe(*args, cwd=run_dir.parent, tag=tag)
            assert result.returncode == 0, result.stderr
            rows = metric_rows(run_dir)
            frames = json.loads((run_dir / "summary.json").read_text())["frames"]
            cache[algo] = Reference(frames, tuple(rows["eval/return_mean"]), rows, run_dir)
            assert_run_intact(run_dir, cache[algo], tag=tag)  # the checks hold for it
        return cache[algo]

    return get
