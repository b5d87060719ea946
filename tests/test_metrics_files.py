"""Metric CSVs at resume and after crashes: rows cut back to the checkpoint exactly once,
atomic rewrites, damaged tails cut (truncate_metrics) or skipped (the readers)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rlpipe.errors import RlpipeError
from rlpipe.figures import plot_run
from rlpipe.files import TEMP_SUFFIX, check_writable
from rlpipe.metrics import parse_rows, truncate_metrics
from rlpipe.plot import main as plot_main
from rlpipe.rundir import RunDir
from rlpipe.runs import find_runs

ROWS = b"0,1.5\n100,2.5\n200,3.5\n"


def write_metric(run_dir: Path, name: str, data: bytes) -> Path:
    path = RunDir(run_dir).metric_path(name)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    return path


def warnings_of(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("rlpipe: warning:")]


@pytest.mark.parametrize(
    ("tail", "cause"),
    [
        pytest.param(b"\0" * 4096, "NUL bytes: a crash or power cut", id="nul-padding"),
        pytest.param(b"300,4.", "torn", id="torn-line"),  # killed in the middle of a write
    ],
)
def test_a_torn_tail_is_cut_with_one_warning(
    tmp_path: Path, tail: bytes, cause: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = write_metric(tmp_path, "eval/return_mean", ROWS + tail)
    truncate_metrics(RunDir(tmp_path).scalars_dir, 1_000)
    assert path.read_bytes() == ROWS
    lines = warnings_of(capsys.readouterr().err)
    assert lines == [
        f"rlpipe: warning: {path}: cut {len(tail)} bytes at the end ({cause} while writing)"
    ]
    assert not path.with_name("return_mean.csv.damaged").exists()


@pytest.mark.parametrize(
    ("data", "kept", "damaged", "said"),
    [
        pytest.param(  # the case: one garbage line among good rows
            b"0,1.0\ngarbage\n100,3.0\n150,4.0\n",
            b"0,1.0\n100,3.0\n150,4.0\n",
            b"garbage\n",
            "line 2 is not a `frames,value` row (damaged): moved it to loss.csv.damaged",
            id="garbage-line",
        ),
        pytest.param(
            b"0,1.0\n50,2.0\0\n100,3.0\n",
            b"0,1.0\n100,3.0\n",
            b"50,2.0\0\n",
            "line 2 is not a `frames,value` row",
            id="nul-in-a-line",
        ),
        pytest.param(
            ROWS + b"\0\0\0\n300,4.5\n",
            ROWS + b"300,4.5\n",
            b"\0\0\0\n",
            "line 4 is not",
            id="nul-line-then-rows",
        ),
        pytest.param(
            b"300\n" + ROWS + b"1,2,3\n",
            ROWS,
            b"300\n1,2,3\n",
            "lines 1, 5 are not a `frames,value` row (damaged): moved them to loss.csv.damaged",
            id="two-lines",
        ),
    ],
)
def test_a_damaged_line_is_moved_aside_and_every_intact_row_kept(
    tmp_path: Path,
    data: bytes,
    kept: bytes,
    damaged: bytes,
    said: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = write_metric(tmp_path, "train/loss", data)
    truncate_metrics(RunDir(tmp_path).scalars_dir, 1_000)
    assert path.read_bytes() == kept
    assert path.with_name("loss.csv.damaged").read_bytes() == damaged
    (line,) = warnings_of(capsys.readouterr().err)
    assert line.startswith(f"rlpipe: warning: {path}: ") and said in line, line
    assert "crash" not in line  # not a crash's torn tail: it does not say so
    truncate_metrics(RunDir(tmp_path).scalars_dir, 1_000)  # once moved, nothing more to say
    assert capsys.readouterr().err == "" and path.read_bytes() == kept


def test_rows_past_the_checkpoint_are_cut_quietly(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    eval_path = write_metric(tmp_path, "eval/return_mean", ROWS)
    loss_path = write_metric(tmp_path, "train/loss", b"10,0.5\n90,0.25\n110,0.125\n")
    mode = 0o640
    os.chmod(loss_path, mode)
    truncate_metrics(RunDir(tmp_path).scalars_dir, 100)
    assert eval_path.read_bytes() == b"0,1.5\n100,2.5\n"  # frames <= 100 kept
    assert loss_path.read_bytes() == b"10,0.5\n90,0.25\n"
    assert loss_path.stat().st_mode & 0o777 == mode
    assert capsys.readouterr().err == ""
    assert not list(tmp_path.rglob(f"*{TEMP_SUFFIX}"))
    truncate_metrics(RunDir(tmp_path).scalars_dir, 0)
    assert eval_path.read_bytes() == b"0,1.5\n" and loss_path.read_bytes() == b""


def test_unchanged_files_are_not_touched(tmp_path: Path) -> None:
    path = write_metric(tmp_path, "eval/return_mean", ROWS)
    empty = write_metric(tmp_path, "train/loss", b"")
    for p in (path, empty):
        os.utime(p, ns=(1_000_000_000, 1_000_000_000))
    before = [(p.stat().st_ino, p.stat().st_mtime_ns) for p in (path, empty)]
    truncate_metrics(RunDir(tmp_path).scalars_dir, 200)
    assert [(p.stat().st_ino, p.stat().st_mtime_ns) for p in (path, empty)] == before
    assert path.read_bytes() == ROWS
    truncate_metrics(
        RunDir(tmp_path / "no-metrics-here").scalars_dir, 0
    )  # no metrics dir: nothing to do


def test_readers_skip_a_damaged_tail(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """read_metric, find_runs, curve.png and rlpipe.plot: no traceback, the good rows drawn."""
    runs = [tmp_path / "sweep" / name for name in ("nul", "torn", "only-nul")]
    write_metric(runs[0], "eval/return_mean", ROWS + b"\0" * 512)
    write_metric(runs[1], "eval/return_mean", ROWS + b"300,4")
    write_metric(runs[2], "eval/return_mean", b"\0" * 512)
    for run in runs[:2]:
        write_metric(run, "train/episode_return", b"5,1.0\n50,2.0\n\0\0")
    frames, values = RunDir(runs[0]).metric("eval/return_mean")
    assert frames.tolist() == [0, 100, 200] and values.tolist() == [1.5, 2.5, 3.5]
    assert RunDir(runs[1]).metric("eval/return_mean")[0].tolist() == [0, 100, 200]
    assert RunDir(runs[2]).metric("eval/return_mean")[0].size == 0
    assert find_runs([tmp_path / "sweep"]) == runs[:2]  # nothing readable in the third
    assert plot_run(runs[0]).is_file()
    plot_main([str(tmp_path / "sweep"), f"out={tmp_path / 'sweep.png'}"])
    assert "from 2 run(s)" in capsys.readouterr().out
    assert (tmp_path / "sweep.png").is_file()


def test_parse_rows() -> None:
    assert parse_rows(b"") == []
    rows = parse_rows(b"1,2\n3,nan\n")
    assert rows[0] == (1.0, 2.0) and rows[1][0] == 3.0 and np.isnan(rows[1][1])
    assert parse_rows(b"1,2\n3,4") == [(1.0, 2.0)]  # a torn last line is not a row
    assert parse_rows(b"1,2,3\n5,6\n") == [(5.0, 6.0)]  # a damaged line hides no later row


TRUNCATE = (
    "import sys; from rlpipe.metrics import truncate_metrics; from rlpipe.rundir import RunDir; "
    "truncate_metrics(RunDir(sys.argv[1]).scalars_dir, 100)"
)


# the 2nd rewrite killed: the 1st file is new, the rest old; only the slow suite kills the 1st
@pytest.mark.parametrize("nth", [2, pytest.param(1, marks=pytest.mark.faults)])
def test_killed_while_truncating_leaves_each_file_whole(tmp_path: Path, nth: int) -> None:
    """SIGKILL at the truncate fault point (a trimmed copy written, not yet renamed): every CSV
    holds its complete old or new content, and a later truncation finishes the job."""
    old = {
        "eval/return_mean": ROWS,
        "train/loss": b"10,0.5\n150,0.25\n",
        "train/episode_return": b"20,9.0\n120,11.0\n" + b"\0" * 100,
        "time/fps": b"50,1000.0\n",  # unchanged: never rewritten
    }
    new = {
        "eval/return_mean": b"0,1.5\n100,2.5\n",
        "train/loss": b"10,0.5\n",
        "train/episode_return": b"20,9.0\n",
        "time/fps": b"50,1000.0\n",
    }
    for name, data in old.items():
        write_metric(tmp_path, name, data)
    env = {**os.environ, "RLPIPE_FAULT": f"truncate@{nth}"}
    proc = subprocess.run(
        [sys.executable, "-c", TRUNCATE, str(tmp_path)],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert len(list(tmp_path.rglob(f"*{TEMP_SUFFIX}"))) == 1  # killed with a copy not renamed
    contents = {name: RunDir(tmp_path).metric_path(name).read_bytes() for name in old}
    changed = [name for name in old if contents[name] != old[name]]
    assert len(changed) == nth - 1, contents  # files are done in order, one per fault point
    for name, data in contents.items():
        assert data in (old[name], new[name]), (name, data)
    truncate_metrics(RunDir(tmp_path).scalars_dir, 100)  # the resume after the crash
    assert {name: RunDir(tmp_path).metric_path(name).read_bytes() for name in old} == new
    assert not list(tmp_path.rglob(f"*{TEMP_SUFFIX}"))  # the killed run's copy is gone


def test_check_writable_writes_nothing(tmp_path: Path) -> None:
    check_writable(tmp_path / "a" / "b" / "out.json", "hint")
    assert not any(tmp_path.iterdir())  # the probe's directories are gone again
    (tmp_path / "file").write_text("x")
    with pytest.raises(RlpipeError, match=r"file is not a directory; use out=<file>$"):
        check_writable(tmp_path / "file" / "deeper" / "out.json", "use out=<file>")
    with pytest.raises(RlpipeError, match="cannot write .*: it is a directory; hint"):
        check_writable(tmp_path, "hint")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_seeds_resumes_and_display_keys_group_together_other_overrides_apart(tmp_path):
    from rlpipe.runs import group_runs

    made = {
        "a0": ["seed=0", "algo.lr=0.1"],
        "a1": ["seed=1", "algo.lr=0.1", f"resume={tmp_path / 'a1'}"],  # a resumed seed
        "b0": ["seed=0", "algo.lr=0.2"],
        "b1": ["seed=1", "algo.lr=0.2", "progress=false", "logger=tensorboard"],  # shown elsewhere
    }
    for name, overrides in made.items():
        (tmp_path / name / ".hydra").mkdir(parents=True)
        (tmp_path / name / ".hydra" / "overrides.yaml").write_text(
            "".join(f"- {o}\n" for o in overrides)
        )
    groups = group_runs([tmp_path / name for name in made])
    assert sorted((g.label, len(g.runs)) for g in groups) == [
        ("algo.lr=0.1", 2),
        ("algo.lr=0.2", 2),
    ]
