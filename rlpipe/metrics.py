"""Metric CSV files: read back, and cut back to a checkpoint when a run resumes
(:func:`truncate_metrics`). Where a run keeps them: :class:`rlpipe.rundir.RunDir`.

Metrics are :class:`rlpipe.loggers.CsvLogger` files (TorchRL ``CSVLogger``'s format), one
``frames,value`` line per logged value and no header. A crash while writing can leave a damaged
tail (a line without its newline, NUL bytes after a power cut): the good part ends at the first
line that does not parse. Readers skip the tail; :func:`truncate_metrics` cuts it.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

from rlpipe.files import TEMP_SUFFIX, write_atomic

if TYPE_CHECKING:
    import numpy as np

EVAL_METRIC = "eval/return_mean"


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


def read_metric(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, values)`` of one metric's CSV file; empty arrays when there is none.

    A damaged tail (see :func:`parse_rows`) is left out; so is a line a running run is
    writing right now.
    """
    import numpy as np  # here: the command line reads no metric and loads no numpy

    path = Path(path)
    if not path.is_file():
        return np.empty(0), np.empty(0)
    rows, _ = parse_rows(path.read_bytes())
    if not rows:
        return np.empty(0), np.empty(0)
    table = np.asarray(rows, dtype=float)
    return table[:, 0], table[:, 1]


def truncate_metrics(scalars: str | Path, frames: int) -> None:
    """Cut every metric CSV below ``scalars`` back to the rows logged at ``frames`` or before.

    Run when a run resumes from its checkpoint at ``frames``: rows logged after it belong to
    the lost part of the run and are logged again, so each row is in the files once. A
    damaged tail is cut too, with one warning line on stderr. A file that changes is replaced
    atomically (a trimmed copy, fsynced, renamed over it, the directory fsynced): a crash at
    any moment leaves each file whole, old or new. Unchanged files are not touched.
    """
    scalars = Path(scalars)
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
