"""Run integrity (issue "Run integrity"): runs killed at every fault point resume intact, damaged
or foreign inputs are refused in one line without touching the run dir, a run dir belongs to one
run and one process, and damaged checkpoints and metric tails are set aside at resume.

Faults are injected with ``RLPIPE_FAULT=<point>[@<n>][:<SIGNAL>]`` (:mod:`rlpipe.faults`). The
DQN share runs in CI; every other algorithm's share is marked ``faults`` (``pytest -m faults``).
Every subprocess carries a unique ``RLPIPE_TEST_TAG`` so that no process of a run (ARS workers
included) may outlive it unnoticed.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from unittest import mock

import pytest
import torch
from conftest import BASE, NEWEST, run_module

from rlpipe.checkpoint import load_checkpoint
from rlpipe.rundir import RunDir

FAULTS = pytest.mark.faults
TAG_VAR = "RLPIPE_TEST_TAG"
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
# a run dir takes 3-4 runs instead of 2-3 per point (each run costs ~10 s of imports).
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
        env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    env.pop("HYDRA_FULL_ERROR", None)
    return subprocess.Popen(
        [sys.executable, "-m", "rlpipe", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def live_processes(tag: str) -> list[int]:
    """PIDs of live processes (zombies have no environment) whose environment holds ``tag``."""
    needle = f"{TAG_VAR}={tag}".encode()
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            environ = (entry / "environ").read_bytes()
        except OSError:  # gone, or not ours to read
            continue
        if needle in environ.split(b"\0"):
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


# ---------------------------------------------------------------------------------------------
# the kill matrix


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Callable[[str], Reference]:
    """The reference of an algorithm's kill-matrix config: one uninterrupted run each (made on
    first use)."""
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


def _kill_cases() -> list:
    cases = []
    for algo in ALGOS:
        for chain in CHAINS:
            marks = () if algo == "dqn" else (FAULTS,)
            cases.append(pytest.param(algo, chain, marks=marks, id=f"{algo}-{chain}"))
    return cases


def _csv_bytes(run_dir: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in (run_dir / "metrics" / "scalars").rglob("*.csv")}


def _cut(data: bytes, frames: int) -> bytes:
    """A metric CSV's rows logged at ``frames`` or before."""
    lines = data.split(b"\n")[:-1]
    return b"".join(line + b"\n" for line in lines if int(line.partition(b",")[0]) <= frames)


@pytest.mark.parametrize(("algo", "chain"), _kill_cases())
def test_runs_killed_at_fault_points_resume_intact(tmp_path, reference, algo, chain):
    run_dir = tmp_path / "run"
    args = ["progress=false", *ALGOS[algo], f"hydra.run.dir={run_dir}"]
    tag = uuid.uuid4().hex
    ref = reference(algo)
    for fault in CHAINS[chain]:
        before = _csv_bytes(run_dir) if fault == "truncate" else {}
        result = rlpipe(*args, cwd=tmp_path, tag=tag, fault=fault)
        # the fault fired: the run died of its signal (the truncate point is only reached when a
        # CSV has rows to cut)
        assert result.returncode == expected_returncode(fault), (fault, result.stderr)
        if fault.endswith(":SIGTERM"):
            last = result.stderr.strip().splitlines()[-1]
            assert "SIGTERM" in last and f"resume={run_dir}" in last, result.stderr
            assert "Traceback" not in result.stderr
            RunDir(run_dir).read_checkpoint()  # it checkpointed before it stopped
        if fault.startswith(("checkpoint_write", "best_write")):  # the temporary file written
            assert list((run_dir / "checkpoints").glob(".*.tmp")), "no checkpoint write killed"
        if fault in ("final_checkpoint", "summary"):  # after the final checkpoint, no summary
            assert RunDir(run_dir).read_checkpoint().state["frames"] == ref.frames
            assert not (run_dir / "summary.json").exists()
        if fault == "truncate":  # every CSV whole: its old bytes, or those cut to the checkpoint
            state = RunDir(run_dir).read_checkpoint().state
            after = _csv_bytes(run_dir)
            assert after.keys() == before.keys()
            for path, data in before.items():
                assert after[path] in (data, _cut(data, state["frames"])), path
            assert list((run_dir / "metrics").rglob(".*.tmp")), "no trimmed copy was killed"
        assert_rows_once(run_dir)
        assert_no_live_processes(tag)

    result = rlpipe(*args, cwd=tmp_path, tag=tag)
    assert result.returncode == 0, result.stderr
    if CHAINS[chain][-1] in ("final_checkpoint", "summary"):
        assert "already finished" in result.stdout, result.stdout
    assert_run_intact(run_dir, ref, tag=tag)
    assert_same_run(run_dir, ref.run_dir)  # killed and resumed: the uninterrupted run, exactly


# ---------------------------------------------------------------------------------------------
# a finished tiny DQN run, and inputs damaged in it


def _rewrite_newest(run_dir: Path, change: Callable[[dict], None]) -> None:
    """Load the newest checkpoint, ``change`` its state, save it back (a zip archive still)."""
    path = run_dir / "checkpoints" / NEWEST
    state = load_checkpoint(path)
    change(state)
    torch.save(state, path)


def _drop_key(state: dict) -> None:
    del state["algo"]["optimizer"]


def _wrong_shape(state: dict) -> None:
    weights = state["algo"]["loss"]
    key = next(k for k, v in weights.items() if torch.is_tensor(v) and v.dim() == 2)
    weights[key] = torch.zeros(weights[key].shape[0] + 1, weights[key].shape[1])


def _bad_rng(state: dict) -> None:
    state["rng"]["torch"] = torch.zeros(8, dtype=torch.uint8)


def _negative_frames(state: dict) -> None:
    state["frames"] = -100


def _damage_all(run_dir: Path) -> None:
    for path in (run_dir / "checkpoints").glob("ckpt_*.pt"):
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


# case -> (damage done to the run dir, extra overrides, what the error line names)
TAMPERING: dict[str, tuple[Callable[[Path], None], list[str], str]] = {
    "ckpt-missing-key": (lambda d: _rewrite_newest(d, _drop_key), [], NEWEST),
    "ckpt-wrong-shape": (lambda d: _rewrite_newest(d, _wrong_shape), [], NEWEST),
    "ckpt-bad-rng": (lambda d: _rewrite_newest(d, _bad_rng), [], NEWEST),
    "ckpt-negative-frames": (lambda d: _rewrite_newest(d, _negative_frames), [], NEWEST),
    "every-ckpt-damaged": (_damage_all, [], "every checkpoint in"),
    "config-empty": (lambda d: (d / "config.yaml").write_bytes(b""), [], "config.yaml"),
    "config-garbage": (
        lambda d: (d / "config.yaml").write_bytes(b"\xff\x00{[: not: a config"),
        [],
        "config.yaml",
    ),
    "config-bad-value": (
        lambda d: (d / "config.yaml").write_text(
            (d / "config.yaml").read_text().replace("\nseed: 0\n", "\nseed: -1\n")
        ),
        [],
        "config.yaml",
    ),
    "seed-negative": (lambda d: None, ["seed=-1"], "seed"),
    "seed-too-large": (lambda d: None, ["seed=4294967296"], "seed"),
}


@pytest.mark.parametrize("case", TAMPERING)
def test_a_damaged_input_is_one_line_and_changes_nothing(tmp_path, run_copy, case):
    damage, overrides, named = TAMPERING[case]
    damage(run_copy)
    before = snapshot(run_copy)
    result = rlpipe(*BASE, *overrides, f"hydra.run.dir={run_copy}", cwd=tmp_path)
    assert named in error_line(result)
    assert snapshot(run_copy) == before


# a config or env error found once the job runs: (overrides, what the error line names)
BAD_RUNS = {
    "unknown-env-id": (["env=gym", "env.id=Nope-v0"], "Nope-v0"),
    "bad-module-path": (["env=gym", "env.id=nomodule:X-v0"], "nomodule"),
    "dqn-on-continuous": (["env=pendulum"], "DQN needs a discrete action space"),
    "sac-on-discrete": (["algo=sac"], "SAC needs continuous actions"),
    "tuple-observation": (["env=gym", "env.id=Blackjack-v1"], "Tuple observation space"),
    "bad-network-target": (["algo.network._target_=torch.nn.Nope"], "torch.nn has no Nope"),
    "lr-inf": (["algo.lr=inf"], "algo.lr must be a finite number > 0, got inf"),
}


@pytest.mark.parametrize("case", BAD_RUNS)
def test_a_bad_config_or_env_is_one_line_and_writes_nothing(tmp_path, case):
    overrides, named = BAD_RUNS[case]
    run_dir = tmp_path / "outputs" / "day" / "run"  # none of it exists yet
    result = rlpipe(*BASE, *overrides, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert named in error_line(result)
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no dir, no log, no lock
    existing = tmp_path / "mine"  # a dir that was there: kept, and nothing written in it
    existing.mkdir()
    result = rlpipe(*BASE, *overrides, f"hydra.run.dir={existing}", cwd=tmp_path)
    assert named in error_line(result)
    assert existing.is_dir() and not any(existing.iterdir())


def test_an_unknown_key_with_cfg_job_is_one_line(run_copy, monkeypatch, capsys):
    from rlpipe.__main__ import main  # no Hydra job runs: the overrides are checked first

    before = snapshot(run_copy)
    argv = ["--cfg", "job", "+algo.nope=1", f"hydra.run.dir={run_copy}"]
    monkeypatch.setattr(sys, "argv", ["rlpipe", *argv])
    with pytest.raises(SystemExit) as exit_info:
        main()
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: "), lines
    assert "algo.nope" in lines[0]
    assert snapshot(run_copy) == before


def test_evaluate_refuses_a_run_dir_whose_env_would_import_a_module(
    tmp_path, run_copy, monkeypatch, capsys
):
    from rlpipe.evaluate import main

    config = run_copy / "config.yaml"
    text = config.read_text().replace("backend: envpool", "backend: auto")  # as a custom env's
    config.write_text(text.replace("id: CartPole-v1", "id: evilmod:Foo-v0"))
    marker = tmp_path / "evilmod-was-imported"
    (tmp_path / "evilmod.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    monkeypatch.chdir(tmp_path)  # as `python -m rlpipe.evaluate` run here: importable
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "evilmod", raising=False)
    before = snapshot(run_copy)
    with pytest.raises(SystemExit) as exit_info:
        main([f"run_dir={run_copy}"])
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: "), lines
    assert "allow_env_import" in lines[0]
    assert not marker.exists() and "evilmod" not in sys.modules
    assert snapshot(run_copy) == before
    # the control: trusted, the run dir's env module is imported (then Foo-v0 is not found)
    with pytest.raises(SystemExit):
        main([f"run_dir={run_copy}", "allow_env_import=true"])
    assert marker.exists()


# ---------------------------------------------------------------------------------------------
# a run dir belongs to one run and one process


@pytest.mark.parametrize(
    ("override", "key"),
    [("algo.hidden_sizes=[64,64]", "algo.hidden_sizes"), ("seed=1", "seed")],
    ids=["architecture", "seed"],
)
def test_another_run_is_refused_and_the_run_still_evaluates(
    tmp_path, run_copy, capsys, override, key
):
    from rlpipe.evaluate import main

    before = snapshot(run_copy)
    result = rlpipe(*BASE, override, f"resume={run_copy}", cwd=tmp_path)
    line = error_line(result)
    assert f"{run_copy} belongs to another run: it differs in {key} (" in line
    assert snapshot(run_copy) == before
    main([f"run_dir={run_copy}", "episodes=1"])  # the run is still whole
    assert "over 1 episodes" in capsys.readouterr().out


def test_a_larger_total_frames_continues_the_run(tmp_path, run_copy):
    tag = uuid.uuid4().hex
    result = rlpipe(*with_frames(BASE, 300), f"resume={run_copy}", cwd=tmp_path, tag=tag)
    assert result.returncode == 0, result.stderr
    assert_run_intact(run_copy, Reference(300, (100, 200, 300)), tag=tag)


def test_resuming_a_finished_run_twice_changes_nothing(tmp_path, run_copy):
    def kept() -> dict[str, bytes]:
        return {
            name: data
            for name, data in snapshot(run_copy).items()
            if name == "summary.json" or name.startswith(("metrics/", "checkpoints/"))
        }

    before = kept()
    for _ in range(2):
        result = rlpipe(*BASE, f"hydra.run.dir={run_copy}", cwd=tmp_path)
        assert result.returncode == 0, result.stderr
        assert "already finished" in result.stdout, result.stdout
        assert kept() == before  # summary.json byte-identical, no row logged, no checkpoint
    assert_run_intact(run_copy, Reference(200, (100, 200)))


def test_sweep_jobs_sharing_one_dir_fail_apart_from_it(tmp_path):
    sweep = tmp_path / "sweep"
    result = rlpipe(
        "-m",
        "seed=0,1",
        *BASE,
        f"hydra.sweep.dir={sweep}",
        "hydra.sweep.subdir=same",
        cwd=tmp_path,
    )
    assert result.returncode == 1, result.stderr
    assert "sweep of 1 jobs, 0 failed, 1 rejected" in result.stdout, result.stdout
    errors = [line for line in result.stderr.splitlines() if line.startswith("rlpipe: error:")]
    assert len(errors) == 1, result.stderr
    refusal = f"{sweep / 'same'} belongs to another run: it differs in seed (1 here, 0 there)"
    assert refusal in errors[0]
    rejected = json.loads((sweep / "rejected" / "1" / "error.json").read_text())
    assert "belongs to another run" in rejected["error"]
    assert "seed: 0\n" in (sweep / "same" / "config.yaml").read_text()
    assert not (sweep / "same" / "error.json").exists()
    assert_run_intact(sweep / "same", Reference(200, (100, 200)))


def _state(pid: int) -> str:
    """A process's state letter (``T``: stopped); ``""`` once it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except OSError:
        return ""


def test_two_resumes_at_once_one_is_refused(tmp_path, run_copy):
    tag = uuid.uuid4().hex
    args = [*with_frames(BASE, 300), f"resume={run_copy}"]
    # whichever takes the lock stops itself after its first iteration, lock held, so the other
    # surely meets it; it is continued once the other has given up
    procs = [popen(*args, cwd=tmp_path, tag=tag, fault="train_step@1:SIGSTOP") for _ in range(2)]
    try:
        deadline = time.monotonic() + RUN_TIMEOUT
        while all(p.poll() is None for p in procs):
            assert time.monotonic() < deadline, "neither resume ended"
            time.sleep(0.1)
        loser = next(p for p in procs if p.returncode is not None)
        winner = next(p for p in procs if p is not loser)
        _, stderr = loser.communicate()
        lines = stderr.strip().splitlines()
        assert loser.returncode == 2 and len(lines) == 1, stderr
        assert lines[0].startswith("rlpipe: error: ")
        assert f"{run_copy} is in use by another rlpipe process (pid {winner.pid})" in lines[0]
        while _state(winner.pid) not in ("T", "Z", ""):
            assert time.monotonic() < deadline, "the winner never reached its first iteration"
            time.sleep(0.1)
        os.kill(winner.pid, signal.SIGCONT)
        _, stderr = winner.communicate(timeout=RUN_TIMEOUT)
        assert winner.returncode == 0, stderr
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert_run_intact(run_copy, Reference(300, (100, 200, 300)), tag=tag)


# ---------------------------------------------------------------------------------------------
# retention and metric tails


def test_a_damaged_newest_checkpoint_is_set_aside_and_one_is_kept(tmp_path, run_copy):
    checkpoints = run_copy / "checkpoints"
    newest = checkpoints / NEWEST
    torn = newest.read_bytes()[: newest.stat().st_size // 2]
    newest.write_bytes(torn)
    orphan = checkpoints / ".ckpt_000000000999.pt.tmp"  # a write that was killed
    orphan.write_bytes(b"half a checkpoint")
    tag = uuid.uuid4().hex
    args = ["checkpoint_every=100", "keep_checkpoints=1", f"resume={run_copy}"]
    result = rlpipe(*with_frames(BASE, 300), *args, cwd=tmp_path, tag=tag)
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.startswith("rlpipe: warning:")]
    assert any(NEWEST in line and "damaged" in line for line in warnings), result.stderr
    assert (checkpoints / "damaged" / NEWEST).read_bytes() == torn
    assert not orphan.exists()
    kept = sorted(checkpoints.glob("ckpt_*.pt"))
    assert [p.name for p in kept] == ["ckpt_000000000300.pt"]
    assert load_checkpoint(kept[0])["frames"] == 300
    assert_run_intact(run_copy, Reference(300, (100, 200, 300)), tag=tag)

    result = rlpipe(*with_frames(BASE, 400), *args, cwd=tmp_path, tag=tag)  # and once more
    assert result.returncode == 0, result.stderr
    assert [p.name for p in checkpoints.glob("ckpt_*.pt")] == ["ckpt_000000000400.pt"]
    assert_run_intact(run_copy, Reference(400, (100, 200, 300, 400)), tag=tag)


def test_damaged_metric_tails_are_cut_with_a_warning(tmp_path, run_copy):
    scalars = run_copy / "metrics" / "scalars"
    nul = scalars / "eval" / "return_mean.csv"
    torn = scalars / "train" / "episode_return.csv"
    with open(nul, "ab") as f:
        f.write(b"\0" * 64)  # a power cut: the size grew, the data did not
    with open(torn, "ab") as f:
        f.write(b"12")  # killed in the middle of a row
    tag = uuid.uuid4().hex
    result = rlpipe(*with_frames(BASE, 300), f"resume={run_copy}", cwd=tmp_path, tag=tag)
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if line.startswith("rlpipe: warning:")]
    assert len(warnings) == 2, result.stderr
    for damaged in (nul, torn):
        assert any(str(damaged) in line for line in warnings), result.stderr
    assert_run_intact(run_copy, Reference(300, (100, 200, 300)), tag=tag)


# ---------------------------------------------------------------------------------------------
# signals in long iterations (the faults share)


@FAULTS
def test_sigterm_after_an_ars_iteration_keeps_its_row(tmp_path, reference):
    run_dir = tmp_path / "run"
    args = ["progress=false", *ALGOS["ars"], f"hydra.run.dir={run_dir}"]
    tag = uuid.uuid4().hex
    result = rlpipe(*args, cwd=tmp_path, tag=tag, fault="train_step@2:SIGTERM")
    assert result.returncode == 128 + signal.SIGTERM, result.stderr
    assert "resume=" in result.stderr.strip().splitlines()[-1], result.stderr
    result = rlpipe(*args, cwd=tmp_path, tag=tag)
    assert result.returncode == 0, result.stderr
    ref = reference("ars")
    frames = metric_rows(run_dir)["train/return_mean"]
    assert frames == ref.rows["train/return_mean"] and len(frames) == 4  # one per iteration
    assert_run_intact(run_dir, ref, tag=tag)
    assert_same_run(run_dir, ref.run_dir)


@pytest.mark.parametrize(
    ("stop", "exact"),
    [("train_step@20:SIGTERM", True), ("train_step@30:SIGTERM", False)],
    ids=["at-a-checkpoint", "between-checkpoints"],
)
def test_a_stopped_dqn_run_logs_no_row_the_uninterrupted_one_does_not(
    tmp_path, reference, stop, exact
):
    """SIGTERM after 400 frames (a checkpoint was due: the resumed run is the uninterrupted one)
    or after 600 (between checkpoints: the rows up to the stop are the uninterrupted run's, no
    row is logged at the stop, and the resumed run's training episodes start afresh there)."""
    run_dir = tmp_path / "run"
    args = ["progress=false", *ALGOS["dqn"], "log_every=100", f"hydra.run.dir={run_dir}"]
    result = rlpipe(*args, cwd=tmp_path, fault=stop)
    assert result.returncode == 128 + signal.SIGTERM, result.stderr
    stopped = RunDir(run_dir).read_checkpoint().frames
    reference_dir = tmp_path / "reference"
    result = rlpipe(*args[:-1], f"hydra.run.dir={reference_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    ours, theirs = metric_files(run_dir), metric_files(reference_dir)
    assert ours and set(ours) <= set(theirs)
    for name, data in ours.items():  # the stop logged no row of its own
        assert data == _cut(theirs[name], stopped), name
    result = rlpipe(*args, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    rows, expected = metric_rows(run_dir), metric_rows(reference_dir)
    for name in set(rows) - EPISODE_METRICS:  # logged at the frames the reference logs at
        assert rows[name] == expected[name], name
    if exact:
        assert_same_run(run_dir, reference_dir)


def _stopped_within_ten_seconds(
    proc: subprocess.Popen, ready: Callable[[], None], settle: float
) -> str:
    """SIGTERM to ``proc`` once ``ready()`` returns and ``settle`` seconds more have passed; its
    stderr, after checking that it exited by the signal within ten seconds of it."""
    try:
        ready()
        time.sleep(settle)
        assert proc.poll() is None, "the run ended before the signal"
        sent = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=120)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert took <= 10, f"took {took:.1f} s to stop after SIGTERM"
    return stderr


@FAULTS
def test_reinforce_stops_within_seconds_of_sigterm_and_resumes_exactly(tmp_path):
    """A long REINFORCE epoch (6,000 episodes on 100 lock-step copies) cut by SIGTERM: the run
    checkpoints the previous epoch within seconds, and the resumed run is the uninterrupted one."""
    run_dir = tmp_path / "run"
    args = [
        "progress=false",
        "algo=reinforce",
        "env=cartpole_continuous",
        "algo.epochs=3",
        "algo.episodes_per_epoch=6000",
        "eval_every=1",
        "checkpoint_every=1",
        "eval_episodes=2",
        f"hydra.run.dir={run_dir}",
    ]
    tag = uuid.uuid4().hex
    proc = popen(*args, cwd=tmp_path, tag=tag)

    def ready() -> None:
        _wait_for(lambda: list((run_dir / "checkpoints").glob("ckpt_*.pt")), proc, "epoch 1")

    _stopped_within_ten_seconds(proc, ready, settle=0.5)
    result = rlpipe(*args, cwd=tmp_path, tag=tag)
    assert result.returncode == 0, result.stderr
    reference_dir = tmp_path / "reference"
    result = rlpipe(*args[:-1], f"hydra.run.dir={reference_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert_same_run(run_dir, reference_dir)
    assert_no_live_processes(tag)


def _wait_for(path_glob: Callable[[], list[Path]], proc: subprocess.Popen, what: str) -> None:
    deadline = time.monotonic() + RUN_TIMEOUT
    while not path_glob():
        if proc.poll() is not None:
            raise AssertionError(f"the run ended before {what}: {proc.communicate()[1]}")
        assert time.monotonic() < deadline, f"no {what}"
        time.sleep(0.05)


@FAULTS
@pytest.mark.parametrize("during", ["eval", "train_step"])
def test_mbrl_honours_sigterm_within_ten_seconds(tmp_path, during):
    run_dir = tmp_path / "run"
    checkpoints = run_dir / "checkpoints"
    args = [
        "algo=mbrl",
        "env=pendulum",
        "progress=false",
        "total_frames=4000",
        "eval_every=200",
        "checkpoint_every=200",
        f"hydra.run.dir={run_dir}",
    ]
    if during == "train_step":
        args.append("eval_episodes=1")  # the first checkpoint comes after the first evaluation
    tag = uuid.uuid4().hex
    proc = popen(*args, cwd=tmp_path, tag=tag)

    def ready() -> None:
        if during == "eval":  # the first iteration (one 200-step episode) ends, then it evaluates
            episodes = run_dir / "metrics" / "scalars" / "train" / "episode_return.csv"
            _wait_for(lambda: [episodes] if episodes.exists() else [], proc, "first episode")
        else:  # the first checkpoint is written, then the second iteration runs
            _wait_for(lambda: list(checkpoints.glob("ckpt_*.pt")), proc, "first checkpoint")

    stderr = _stopped_within_ten_seconds(proc, ready, settle=1.0)
    assert f"resume={run_dir}" in stderr.strip().splitlines()[-1], stderr
    assert list(checkpoints.glob("ckpt_*.pt"))
    RunDir(checkpoints.parent).read_checkpoint()
    assert_no_live_processes(tag)
