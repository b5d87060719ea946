"""Checkpoints written atomically (temp file, fsync, rename), the newest ``keep`` kept."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

PATTERN = "ckpt_*.pt"


def checkpoint_path(directory: str | Path, frames: int) -> Path:
    """Where the checkpoint taken after ``frames`` frames lives (names sort by frames)."""
    return Path(directory) / f"ckpt_{frames:012d}.pt"


def save_checkpoint(state: dict[str, Any], path: str | Path, keep: int | None = None) -> Path:
    """Write ``state`` to ``path`` so that ``path`` is never seen half-written.

    The data goes to a temporary file in the same directory, is flushed to disk, and is
    renamed over ``path``. With ``keep``, older ``ckpt_*.pt`` files beyond the newest
    ``keep`` in that directory are deleted afterwards.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        torch.save(state, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
    if keep is not None:
        for old in list_checkpoints(path.parent)[:-keep]:
            old.unlink()
    return path


def list_checkpoints(directory: str | Path) -> list[Path]:
    """Checkpoints in ``directory``, oldest first."""
    return sorted(Path(directory).glob(PATTERN))


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Load a checkpoint with ``weights_only=True``: tensors and plain containers only."""
    return torch.load(path, map_location=map_location, weights_only=True)
