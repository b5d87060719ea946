"""Run integrity (issue "Run integrity"), processes: a run dir belongs to one run and one
process, damaged checkpoints and metric tails are set aside at resume, and long iterations
honour signals (the harness: tests/fault_harness.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import BASE, NEWEST
from fault_harness import (
    ALGOS,
    EPISODE_METRICS,
    FAULTS,
    RUN_TIMEOUT,
    Reference,
    assert_no_live_processes,
    assert_run_intact,
    assert_same_run,
    cut_rows,
    error_line,
    metric_files,
    metric_rows,
    popen,
    rlpipe,
    snapshot,
    with_frames,
)

from rlpipe.checkpoint import load_checkpoint
from rlpipe.rundir import RunDir

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
    assert "over 1 episode on one env (" in capsys.readouterr().out


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
        assert data == cut_rows(theirs[name], stopped), name
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
