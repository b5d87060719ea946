"""Metric CSV files: read back, and cut back to a checkpoint when a run resumes
(:func:`truncate_metrics`). Where a run keeps them: :class:`rlpipe.rundir.RunDir`.

Metrics are :class:`rlpipe.loggers.CsvLogger` files (TorchRL ``CSVLogger``'s format), one
``frames,value`` line per logged value and no header. A crash while writing can leave a torn
tail (a last line without its newline, NUL bytes after a power cut); any other line that is not
``<number>,<number>`` is damage (an edit, a disk error). Readers keep every intact row;
:func:`truncate_metrics` cuts a torn tail and moves damaged lines to a ``.damaged`` side file,
keeping every intact row.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from rlpipe.console import warn
from rlpipe.files import TEMP_SUFFIX, NotOwnFile, read_regular, set_aside, strange, write_atomic

if TYPE_CHECKING:
    import numpy as np

EVAL_METRIC = "eval/return_mean"
DAMAGED_SUFFIX = ".damaged"  # <name>.csv.damaged: lines moved out of <name>.csv


@dataclass
class Parsed:
    """A metric CSV's bytes taken apart: its intact rows (and their lines), its damaged lines
    (1-based line numbers), and the torn tail after the last newline."""

    rows: list[tuple[float, float]] = field(default_factory=list)
    lines: list[bytes] = field(default_factory=list)
    damaged: list[tuple[int, bytes]] = field(default_factory=list)
    tail: bytes = b""


def parse(data: bytes) -> Parsed:
    """Take a metric CSV's bytes apart (see :class:`Parsed`)."""
    parsed = Parsed()
    *complete, parsed.tail = data.split(b"\n")
    for number, line in enumerate(complete, 1):
        row = _parse_line(line)
        if row is None:
            parsed.damaged.append((number, line))
        else:
            parsed.rows.append(row)
            parsed.lines.append(line)
    return parsed


def parse_rows(data: bytes) -> list[tuple[float, float]]:
    """The intact ``(frames, value)`` rows of a metric CSV's bytes."""
    return parse(data).rows


def _parse_line(line: bytes) -> tuple[float, float] | None:
    fields = line.split(b",")
    if len(fields) != 2 or b"\0" in line:
        return None
    try:
        return float(fields[0]), float(fields[1])
    except ValueError:
        return None


def read_metric_bytes(path: str | Path) -> bytes:
    """A metric CSV's bytes; empty when it is missing, and when it is a link or a special file
    (a FIFO is never waited on), which is said in one warning line."""
    try:
        return read_regular(path)
    except FileNotFoundError:
        return b""
    except NotOwnFile as err:
        warn(f"skipped {err}")
        return b""


def read_metric(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, values)`` of one metric's CSV file (its intact rows); empty arrays when there
    is none. A torn tail (or a line a running run is writing right now) is left out."""
    import numpy as np  # here: the command line reads no metric and loads no numpy

    rows = parse_rows(read_metric_bytes(path))
    if not rows:
        return np.empty(0), np.empty(0)
    table = np.asarray(rows, dtype=float)
    return table[:, 0], table[:, 1]


def truncate_metrics(scalars: str | Path, frames: int) -> None:
    """Cut every metric CSV below ``scalars`` back to the rows logged at ``frames`` or before.

    Run when a run resumes from its checkpoint at ``frames``: rows logged after it belong to
    the lost part of the run and are logged again, so each row is in the files once. A torn
    tail is cut and damaged lines are moved to ``<name>.csv.damaged``, each file's one warning
    line on stderr saying which; a link or special file in a CSV's place is set aside
    (``<name>.csv.refused``), never read. A file that changes is replaced atomically (a trimmed
    copy, fsynced, renamed over it, the directory fsynced): a crash at any moment leaves each
    file whole, old or new. Unchanged files are not touched.
    """
    scalars = Path(scalars)
    if strange(scalars, directory=True) or not scalars.is_dir():
        return
    for root, dirs, files in os.walk(scalars):  # links to directories are not walked into
        csv_dirs = [name for name in dirs if name.endswith(".csv")]  # set aside, not entered
        dirs[:] = [name for name in dirs if name not in csv_dirs]
        for name in sorted(files + csv_dirs):
            path = Path(root, name)
            if name.startswith(".") and name.endswith(f".csv{TEMP_SUFFIX}"):
                path.unlink()  # a copy a killed truncation left
            elif name.endswith(".csv"):
                _truncate_file(path, frames)


def _truncate_file(path: Path, frames: int) -> None:
    what = strange(path)
    if what is not None:
        aside = set_aside(path)
        _warn(path, f"it was {what}, not a metrics file of this run: moved it to {aside.name}")
        return
    data = read_regular(path)
    parsed = parse(data)
    said = []
    if parsed.damaged:
        _keep_damaged(path, parsed.damaged)
        numbers = ", ".join(str(number) for number, _ in parsed.damaged[:5])
        more = "" if len(parsed.damaged) <= 5 else f" and {len(parsed.damaged) - 5} more"
        one = len(parsed.damaged) == 1
        said.append(
            f"{'line' if one else 'lines'} {numbers}{more} {'is' if one else 'are'} not a "
            f"`frames,value` row (damaged): moved {'it' if one else 'them'} to "
            f"{path.name}{DAMAGED_SUFFIX}; every intact row is kept"
        )
    if parsed.tail:
        cause = "NUL bytes: a crash or power cut" if not parsed.tail.strip(b"\0") else "torn"
        said.append(f"cut {len(parsed.tail)} bytes at the end ({cause} while writing)")
    if said:
        _warn(path, "; ".join(said))
    kept = b"".join(
        line + b"\n" for line, (step, _) in zip(parsed.lines, parsed.rows) if step <= frames
    )
    if kept != data or os.lstat(path).st_nlink > 1:  # a hard link's other name keeps its bytes
        write_atomic(path, kept, fault="truncate")


def _keep_damaged(path: Path, damaged: list[tuple[int, bytes]]) -> None:
    """Append the damaged lines to ``<path>.damaged`` (written before the CSV loses them)."""
    side = path.with_name(path.name + DAMAGED_SUFFIX)
    if strange(side):
        set_aside(side)
    old = read_regular(side) if side.exists() else b""
    write_atomic(side, old + b"".join(line + b"\n" for _, line in damaged))


def _warn(path: Path, message: str) -> None:
    warn(f"{path}: {message}")
