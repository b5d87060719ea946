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
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from rlpipe.cli import USER_ERRORS, format_error
from rlpipe.files import write_atomic
from rlpipe.rundir import RunDirConflict
from rlpipe.runner import RunResult

log = logging.getLogger(__name__)

ERROR_FILE = "error.json"
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


def run_sweep_job(
    job: Callable[[], RunResult],
    run_dir: str | Path,
    *,
    record: Callable[[Path], None],
    rejected_dir: str | Path,
) -> RunResult | None:
    """Run one job of a sweep; on an error, record it and return None.

    The error goes to ``error.json`` beside the job's record (``record(dir)`` writes Hydra's
    ``.hydra/`` files where missing) in ``run_dir``, or, when the run dir belongs to another run
    or another process (:class:`~rlpipe.rundir.RunDirConflict`: jobs that resolve to one dir),
    in ``rejected_dir`` so that nothing of that run changes. User errors are reported in their
    one line; anything else (a bug) also logs its traceback.
    """
    start = time.perf_counter()
    try:
        return job()
    except Exception as err:  # noqa: BLE001  (any failure is this job's, not the sweep's)
        if isinstance(err, USER_ERRORS):
            message = format_error(err)
        else:
            log.exception("job failed")
            message = f"{type(err).__name__}: {format_error(err)}"
        print(f"rlpipe: error: {message} (job in {run_dir})", file=sys.stderr)
        where = Path(rejected_dir if isinstance(err, RunDirConflict) else run_dir)
        record(where)
        record_error = {"error": message, "wall_time": time.perf_counter() - start}
        write_atomic(where / ERROR_FILE, (json.dumps(record_error, indent=2) + "\n").encode())
        return None


@dataclass
class JobRow:
    """One job of a sweep as the summary shows it."""

    job: int
    overrides: list[str]
    status: str  # ok | failed | unfinished
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
        summary, error = job_dir / "summary.json", job_dir / ERROR_FILE
        if summary.is_file():
            data = json.loads(summary.read_text())
            row.status = "ok"
            for key in ("eval_mean", "eval_std", "eval_episodes", "frames", "wall_time"):
                setattr(row, key, data[key])
        elif error.is_file():
            data = json.loads(error.read_text())
            row.status, row.error, row.wall_time = "failed", data["error"], data["wall_time"]
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
