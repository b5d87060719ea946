"""The fault-injection suite's hostile run dirs (issue 37): a run dir handed over with links,
hard links, FIFOs or files where rlpipe keeps its own never makes rlpipe read, write, prune or
load anything outside it. Links and special files are set aside (``<name>.refused``, a warning
each) when a run begins, or refused in one line where the run cannot go on without them (the
run dir itself, its directories, ``config.yaml``); every file outside stays byte for byte."""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
from conftest import BASE, NEWEST
from fault_harness import (
    Reference,
    assert_run_intact,
    error_line,
    rlpipe,
    with_frames,
)

from rlpipe.rundir import RunDir

OLDEST = "ckpt_000000000100.pt"
SCALARS = Path("metrics", "scalars")


def victim(tmp_path: Path, data: bytes = b"a file of yours, outside the run dir\n") -> Path:
    """A file outside the run dir that nothing may change."""
    path = tmp_path / "outside" / f"victim-{len(list(tmp_path.glob('outside/*')))}"
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(data)
    return path


def link(entry: Path, target: Path) -> None:
    """Put a symbolic link to ``target`` in place of ``entry``."""
    if entry.is_dir() and not entry.is_symlink():
        shutil.rmtree(entry)
    else:
        entry.unlink(missing_ok=True)
    entry.symlink_to(target)


def hard_link(entry: Path, target: Path) -> None:
    """Put a second name of ``target`` in place of ``entry``."""
    entry.unlink(missing_ok=True)
    os.link(target, entry)


def fifo(entry: Path) -> None:
    entry.unlink(missing_ok=True)
    os.mkfifo(entry)


def resume_more(tmp_path: Path, run_dir: Path):
    """Train ``run_dir`` on to 300 frames (one checkpoint, evaluation and CSV rows more; the
    newest checkpoint alone kept), from its newest checkpoint of its own, or from zero."""
    args = [*with_frames(BASE, 300), "keep_checkpoints=1", f"hydra.run.dir={run_dir}"]
    return rlpipe(*args, cwd=tmp_path)


def everything(directory: Path) -> dict[str, bytes | str]:
    """Every entry below ``directory`` (links not followed): files' bytes, links' targets."""
    found: dict[str, bytes | str] = {}
    for root, dirs, files in os.walk(directory):
        for name in dirs + files:
            path = Path(root, name)
            key = str(path.relative_to(directory))
            if path.is_symlink():
                found[key] = f"-> {os.readlink(path)}"
            elif path.is_file():
                found[key] = path.read_bytes()
            elif not path.is_dir():
                found[key] = "special"
    return found


def warnings_of(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("rlpipe: warning:")]


# ---------------------------------------------------------------------------------------------
# files in the run dir: set aside, the run goes on, nothing outside changes


def _lock_link(run: Path, tmp: Path) -> list[Path]:
    link(run / ".lock", target := victim(tmp))
    return [target]


def _lock_hard_link(run: Path, tmp: Path) -> list[Path]:
    hard_link(run / ".lock", target := victim(tmp))
    return [target]


def _lock_fifo(run: Path, tmp: Path) -> list[Path]:
    fifo(run / ".lock")
    return []


def _lock_directory(run: Path, tmp: Path) -> list[Path]:
    (run / ".lock").unlink(missing_ok=True)
    (run / ".lock").mkdir()
    return []


def _checkpoint_link(run: Path, tmp: Path) -> list[Path]:
    """The issue's case: a checkpoint from outside, newer by name than the run's own."""
    outside = victim(tmp, (run / "checkpoints" / NEWEST).read_bytes())
    (run / "checkpoints" / "ckpt_000000009999.pt").symlink_to(outside)
    return [outside]


def _checkpoint_hard_link(run: Path, tmp: Path) -> list[Path]:
    outside = victim(tmp, (run / "checkpoints" / OLDEST).read_bytes())
    hard_link(run / "checkpoints" / OLDEST, outside)  # pruned at 300 frames: only its name goes
    return [outside]


def _best_link(run: Path, tmp: Path) -> list[Path]:
    (best,) = RunDir(run).bests()
    outside = victim(tmp, best.read_bytes())
    (run / "checkpoints" / "best_000000009999.pt").symlink_to(outside)
    return [outside]


def _csv_link(run: Path, tmp: Path) -> list[Path]:
    link(run / SCALARS / "train" / "loss.csv", target := victim(tmp, b"0,1.0\n"))
    return [target]


def _csv_hard_link(run: Path, tmp: Path) -> list[Path]:
    loss = run / SCALARS / "train" / "loss.csv"
    hard_link(loss, target := victim(tmp, loss.read_bytes()))
    return [target]


def _csv_fifo(run: Path, tmp: Path) -> list[Path]:
    fifo(run / SCALARS / "train" / "episode_return.csv")  # reading it would wait forever
    return []


def _summary_link(run: Path, tmp: Path) -> list[Path]:
    link(run / "summary.json", target := victim(tmp, (run / "summary.json").read_bytes()))
    return [target]


def _curve_link(run: Path, tmp: Path) -> list[Path]:
    link(run / "curve.png", target := victim(tmp))
    return [target]


def _log_link(run: Path, tmp: Path) -> list[Path]:
    link(run / "rlpipe.log", target := victim(tmp))
    return [target]


def _temp_link(run: Path, tmp: Path) -> list[Path]:
    """A planted temporary name: the next atomic write of summary.json must not follow it."""
    (run / ".summary.json.tmp").symlink_to(target := victim(tmp))
    return [target]


def _every_file_a_link(run: Path, tmp: Path) -> list[Path]:
    """Every file of the run (but config.yaml) a link to a copy of itself outside."""
    targets = []
    for path in sorted(run.rglob("*")):
        if path.is_file() and path.name != "config.yaml":
            targets.append(victim(tmp, path.read_bytes()))
            link(path, targets[-1])
    return targets


# case -> (the damage, returning the files outside that must not change; what a warning names)
FILES: dict[str, tuple[Callable[[Path, Path], list[Path]], str]] = {
    "lock-link": (_lock_link, ".lock was a symbolic link"),
    "lock-hard-link": (_lock_hard_link, ".lock was a file with another name too"),
    "lock-fifo": (_lock_fifo, ".lock was a FIFO"),
    "lock-directory": (_lock_directory, ".lock was a directory"),
    "checkpoint-link": (_checkpoint_link, "ckpt_000000009999.pt was a symbolic link"),
    "checkpoint-hard-link": (_checkpoint_hard_link, ""),  # a regular file: no warning
    "best-link": (_best_link, "best_000000009999.pt was a symbolic link"),
    "csv-link": (_csv_link, "loss.csv: it was a symbolic link"),
    "csv-hard-link": (_csv_hard_link, ""),  # copied before rows are appended: no warning
    "csv-fifo": (_csv_fifo, "episode_return.csv: it was a FIFO"),
    "summary-link": (_summary_link, "summary.json was a symbolic link"),
    "curve-link": (_curve_link, "curve.png was a symbolic link"),
    "log-link": (_log_link, "rlpipe.log was a symbolic link"),
    "temp-link": (_temp_link, ""),
    "every-file-a-link": (_every_file_a_link, "was a symbolic link"),
}


# the cases planted together in one run dir, one resume each: no two touch the same name, and
# every-file-a-link, which links them all, goes alone
ROUNDS = [
    ("lock-link", "checkpoint-link", "csv-fifo", "summary-link", "temp-link"),
    ("lock-hard-link", "checkpoint-hard-link", "csv-hard-link", "curve-link"),
    ("lock-fifo", "best-link", "csv-link", "log-link"),
    ("lock-directory",),
    ("every-file-a-link",),
]


def test_the_rounds_plant_every_case_once():
    assert sorted(case for cases in ROUNDS for case in cases) == sorted(FILES)


@pytest.mark.parametrize("cases", ROUNDS, ids=["+".join(cases) for cases in ROUNDS])
def test_a_hostile_file_is_set_aside_and_nothing_outside_changes(tmp_path, run_copy, cases):
    outside = [path for case in cases for path in FILES[case][0](run_copy, tmp_path)]
    before = {path: path.read_bytes() for path in outside}
    result = resume_more(tmp_path, run_copy)
    assert result.returncode == 0, result.stderr
    assert {path: path.read_bytes() for path in outside} == before  # not one byte outside
    for warned in filter(None, (FILES[case][1] for case in cases)):
        assert any(warned in line for line in warnings_of(result.stderr)), (warned, result.stderr)
    assert_run_intact(run_copy, Reference(300, (100, 200, 300)))
    for path in run_copy.rglob("*"):  # what the run holds now is its own
        assert not path.is_symlink() or path.name.endswith(".refused"), path
    assert [p.name for p in RunDir(run_copy).checkpoints()] == ["ckpt_000000000300.pt"]


def test_a_linked_checkpoint_is_not_used_counted_or_reported(tmp_path, run_copy, capsys):
    """The issue's case: evaluate reports the run's own newest checkpoint (and names the link
    it skipped), the resume starts from it, and pruning (keep 3) counts only the run's own."""
    from rlpipe.evaluate import main

    (outside,) = _checkpoint_link(run_copy, tmp_path)
    main([f"run_dir={run_copy}", "episodes=1"])
    captured = capsys.readouterr()
    assert "trained (ckpt_000000000200)" in captured.out, captured.out
    assert "ckpt_000000009999.pt: it is a symbolic link" in captured.err, captured.err
    result = rlpipe(*with_frames(BASE, 300), f"resume={run_copy}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert f"from {NEWEST} at 200 frames" in result.stdout, result.stdout
    own = [p.name for p in RunDir(run_copy).checkpoints()]
    assert own == [OLDEST, NEWEST, "ckpt_000000000300.pt"]  # the run's real ones, all kept
    assert (run_copy / "checkpoints" / "ckpt_000000009999.pt.refused").is_symlink()
    assert outside.is_file()


@pytest.mark.parametrize("what", ["link", "fifo"])
def test_readers_skip_a_hostile_csv_without_waiting_on_it(tmp_path, finished_run, capsys, what):
    """rlpipe.plot reads no CSV through a link and never waits on a FIFO: of a sweep dir whose
    second run's eval CSV is one, it draws the first and says it skipped the other."""
    from rlpipe.plot import main

    sweep = tmp_path / "sweep"
    for name in ("a", "b"):
        shutil.copytree(finished_run, sweep / name)
    hostile = sweep / "b" / SCALARS / "eval" / "return_mean.csv"
    if what == "fifo":
        fifo(hostile)
    else:
        link(hostile, victim(tmp_path, hostile.read_bytes()))
    main([str(sweep), f"out={tmp_path / 'curves.png'}"])
    captured = capsys.readouterr()
    assert "from 1 run(s)" in captured.out, captured.out
    assert f"rlpipe: warning: skipped {hostile} is a" in captured.err, captured.err
    assert (tmp_path / "curves.png").is_file()


# ---------------------------------------------------------------------------------------------
# what the run cannot go on without: refused in one line, nothing changed


def _run_dir_link(run: Path, tmp: Path) -> Path:
    """The run dir itself a link (to the real run, elsewhere)."""
    real = tmp / "elsewhere"
    shutil.move(run, real)
    run.symlink_to(real)
    return real


def _checkpoints_a_file(run: Path, tmp: Path) -> Path:
    shutil.rmtree(run / "checkpoints")
    (run / "checkpoints").write_text("not a directory\n")
    return run


def _checkpoints_link(run: Path, tmp: Path) -> Path:
    shutil.move(run / "checkpoints", tmp / "elsewhere")
    (run / "checkpoints").symlink_to(tmp / "elsewhere")
    return tmp / "elsewhere"


def _metrics_dir_link(run: Path, tmp: Path) -> Path:
    shutil.move(run / SCALARS / "train", tmp / "elsewhere")
    (run / SCALARS / "train").symlink_to(tmp / "elsewhere")
    return tmp / "elsewhere"


def _videos_link(run: Path, tmp: Path) -> Path:
    (tmp / "elsewhere").mkdir()
    (run / "videos").symlink_to(tmp / "elsewhere")
    return tmp / "elsewhere"


def _config_link(run: Path, tmp: Path) -> Path:
    link(run / "config.yaml", victim(tmp, (run / "config.yaml").read_bytes()))
    return tmp / "outside"


def _config_fifo(run: Path, tmp: Path) -> Path:
    fifo(run / "config.yaml")
    return run


# case -> (the damage, returning a dir outside or the real dir to watch; what the line names)
REFUSED: dict[str, tuple[Callable[[Path, Path], Path], str]] = {
    "run-dir-a-link": (_run_dir_link, "is a symbolic link (to"),
    "checkpoints-a-file": (_checkpoints_a_file, "checkpoints is a file, not a directory"),
    "checkpoints-a-link": (_checkpoints_link, "checkpoints is a symbolic link"),
    "metrics-dir-a-link": (_metrics_dir_link, "train is a symbolic link"),
    "videos-a-link": (_videos_link, "videos is a symbolic link"),
    "config-a-link": (_config_link, "config.yaml is a symbolic link"),
    "config-a-fifo": (_config_fifo, "config.yaml is a FIFO"),
}


@pytest.mark.parametrize("case", REFUSED)
@pytest.mark.parametrize("how", ["resume", "run-dir"])
def test_a_hostile_directory_or_config_is_one_line_and_changes_nothing(
    tmp_path, run_copy, case, how
):
    damage, named = REFUSED[case]
    watched = damage(run_copy, tmp_path)
    before = everything(tmp_path)
    where = f"resume={run_copy}" if how == "resume" else f"hydra.run.dir={run_copy}"
    result = rlpipe(*with_frames(BASE, 300), where, cwd=tmp_path)
    line = error_line(result)
    assert named in line and "rlpipe reads" in line, line
    assert everything(tmp_path) == before  # no lock, no log, no byte anywhere
    assert watched.exists()
