"""One checkpoint file: written atomically (temp file, fsync, rename), loaded safely
(``weights_only=True``), and known to load or not. Where checkpoints live, which are kept and
which one resumes a run: :class:`rlpipe.rundir.RunDir`. Torch is imported when a checkpoint is
written or read, not with this module."""

from __future__ import annotations

import io
import os
import pickle
import re
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rlpipe.errors import RlpipeError
from rlpipe.files import open_regular, write_atomic

if TYPE_CHECKING:
    import torch

# (path, size, mtime) of checkpoints known to load: written here, or loaded once
_known_good: set[tuple[str, int, int]] = set()


class UnsafeCheckpoint(RlpipeError):
    """The checkpoint holds pickled objects that ``weights_only`` loading does not allow."""


class CorruptCheckpoint(RlpipeError):
    """The checkpoint file is truncated or otherwise unreadable."""


def save_checkpoint(
    state: dict[str, Any], path: str | Path, *, fault: str = "checkpoint_write"
) -> Path:
    """Write ``state`` to ``path`` so that ``path`` is never seen half-written.

    The data goes to a temporary file in the same directory, is flushed to disk, and is
    renamed over ``path``. A failed write (disk full, read-only) removes the temporary file and
    raises :class:`RlpipeError`; earlier checkpoints stay.
    """
    import torch

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
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``: tensors and plain containers only.

    A file carrying other pickled objects (which could run code when unpickled) is refused
    with :class:`UnsafeCheckpoint`; a damaged file raises :class:`CorruptCheckpoint`; a link or
    special file in its place, :class:`~rlpipe.files.NotOwnFile` (nothing is read through it).
    """
    with os.fdopen(open_regular(path), "rb") as file:
        state = _load(file, path, map_location)
    _known_good.add(_identity(Path(path)))
    return state


def _load(file: io.BufferedReader, path: str | Path, map_location: Any) -> dict[str, Any]:
    import torch

    if not zipfile.is_zipfile(file):  # torch.save writes a zip archive; this is not one
        raise CorruptCheckpoint(f"checkpoint {path} is damaged (not a torch zip archive)")
    file.seek(0)
    try:
        return torch.load(file, map_location=map_location, weights_only=True)
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


def loads(path: Path) -> bool:
    """Whether ``path`` loads (remembered for files written or loaded here, unchanged since)."""
    if _identity(path) in _known_good:
        return True
    try:
        load_checkpoint(path)
    except RlpipeError:
        return False
    return True


def _identity(path: Path) -> tuple[str, int, int]:
    stat = os.lstat(path)
    return str(path), stat.st_size, stat.st_mtime_ns


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
