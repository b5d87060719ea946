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

import json
import logging
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from rlpipe.cli import USER_ERRORS, format_error
from rlpipe.errors import RunDirConflict, check
from rlpipe.files import write_atomic
from rlpipe.outcomes import Interrupted, RunResult
from rlpipe.rundir import RunDir
from rlpipe.sweep_summary import (
    CSV_FILE,
    ERROR_FILE,
    INTERRUPTED_FILE,
    MARKDOWN_FILE,
    REJECTED,
    summary_markdown,
    write_summary,
)

log = logging.getLogger(__name__)


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
        rows, rejected = write_summary(sweep_dir)
        self.table = summary_markdown(rows, rejected)
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


class SweepSummary(Callback):
    """Hydra callback: when a multirun ends, write and print its summary table.

    ``failed_jobs`` holds how many jobs of the last sweep this process summarised failed, did
    not finish or were rejected; the command line exits non-zero when there are any.
    """

    failed_jobs = 0

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        rows, rejected = write_summary(sweep_dir)
        if not rows and not rejected:
            return
        failed = sum(row.status != "ok" for row in rows)
        SweepSummary.failed_jobs = failed + len(rejected)
        print(f"\n{summary_markdown(rows, rejected)}")
        refused = f", {len(rejected)} rejected ({sweep_dir / REJECTED})" if rejected else ""
        print(
            f"rlpipe: sweep of {len(rows)} jobs, {failed} failed{refused} | summary "
            f"{sweep_dir / MARKDOWN_FILE}, {sweep_dir / CSV_FILE}"
        )
