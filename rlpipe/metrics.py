"""A run's logged metrics, read back: one metric's CSV, the runs below a directory, and runs
grouped by the overrides that made them (seeds of one setting together); and cutting a run's
CSVs back to its checkpoint when it resumes (:func:`truncate_metrics`).

Metrics are :class:`rlpipe.loggers.CsvLogger` files (TorchRL ``CSVLogger``'s format),
``<run dir>/metrics/scalars/<name>.csv``, one ``frames,value`` line per logged value and no
header. A crash while writing can leave a damaged tail (a line without its newline, NUL bytes
after a power cut): the good part ends at the first line that does not parse. Readers skip the
tail; :func:`truncate_metrics` cuts it.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from rlpipe.config import flatten
from rlpipe.errors import check
from rlpipe.files import TEMP_SUFFIX, write_atomic
from rlpipe.loggers import METRICS_DIR

EVAL_METRIC = "eval/return_mean"


def metric_path(run_dir: str | Path, name: str) -> Path:
    """Where ``name`` (e.g. ``eval/return_mean``) lives in ``run_dir``."""
    return Path(run_dir) / METRICS_DIR / "scalars" / f"{name}.csv"


def parse_rows(data: bytes) -> tuple[list[tuple[float, float]], int]:
    """The ``(frames, value)`` rows of a metric CSV's bytes and the length of its good part.

    The good part is the complete lines (newline included) before the first one that is not
    ``<number>,<number>``: a last line without its newline (torn by a crash), NUL bytes (a
    power cut), garbage.
    """
    rows: list[tuple[float, float]] = []
    good = 0
    while good < len(data):
        end = data.find(b"\n", good)
        if end < 0:
            break  # torn: its newline never made it
        row = _parse_line(data[good:end])
        if row is None:
            break
        rows.append(row)
        good = end + 1
    return rows, good


def _parse_line(line: bytes) -> tuple[float, float] | None:
    fields = line.split(b",")
    if len(fields) != 2 or b"\0" in line:
        return None
    try:
        return float(fields[0]), float(fields[1])
    except ValueError:
        return None


def read_metric(run_dir: str | Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, values)`` of one metric; empty arrays when the run did not log it.

    A damaged tail (see :func:`parse_rows`) is left out; so is a line a running run is
    writing right now.
    """
    path = metric_path(run_dir, name)
    if not path.is_file():
        return np.empty(0), np.empty(0)
    rows, _ = parse_rows(path.read_bytes())
    if not rows:
        return np.empty(0), np.empty(0)
    table = np.asarray(rows, dtype=float)
    return table[:, 0], table[:, 1]


def truncate_metrics(run_dir: str | Path, frames: int) -> None:
    """Cut every metric CSV of ``run_dir`` back to the rows logged at ``frames`` or before.

    Run when a run resumes from its checkpoint at ``frames``: rows logged after it belong to
    the lost part of the run and are logged again, so each row is in the files once. A
    damaged tail is cut too, with one warning line on stderr. A file that changes is replaced
    atomically (a trimmed copy, fsynced, renamed over it, the directory fsynced): a crash at
    any moment leaves each file whole, old or new. Unchanged files are not touched.
    """
    scalars = Path(run_dir) / METRICS_DIR / "scalars"
    if not scalars.is_dir():
        return
    for stale in scalars.rglob(f".*.csv{TEMP_SUFFIX}"):  # a copy a killed truncation left
        stale.unlink()
    for path in sorted(scalars.rglob("*.csv")):
        if path.is_file():
            _truncate_file(path, frames)


def _truncate_file(path: Path, frames: int) -> None:
    data = path.read_bytes()
    rows, good = parse_rows(data)
    if good < len(data):
        print(
            f"rlpipe: warning: {path}: cut {len(data) - good} damaged bytes at the end "
            "(a crash while writing)",
            file=sys.stderr,
        )
    lines = data[:good].split(b"\n")[:-1]  # the good part ends with a newline
    kept = b"".join(line + b"\n" for line, (step, _) in zip(lines, rows) if step <= frames)
    if kept != data:
        write_atomic(path, kept, fault="truncate")


@dataclass
class Group:
    """Runs that differ only by seed (or a resume), and the overrides that set them apart."""

    label: str
    runs: list[Path]


def find_runs(dirs: Sequence[str | Path], metric: str = EVAL_METRIC) -> list[Path]:
    """Run dirs in ``dirs`` or below them (a multirun sweep dir) that logged ``metric``."""
    runs: list[Path] = []
    for directory in map(Path, dirs):
        check(directory.is_dir(), f"{directory} is not a directory")
        relative = metric_path("", metric)
        found = sorted(
            p.parents[len(relative.parts) - 1]
            for p in directory.rglob(str(relative))
            if parse_rows(p.read_bytes())[0]
        )
        check(
            bool(found),
            f"no metrics under {directory}: no run dir with {METRICS_DIR}/scalars/{metric}.csv "
            "(runs with logger=none write none)",
        )
        runs += found
    return list(dict.fromkeys(runs))


def run_overrides(run_dir: Path) -> list[str]:
    """``key=value`` overrides that made ``run_dir``: Hydra's record, else its whole config."""
    hydra_record = run_dir / ".hydra" / "overrides.yaml"
    if hydra_record.is_file():
        return list(OmegaConf.load(hydra_record))
    config = run_dir / "config.yaml"
    if not config.is_file():
        return []
    flat = flatten(OmegaConf.to_container(OmegaConf.load(config)))
    return [f"{key}={value}" for key, value in flat.items()]


def _key(override: str) -> str:
    return override.split("=")[0].lstrip("+~")


# overrides that never tell experiments apart: seeds are what a group averages over, and a resumed
# run is the run it continues
NOT_GROUPED = ("seed", "resume")


def group_runs(runs: Sequence[Path]) -> list[Group]:
    """Group runs that differ only by ``seed`` (or ``resume``), each labelled by what sets it apart.

    Runs whose overrides agree but for ``seed`` and ``resume`` form one group; a group's label
    is its overrides that not every run shares (a single group: its overrides, or "defaults").
    """
    keyed: dict[frozenset[str], list[Path]] = {}
    for run in runs:
        overrides = frozenset(o for o in run_overrides(run) if _key(o) not in NOT_GROUPED)
        keyed.setdefault(overrides, []).append(run)
    common = frozenset.intersection(*keyed) if keyed else frozenset()
    groups = []
    for overrides, members in keyed.items():
        label = " ".join(sorted(overrides - common if len(keyed) > 1 else overrides))
        groups.append(Group(label or "defaults", members))
    return groups
