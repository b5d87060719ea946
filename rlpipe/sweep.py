"""Sweeps (``python -m rlpipe -m ...``): failed jobs recorded, one summary table per sweep.

Inside a multirun, a job that fails must not end the sweep: :func:`run_sweep_job` writes its
error line to ``error.json`` in the job's directory and returns None (so an Optuna sweeper counts
the trial as failed), and the other jobs run. When the sweep ends, the :class:`SweepSummary`
Hydra callback (``hydra.callbacks`` in ``conf/config.yaml``) collects every job's
``summary.json`` or ``error.json`` into ``summary.csv`` and ``summary.md`` in the sweep directory
and prints the table. It reads the job directories rather than the launcher's return values, so
it works the same whether the jobs ran here, in joblib workers or on a Slurm cluster.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from rlpipe.cli import USER_ERRORS, format_error
from rlpipe.errors import RunDirConflict, check
from rlpipe.files import write_atomic
from rlpipe.outcomes import Interrupted, RunResult
from rlpipe.rundir import RunDir

log = logging.getLogger(__name__)

ERROR_FILE = "error.json"
INTERRUPTED_FILE = "interrupted.json"
CSV_FILE = "summary.csv"
MARKDOWN_FILE = "summary.md"
COLUMNS = (
    "job",
    "overrides",
    "status",
    "eval_mean",
    "eval_std",
    "eval_episodes",
    "frames",
    "wall_time",
    "run_dir",
    "error",
)


def resume_sweep(argv: list[str]) -> list[str]:
    """``-m resume_sweep=<sweep dir> [more overrides]``: the sweep's own command again, in its
    dir (from Hydra's ``multirun.yaml``): finished jobs report their result, interrupted ones
    resume from their checkpoint, the rest start."""
    given = [arg for arg in argv if re.match(r"^\+{0,2}resume_sweep=", arg)]
    if not given:
        return argv
    sweep_dir = Path(given[-1].partition("=")[2])
    record = sweep_dir / "multirun.yaml"
    check(
        record.is_file(),
        f"{sweep_dir} is not a sweep directory (no multirun.yaml); pass the directory a "
        "python -m rlpipe -m ... run wrote (outputs/multirun/<date>/<time>)",
    )
    task = list(OmegaConf.load(record).hydra.overrides.task)
    rest = [arg for arg in argv if arg not in given and arg not in ("-m", "--multirun")]
    return ["-m", *task, *rest, f"hydra.sweep.dir={sweep_dir}"]


class SweepStopped(BaseException):
    """A signal stopped a sweep's job (after its checkpoint): the sweep stops as a whole.

    A ``BaseException``, so that it passes through Hydra's launcher (which would record an
    ``Exception`` as a failed job and go on with the next); the command line prints
    :attr:`message` and exits with the signal's code.
    """

    def __init__(self, interrupted: Interrupted, sweep_dir: str | Path) -> None:
        super().__init__(str(interrupted))
        self.exit_code = interrupted.exit_code
        rows = write_summary(sweep_dir)
        self.table = summary_markdown(rows)
        done = sum(row.status == "ok" for row in rows)
        self.message = (
            f"sweep stopped: {interrupted.signal_name} during job {len(rows) - 1} (checkpointed), "
            f"{done} jobs finished; continue the whole sweep with: "
            f"python -m rlpipe -m resume_sweep={sweep_dir}"
        )


def run_sweep_job(
    job: Callable[[], RunResult],
    run_dir: str | Path,
    *,
    record: Callable[[RunDir], None],
    rejected_dir: str | Path,
    sweep_dir: str | Path,
) -> RunResult | None:
    """Run one job of a sweep; on an error, record it and return None; on a signal
    (:class:`~rlpipe.outcomes.Interrupted`), record it and stop the sweep (:class:`SweepStopped`).

    The error goes to ``error.json`` beside the job's record (``record(RunDir(dir))`` writes Hydra's
    ``.hydra/`` files where missing) in ``run_dir``, or, when the run dir belongs to another run
    or another process (:class:`~rlpipe.errors.RunDirConflict`: jobs that resolve to one dir),
    in ``rejected_dir`` so that nothing of that run changes. User errors are reported in their
    one line; anything else (a bug) also logs its traceback.
    """
    start = time.perf_counter()
    try:
        result = job()
    except Interrupted as err:  # Ctrl-C/SIGTERM: the job checkpointed; the whole sweep stops
        _mark(Path(run_dir), INTERRUPTED_FILE, str(err), time.perf_counter() - start)
        raise SweepStopped(err, sweep_dir) from err
    except Exception as err:  # noqa: BLE001  (any failure is this job's, not the sweep's)
        if isinstance(err, USER_ERRORS):
            message = format_error(err)
        else:
            log.exception("job failed")
            message = f"{type(err).__name__}: {format_error(err)}"
        print(f"rlpipe: error: {message} (job in {run_dir})", file=sys.stderr)
        where = Path(rejected_dir if isinstance(err, RunDirConflict) else run_dir)
        record(RunDir(where))
        _mark(where, ERROR_FILE, message, time.perf_counter() - start)
        return None
    for stale in (ERROR_FILE, INTERRUPTED_FILE):  # of an earlier attempt (resume_sweep)
        (Path(run_dir) / stale).unlink(missing_ok=True)
    return result


def _mark(job_dir: Path, name: str, message: str, wall_time: float) -> None:
    """Record why a job did not finish (``error.json`` or ``interrupted.json``, the other
    removed: the newest attempt's reason counts)."""
    data = {"error": message, "wall_time": wall_time}
    write_atomic(job_dir / name, (json.dumps(data, indent=2) + "\n").encode())
    other = INTERRUPTED_FILE if name == ERROR_FILE else ERROR_FILE
    (job_dir / other).unlink(missing_ok=True)


@dataclass
class JobRow:
    """One job of a sweep as the summary shows it."""

    job: int
    overrides: list[str]
    status: str  # ok | failed | interrupted | unfinished
    run_dir: str
    eval_mean: float = math.nan
    eval_std: float = math.nan
    eval_episodes: int = 0
    frames: int = 0
    wall_time: float = math.nan
    error: str = ""


def collect_jobs(sweep_dir: str | Path) -> list[JobRow]:
    """Every job directory under ``sweep_dir`` (those with ``.hydra/``), by job number."""
    rows = []
    for hydra_dir in Path(sweep_dir).glob("**/.hydra"):
        job_dir = hydra_dir.parent
        overrides = OmegaConf.to_container(OmegaConf.load(hydra_dir / "overrides.yaml"))
        number = OmegaConf.load(hydra_dir / "hydra.yaml").hydra.job.num
        row = JobRow(int(number), list(overrides), "unfinished", str(job_dir))
        error, interrupted = job_dir / ERROR_FILE, job_dir / INTERRUPTED_FILE
        summary = RunDir(job_dir).read_summary()
        if summary is not None:
            row.status = "ok"
            for key in ("eval_mean", "eval_std", "eval_episodes", "frames", "wall_time"):
                setattr(row, key, getattr(summary, key))
        elif interrupted.is_file() or error.is_file():
            data = json.loads((interrupted if interrupted.is_file() else error).read_text())
            row.status = "interrupted" if interrupted.is_file() else "failed"
            row.error, row.wall_time = data["error"], data["wall_time"]
        else:
            row.error = "did not finish (no summary.json): killed, or still running"
        rows.append(row)
    return sorted(rows, key=lambda row: row.job)


def summary_csv(rows: Sequence[JobRow]) -> str:
    """The summary as CSV: one row per job, the full overrides, raw numbers."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        values = {**vars(row), "overrides": " ".join(row.overrides)}
        writer.writerow([values[column] for column in COLUMNS])
    return out.getvalue()


def summary_markdown(rows: Sequence[JobRow]) -> str:
    """The summary as a Markdown table; overrides shared by every job are listed once above it."""
    common = set.intersection(*(set(row.overrides) for row in rows)) if len(rows) > 1 else set()
    lines = []
    if common:
        shared = " ".join(o for o in rows[0].overrides if o in common)
        lines += [f"every job: `{shared}`", ""]
    lines += [
        "| job | overrides | final eval | frames | wall s | error |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        own = " ".join(o for o in row.overrides if o not in common) or "–"
        score = f"{row.eval_mean:.2f} ± {row.eval_std:.2f}" if row.status == "ok" else row.status
        frames = f"{row.frames:,}" if row.status == "ok" else "–"
        wall = "–" if math.isnan(row.wall_time) else f"{row.wall_time:.1f}"
        error = row.error.replace("|", "\\|")
        lines.append(f"| {row.job} | {own} | {score} | {frames} | {wall} | {error} |")
    return "\n".join(lines) + "\n"


def write_summary(sweep_dir: str | Path) -> list[JobRow]:
    """Write ``summary.csv`` and ``summary.md`` into ``sweep_dir`` (each complete, or absent)."""
    rows = collect_jobs(sweep_dir)
    if rows:
        write_atomic(Path(sweep_dir) / CSV_FILE, summary_csv(rows).encode())
        write_atomic(Path(sweep_dir) / MARKDOWN_FILE, summary_markdown(rows).encode())
    return rows


class SweepSummary(Callback):
    """Hydra callback: when a multirun ends, write and print its summary table.

    ``failed_jobs`` holds how many jobs of the last sweep this process summarised failed (or
    did not finish); the command line exits non-zero when there are any.
    """

    failed_jobs = 0

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        rows = write_summary(sweep_dir)
        if not rows:
            return
        failed = sum(row.status != "ok" for row in rows)
        SweepSummary.failed_jobs = failed
        print(f"\n{summary_markdown(rows)}")
        print(
            f"rlpipe: sweep of {len(rows)} jobs, {failed} failed | summary "
            f"{sweep_dir / MARKDOWN_FILE}, {sweep_dir / CSV_FILE}"
        )
