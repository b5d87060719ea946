"""benchmarks/presets_sb3.py's SB3 saves (hours-long presets resume across calls): a kill at every
write point of a save leaves a complete save, the newest one that was finished, to resume from."""

from __future__ import annotations

import importlib
import importlib.util
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


@pytest.mark.skipif(
    importlib.util.find_spec("sb3_contrib") is None, reason='needs the "bench" extra'
)
def test_an_sb3_run_with_the_zoos_normaliser_resumes_from_its_save(presets, tmp_path):
    """sb3-contrib's ARS on the Zoo's VecNormalize: the save holds the normaliser, and a later
    call with a larger budget goes on from the save's evals and frames."""
    table = importlib.import_module("presets_table")
    preset = table.PRESETS["ars_pendulum"]
    job = presets.Sb3Job(
        preset.env, 100, 1600, 800, 2, 2, preset.sb3, "ARS", "MlpPolicy", 1, True, str(tmp_path)
    )
    first = presets.run_sb3(job)
    saved = json.loads((tmp_path / "progress.json").read_text())
    # an ARS iteration is 2 x 4 Pendulum episodes of 200 steps: 1600 frames
    assert saved["dir"] == "1600" and (tmp_path / "1600" / "normalizer.pkl").is_file()
    resumed = presets.run_sb3(presets.Sb3Job(**{**job.__dict__, "frames": 3200}))
    assert [e[0] for e in resumed["evals"]] == [800, 1600, 2400, 3200]
    assert resumed["evals"][:2] == [tuple(e) for e in first["evals"]]
