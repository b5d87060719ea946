"""A sweep's summary, read from its job directories: one row per job (``summary.csv``,
``summary.md``), one aggregate row per group of seeds, and the jobs refused because their dir
belonged to another run, apart (``rejected/``)."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from rlpipe.files import read_regular, write_atomic
from rlpipe.rundir import RunDir
from rlpipe.runs import group_by_overrides
from rlpipe.stats import AGGREGATES, bootstrap_band

ERROR_FILE = "error.json"
INTERRUPTED_FILE = "interrupted.json"
CSV_FILE = "summary.csv"
MARKDOWN_FILE = "summary.md"
REJECTED = "rejected"  # <sweep dir>/rejected/<job>: jobs whose dir belonged to another run
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


@dataclass
class JobRow:
    """One job of a sweep as the summary shows it."""

    job: int
    overrides: list[str]
    status: str  # ok | failed | interrupted | unfinished | rejected
    run_dir: str
    eval_mean: float = math.nan
    eval_std: float = math.nan
    eval_episodes: int = 0
    frames: int = 0
    wall_time: float = math.nan
    error: str = ""


def collect_jobs(sweep_dir: str | Path, *, rejected: bool = False) -> list[JobRow]:
    """Every job directory under ``sweep_dir`` (those with ``.hydra/``), by job number: the jobs
    that ran in their own dirs, or (``rejected``) those refused because their dir belonged to
    another run, recorded under ``rejected/`` (:func:`rlpipe.sweep.run_sweep_job`)."""
    rows = []
    for hydra_dir in Path(sweep_dir).glob(f"**/{RunDir.HYDRA}"):
        job_dir = hydra_dir.parent
        if (job_dir.relative_to(sweep_dir).parts[:1] == (REJECTED,)) == rejected:
            rows.append(_job_row(RunDir(job_dir), "rejected" if rejected else "failed"))
    return sorted(rows, key=lambda row: row.job)


def _job_row(job: RunDir, failed: str) -> JobRow:
    """One job's row from its dir: ``summary.json``, else ``interrupted.json`` or ``error.json``
    (then ``failed`` is its status)."""
    hydra = job.read_yaml(f"{RunDir.HYDRA}/hydra.yaml")
    number = OmegaConf.select(hydra, "hydra.job.num", default=-1) if hydra is not None else -1
    row = JobRow(int(number), job.overrides(), "unfinished", str(job.path))
    summary = job.read_summary()
    marks = {name: _read_json(job.path / name) for name in (INTERRUPTED_FILE, ERROR_FILE)}
    if summary is not None:
        row.status = "ok"
        for key in ("eval_mean", "eval_std", "eval_episodes", "frames", "wall_time"):
            setattr(row, key, getattr(summary, key))
    elif any(marks.values()):
        name = INTERRUPTED_FILE if marks[INTERRUPTED_FILE] else ERROR_FILE
        row.status = "interrupted" if name == INTERRUPTED_FILE else failed
        row.error, row.wall_time = marks[name]["error"], marks[name]["wall_time"]
    else:
        row.error = "did not finish (no summary.json): killed, or still running"
    return row


def _read_json(path: Path) -> dict[str, Any] | None:
    """A job's ``error.json``/``interrupted.json``, or None (missing or not its own file)."""
    try:
        return json.loads(read_regular(path))
    except (OSError, ValueError):
        return None


def summary_csv(rows: Sequence[JobRow]) -> str:
    """The summary as CSV: one row per job, the full overrides, raw numbers."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(COLUMNS)
    for row in rows:
        values = {**vars(row), "overrides": " ".join(row.overrides)}
        writer.writerow([values[column] for column in COLUMNS])
    return out.getvalue()


def summary_markdown(rows: Sequence[JobRow], rejected: Sequence[JobRow] = ()) -> str:
    """The summary as Markdown: a table of the jobs (overrides shared by every job listed once
    above it), one aggregate row per group of seeds, and the rejected jobs apart."""
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
        lines.append(f"| {row.job} | {own} | {score} | {frames} | {wall} | {_cell(row.error)} |")
    lines += group_lines(rows)
    if rejected:
        lines += [
            "",
            f"Rejected: their dir belonged to another run (nothing of it changed); their "
            f"records are in {REJECTED}/<job>:",
            "",
            "| job | overrides | error |",
            "|---|---|---|",
        ]
        for row in rejected:
            lines.append(f"| {row.job} | {' '.join(row.overrides)} | {_cell(row.error)} |")
    return "\n".join(lines) + "\n"


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def group_lines(rows: Sequence[JobRow]) -> list[str]:
    """Markdown lines: one row per group of seeds (jobs alike but for ``seed``) over the final
    evals of its finished jobs: the mean and the IQM, each with a 95% bootstrap confidence
    interval, and how many seeds reached the env's target where gymnasium knows one."""
    import numpy as np

    finished = [row for row in rows if row.status == "ok"]
    if not finished:
        return []
    groups = group_by_overrides(finished, lambda row: row.overrides)
    lines = [
        "",
        "Over seeds (final evals of the finished jobs; [95% bootstrap confidence interval]):",
        "",
        "| group | seeds | mean | IQM | solved |",
        "|---|---|---|---|---|",
    ]
    for label, members in groups:
        values = np.array([row.eval_mean for row in members])
        mean, iqm = (_with_interval(values, aggregate) for aggregate in ("mean", "iqm"))
        label = label if len(groups) > 1 else "every job"
        solved = _solved(values, reward_threshold(RunDir(members[0].run_dir).identity()[0]))
        lines.append(f"| {label} | {len(members)} | {mean} | {iqm} | {solved} |")
    return lines


def _with_interval(values: Any, aggregate: str) -> str:
    point = float(AGGREGATES[aggregate](values))
    if len(values) < 2:
        return f"{point:.2f}"
    low, high = bootstrap_band(values, aggregate)
    return f"{point:.2f} [{float(low):.2f}, {float(high):.2f}]"


def _solved(values: Any, target: float | None) -> str:
    if target is None:
        return "– (no known target)"
    return f"{int((values >= target).sum())}/{len(values)} (≥ {target:g})"


def reward_threshold(env_id: str) -> float | None:
    """The return at which gymnasium's registry calls ``env_id`` solved (its spec's
    ``reward_threshold``), or None; an id naming a module (``module:Id``) is not imported."""
    if ":" in env_id:
        return None
    import gymnasium

    spec = gymnasium.registry.get(env_id)
    threshold = None if spec is None else spec.reward_threshold
    return None if threshold is None else float(threshold)


def write_summary(sweep_dir: str | Path) -> tuple[list[JobRow], list[JobRow]]:
    """Write ``summary.csv`` (the rejected jobs last, status ``rejected``) and ``summary.md``
    into ``sweep_dir`` (each complete, or absent); return the jobs and the rejected jobs."""
    rows, rejected = collect_jobs(sweep_dir), collect_jobs(sweep_dir, rejected=True)
    if rows or rejected:
        write_atomic(Path(sweep_dir) / CSV_FILE, summary_csv([*rows, *rejected]).encode())
        markdown = summary_markdown(rows, rejected)
        write_atomic(Path(sweep_dir) / MARKDOWN_FILE, markdown.encode())
    return rows, rejected
