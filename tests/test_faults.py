"""Run integrity (issue "Run integrity"), files: runs killed at every fault point resume intact,
and damaged or foreign inputs are refused in one line without touching the run dir (the harness:
tests/fault_harness.py; processes and signals: tests/test_faults_processes.py)."""

from __future__ import annotations

import re
import sys
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from conftest import BASE, NEWEST
from fault_harness import (
    ALGOS,
    CHAINS,
    FAULTS,
    assert_no_live_processes,
    assert_rows_once,
    assert_run_intact,
    assert_same_run,
    csv_bytes,
    cut_rows,
    error_line,
    expected_returncode,
    rlpipe,
    snapshot,
)

from rlpipe.checkpoint import load_checkpoint
from rlpipe.rundir import RunDir

# ---------------------------------------------------------------------------------------------
# the kill matrix


def _kill_cases() -> list:
    cases = []
    for algo in ALGOS:
        for chain in CHAINS:
            marks = () if algo == "dqn" else (FAULTS,)
            cases.append(pytest.param(algo, chain, marks=marks, id=f"{algo}-{chain}"))
    return cases


@pytest.mark.parametrize(("algo", "chain"), _kill_cases())
def test_runs_killed_at_fault_points_resume_intact(tmp_path, reference, algo, chain):
    run_dir = tmp_path / "run"
    args = ["progress=false", *ALGOS[algo], f"hydra.run.dir={run_dir}"]
    tag = uuid.uuid4().hex
    ref = reference(algo)
    for fault in CHAINS[chain]:
        before = csv_bytes(run_dir) if fault == "truncate" else {}
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
            after = csv_bytes(run_dir)
            assert after.keys() == before.keys()
            for path, data in before.items():
                assert after[path] in (data, cut_rows(data, state["frames"])), path
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
    "unknown-env-id": (["env=gym", "env.id=Nope-v0"], "cannot make gymnasium env 'Nope-v0'"),
    "bad-module-path": (["env=gym", "env.id=nomodule:X-v0"], "names module 'nomodule'"),
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


# a value refused before torch loads, and a network refused once envs and torch are up
@pytest.mark.parametrize("case", ["lr-inf", "bad-network-target"])
def test_a_bad_run_into_a_dir_that_was_there_keeps_it_empty(tmp_path, case):
    overrides, named = BAD_RUNS[case]
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
    text = re.sub("backend: (envpool|gymnasium)", "backend: auto", config.read_text())
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
