"""benchmarks/presets_sb3.py's SB3 saves (hours-long presets resume across calls): a kill at every
write point of a save leaves a complete save, the newest one that was finished, to resume from."""

from __future__ import annotations

import importlib
import json
import os
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def presets():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        yield importlib.import_module("presets_sb3")
    finally:
        sys.path.remove(str(BENCHMARKS))


class Killed(BaseException):
    """What the process's death looks like to the code after the write point: nothing runs."""


class FakeModel:
    """What Sb3Saves uses of an SB3 model: its frames and its two save methods."""

    def __init__(self, frames: int, die_at: str | None = None) -> None:
        self.num_timesteps, self.die_at = frames, die_at

    def _write(self, path: Path, what: str) -> None:
        if self.die_at == f"{what}-before":
            raise Killed
        Path(path).write_text(f"{what} at {self.num_timesteps}")
        if self.die_at == f"{what}-after":
            raise Killed

    def save(self, path: Path) -> None:
        self._write(path, "model")

    def save_replay_buffer(self, path: Path) -> None:
        self._write(path, "replay")


# every write of a save, and the rename and clean-up after them
POINTS = [
    "model-before",
    "model-after",
    "replay-before",
    "replay-after",
    "progress",
    "replace",
    "cleanup",
]


@pytest.mark.parametrize("point", POINTS)
def test_a_save_killed_at_any_point_leaves_a_complete_one(presets, tmp_path, monkeypatch, point):
    saves = presets.Sb3Saves(tmp_path)
    saves.save(FakeModel(1000), [[1000, -5.0, 1.5]])
    evals = [[1000, -5.0, 1.5], [2000, -3.0, 3.0]]
    real_replace, real_write = os.replace, Path.write_text

    def write_text(self: Path, text: str, *args, **kwargs):
        if point == "progress" and self.suffix == ".tmp":
            real_write(self, text[: len(text) // 2])  # a torn temporary file
            raise Killed
        return real_write(self, text, *args, **kwargs)

    def replace(src, dst):
        if point == "replace":
            raise Killed
        real_replace(src, dst)
        if point == "cleanup":
            raise Killed  # renamed; the older save is not removed yet

    monkeypatch.setattr(Path, "write_text", write_text)
    monkeypatch.setattr(presets.os, "replace", replace)
    with pytest.raises(Killed):
        saves.save(FakeModel(2000, point if "-" in point else None), evals)
    monkeypatch.undo()

    newest = saves.newest()
    finished = point == "cleanup"  # the progress file names the new save only once it is whole
    frames = 2000 if finished else 1000
    assert newest is not None
    assert newest.model.read_text() == f"model at {frames}"
    assert newest.replay.read_text() == f"replay at {frames}"
    assert newest.evals == (evals if finished else evals[:1])
    # the next save goes on from there and leaves only itself
    saves.save(FakeModel(3000), evals + [[3000, -1.0, 4.5]])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["3000", "progress.json"]
    assert json.loads((tmp_path / "progress.json").read_text())["dir"] == "3000"
