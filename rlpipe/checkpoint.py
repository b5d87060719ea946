"""Checkpoints written atomically (temp file, fsync, rename), the newest ``keep`` kept, and
loaded safely (``weights_only=True``), falling back past damaged files."""

from __future__ import annotations

import io
import os
import pickle
import re
import sys
import zipfile
from pathlib import Path
from typing import Any

import torch

from rlpipe.errors import RlpipeError

PATTERN = "ckpt_*.pt"


def checkpoint_path(directory: str | Path, frames: int) -> Path:
    """Where the checkpoint taken after ``frames`` frames lives (names sort by frames)."""
    return Path(directory) / f"ckpt_{frames:012d}.pt"


def save_checkpoint(state: dict[str, Any], path: str | Path, keep: int | None = None) -> Path:
    """Write ``state`` to ``path`` so that ``path`` is never seen half-written.

    The data goes to a temporary file in the same directory, is flushed to disk, and is
    renamed over ``path``. With ``keep``, older ``ckpt_*.pt`` files beyond the newest
    ``keep`` in that directory are deleted afterwards. A failed write (disk full, read-only)
    removes the temporary file and raises :class:`RlpipeError`; earlier checkpoints stay.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        data = io.BytesIO()
        torch.save(state, data)  # in memory first: a failing disk then fails with an OSError
        with open(tmp, "wb") as f:
            f.write(data.getbuffer())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError):
            raise RlpipeError(
                f"cannot write checkpoint {path}: {err.strerror or err}; free some disk space "
                "or pick a writable hydra.run.dir (earlier checkpoints are intact)"
            ) from err
        raise
    if keep is not None:
        for old in list_checkpoints(path.parent)[:-keep]:
            old.unlink()
    return path


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
        return path, state
    raise RlpipeError(
        f"every checkpoint in {directory} is damaged ({len(found)} files); cannot resume"
    )
