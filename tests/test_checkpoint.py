"""Atomic checkpoints, pruning, and weights-only loading."""

from __future__ import annotations

import pytest
import torch

from rlpipe.checkpoint import UnsafeCheckpoint, load_checkpoint, save_checkpoint
from rlpipe.rundir import RunDir
from rlpipe.runtime import rng_state, set_rng_state


def test_save_load_and_keep_last_k(tmp_path):
    run = RunDir(tmp_path)
    with run.session(None, frames=0, keep=2):
        for frames in (10, 20, 30, 40):
            run.save_checkpoint({"frames": frames, "w": torch.ones(2) * frames}, frames)
    paths = run.checkpoints()
    assert [p.name for p in paths] == ["ckpt_000000000030.pt", "ckpt_000000000040.pt"]
    state = load_checkpoint(paths[-1])
    assert state["frames"] == 40 and torch.equal(state["w"], torch.full((2,), 40.0))
    assert not list(run.checkpoints_dir.glob("*.tmp")) and not list(run.checkpoints_dir.glob(".*"))


def test_writes_outside_a_session_are_refused(tmp_path):
    with pytest.raises(AssertionError, match="need a session"):
        RunDir(tmp_path).save_checkpoint({"frames": 1}, 1)
    assert not tmp_path.joinpath("checkpoints").exists()


def test_failed_write_leaves_previous_checkpoint_intact(tmp_path):
    path = tmp_path / "ckpt_000000000001.pt"
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


def test_the_rng_state_carries_cudas_generators_once_cuda_is_in_use(tmp_path, monkeypatch):
    """Draws on a CUDA device (DQN's ε-greedy coin, for one) come from CUDA's generators: a
    resumed CUDA run draws on from where it stopped only if the checkpoint holds them. A CPU run
    (CUDA not initialised) neither stores nor initialises them. Fakes stand in for CUDA here;
    tests/test_faults.py's DQN resumes check it on a GPU machine."""
    assert "cuda" not in rng_state() or torch.cuda.is_initialized()
    generators = [torch.arange(8, dtype=torch.uint8), torch.arange(8, 16, dtype=torch.uint8)]
    restored = []
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)  # resumed on a smaller machine
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: [g.clone() for g in generators])
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", restored.extend)
    run = RunDir(tmp_path)
    with run.session(None, frames=0, keep=1):
        run.save_checkpoint({"rng": rng_state()}, 1)
    set_rng_state(load_checkpoint(run.checkpoints()[-1])["rng"])
    assert len(restored) == 1 and torch.equal(restored[0], generators[0])
