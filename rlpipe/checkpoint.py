"""Checkpoints written atomically (temp file, fsync, rename), the newest ``keep`` that load
kept (damaged ones moved to ``damaged/``), and loaded safely (``weights_only=True``), falling
back past damaged files."""

from __future__ import annotations

import io
import os
import pickle
import re
import sys
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

from rlpipe.errors import RlpipeError
from rlpipe.files import TEMP_SUFFIX, write_atomic

PATTERN = "ckpt_*.pt"
BEST_PATTERN = "best_*.pt"  # the best-eval checkpoint, beside the newest ones (not a resume point)
DAMAGED_DIR = "damaged"
# (path, size, mtime) of checkpoints known to load: written here, or loaded once
_known_good: set[tuple[str, int, int]] = set()


def checkpoint_path(directory: str | Path, frames: int) -> Path:
    """Where the checkpoint taken after ``frames`` frames lives (names sort by frames)."""
    return Path(directory) / f"ckpt_{frames:012d}.pt"


def best_path(directory: str | Path, frames: int) -> Path:
    """Where the checkpoint of the best evaluation so far (taken after ``frames``) lives."""
    return Path(directory) / f"best_{frames:012d}.pt"


def list_best(directory: str | Path) -> list[Path]:
    """Best-eval checkpoints in ``directory``, oldest first: the last is the best (one, unless a
    process died between writing a new one and removing the old)."""
    return sorted(Path(directory).glob(BEST_PATTERN))


def save_checkpoint(
    state: dict[str, Any],
    path: str | Path,
    keep: int | None = None,
    *,
    fault: str = "checkpoint_write",
) -> Path:
    """Write ``state`` to ``path`` so that ``path`` is never seen half-written.

    The data goes to a temporary file in the same directory, is flushed to disk, and is
    renamed over ``path``. With ``keep``, :func:`prune_checkpoints` runs afterwards. A failed
    write (disk full, read-only) removes the temporary file and raises :class:`RlpipeError`;
    earlier checkpoints stay.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        data = io.BytesIO()
        torch.save(state, data)  # in memory first: a failing disk then fails with an OSError
        write_atomic(path, data.getvalue(), fault=fault)
    except OSError as err:
        raise RlpipeError(
            f"cannot write checkpoint {path}: {err.strerror or err}; free some disk space "
            "or pick a writable hydra.run.dir (earlier checkpoints are intact)"
        ) from err
    _known_good.add(_identity(path))
    if keep is not None:
        prune_checkpoints(path.parent, keep)
    return path


def prune_checkpoints(directory: str | Path, keep: int) -> None:
    """Keep the newest ``keep`` checkpoints in ``directory`` that load and delete older ones;
    move damaged (or refused) ones to ``damaged/`` with a warning; remove orphan temp files
    (a write that was killed)."""
    directory = Path(directory)
    for tmp in directory.glob(f".*.pt{TEMP_SUFFIX}"):  # of a checkpoint or a best
        tmp.unlink(missing_ok=True)
    kept = 0
    for path in reversed(list_checkpoints(directory)):
        if kept >= keep:
            path.unlink()
        elif _loads(path):
            kept += 1
        else:
            aside = directory / DAMAGED_DIR / path.name
            aside.parent.mkdir(exist_ok=True)
            os.replace(path, aside)
            print(f"rlpipe: warning: moved damaged checkpoint {path} to {aside}", file=sys.stderr)


def _identity(path: Path) -> tuple[str, int, int]:
    stat = path.stat()
    return str(path), stat.st_size, stat.st_mtime_ns


def _loads(path: Path) -> bool:
    if _identity(path) in _known_good:
        return True
    try:
        load_checkpoint(path)
    except RlpipeError:
        return False
    _known_good.add(_identity(path))
    return True


@contextmanager
def fitting(path: str | Path) -> Iterator[None]:
    """Turn any error while applying checkpoint ``path``'s state (wrong keys or shapes, another
    algorithm's state, a bad RNG state) into one :class:`RlpipeError` line."""
    try:
        yield
    except Exception as err:  # noqa: BLE001  (load_state_dict raises many kinds)
        reason = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise RlpipeError(
            f"checkpoint {path} does not fit this run ({type(err).__name__}: {reason[:200]}); "
            "it was written by another version of the run or damaged: use a checkpoint this "
            "run wrote"
        ) from err


def list_checkpoints(directory: str | Path) -> list[Path]:
    """Checkpoints in ``directory``, oldest first."""
    return sorted(Path(directory).glob(PATTERN))


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``: tensors and plain containers only.

    A file carrying other pickled objects (which could run code when unpickled) is refused
    with :class:`UnsafeCheckpoint`; a damaged file raises :class:`CorruptCheckpoint`.
    """
    if not zipfile.is_zipfile(path):  # torch.save writes a zip archive; this is not one
        raise CorruptCheckpoint(f"checkpoint {path} is damaged (not a torch zip archive)")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        found = re.search(r"GLOBAL (\S+)", str(err))
        raise UnsafeCheckpoint(
            f"refusing checkpoint {path}: it holds a pickled object "
            f"({found.group(1) if found else 'not a tensor or plain container'}) that could "
            "run code when loaded; use checkpoints rlpipe wrote"
        ) from err
    except Exception as err:  # noqa: BLE001  (torch raises many kinds on a damaged file)
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise CorruptCheckpoint(f"checkpoint {path} is damaged ({reason})") from err


class UnsafeCheckpoint(RlpipeError):
    """The checkpoint holds pickled objects that ``weights_only`` loading does not allow."""


class CorruptCheckpoint(RlpipeError):
    """The checkpoint file is truncated or otherwise unreadable."""


def load_latest(directory: str | Path) -> tuple[Path, dict[str, Any]]:
    """The newest checkpoint in ``directory`` that loads, skipping damaged ones with a warning.

    Raises :class:`RlpipeError` when there is none (or none intact), and
    :class:`UnsafeCheckpoint` at once for a file that is refused for safety.
    """
    found = list_checkpoints(directory)
    if not found:
        raise RlpipeError(f"no checkpoint in {directory}")
    damaged = []
    for path in reversed(found):
        try:
            state = load_checkpoint(path)
        except CorruptCheckpoint as err:
            damaged.append(str(err))
            continue
        for message in damaged:
            print(f"rlpipe: warning: {message}; using {path.name} instead", file=sys.stderr)
        _known_good.add(_identity(path))
        return path, state
    raise RlpipeError(
        f"every checkpoint in {directory} is damaged ({len(found)} files); cannot resume"
    )
