"""Atomic checkpoints, pruning, and weights-only loading."""

from __future__ import annotations

import pytest
import torch

from rlpipe.checkpoint import (
    UnsafeCheckpoint,
    checkpoint_path,
    list_checkpoints,
    load_checkpoint,
    save_checkpoint,
)


def test_save_load_and_keep_last_k(tmp_path):
    for frames in (10, 20, 30, 40):
        save_checkpoint(
            {"frames": frames, "w": torch.ones(2) * frames},
            checkpoint_path(tmp_path, frames),
            keep=2,
        )
    paths = list_checkpoints(tmp_path)
    assert [p.name for p in paths] == ["ckpt_000000000030.pt", "ckpt_000000000040.pt"]
    state = load_checkpoint(paths[-1])
    assert state["frames"] == 40 and torch.equal(state["w"], torch.full((2,), 40.0))
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*"))


def test_failed_write_leaves_previous_checkpoint_intact(tmp_path):
    path = checkpoint_path(tmp_path, 1)
    save_checkpoint({"ok": torch.zeros(1)}, path)

    class Unpicklable:
        def __reduce__(self):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        save_checkpoint({"bad": Unpicklable()}, path)
    assert torch.equal(load_checkpoint(path)["ok"], torch.zeros(1))
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temp file left behind


class _Evil:
    def __reduce__(self):
        return (print, ("pwned",))


def test_pickled_objects_are_refused(tmp_path):
    path = tmp_path / "evil.pt"
    torch.save({"x": _Evil()}, path)
    with pytest.raises(UnsafeCheckpoint, match="refusing checkpoint .*evil.pt"):
        load_checkpoint(path)
