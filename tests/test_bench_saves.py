"""benchmarks/presets_sb3.py's SB3 saves (hours-long presets resume across calls): a kill at every
write point of a save leaves a complete save, the newest one that was finished, to resume from."""

from __future__ import annotations

import importlib
import importlib.util
import json
import os
import shutil
from pathlib import Path

import pytest
from conftest import benchmarks_importable


@pytest.fixture(scope="module")
def presets():
    with benchmarks_importable():
        yield importlib.import_module("presets_sb3")


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


def die_at(monkeypatch, tear: bool, rename: bool, after_rename: bool = False) -> None:
    """The process dies while a file is written atomically (``tear``: half of its temporary copy
    on disk), in place of ``os.replace`` (``rename``) or just after it (``after_rename``)."""
    real_replace, real_write = os.replace, os.write

    def write(fd: int, data) -> int:
        if tear:
            real_write(fd, bytes(data[: len(data) // 2]))  # a torn temporary copy
            raise Killed
        return real_write(fd, data)

    def replace(src, dst):
        if rename:
            raise Killed
        real_replace(src, dst)
        if after_rename:
            raise Killed

    monkeypatch.setattr(os, "write", write)
    monkeypatch.setattr(os, "replace", replace)


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
    # at "cleanup": renamed, the older save not removed yet
    die_at(monkeypatch, point == "progress", point == "replace", point == "cleanup")
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
def test_an_sb3_run_with_the_zoos_normaliser_resumes_from_its_save(
    presets, tmp_path, monkeypatch, capsys
):
    """sb3-contrib's ARS on the Zoo's VecNormalize: the save holds the normaliser, and a later
    call with a larger budget goes on from the save's evals and frames, with draws of its own
    (SB3's load alone would seed them from the run's seed again, replaying its first ones)."""
    table = importlib.import_module("presets_table")
    preset = table.PRESETS["ars_pendulum"]
    saves, again = tmp_path / "saves", tmp_path / "again"
    job = presets.Sb3Job(
        preset.env, 100, 1600, 800, 2, 2, preset.sb3, "ARS", "MlpPolicy", 1, True, str(saves)
    )
    first = presets.run_sb3(job)
    saved = json.loads((saves / "progress.json").read_text())
    # each save says so on the console: the run is hours long
    assert f"presets: SB3 saved at 1,600 of 1,600 frames (eval {first['evals'][-1][1]:.1f}, " in (
        capsys.readouterr().err
    )
    # an ARS iteration is 2 x 4 Pendulum episodes of 200 steps: 1600 frames
    assert saved["dir"] == "1600" and (saves / "1600" / "normalizer.pkl").is_file()
    shutil.copytree(saves, again)
    resumed = presets.run_sb3(presets.Sb3Job(**{**job.__dict__, "frames": 3200}))
    assert [e[0] for e in resumed["evals"]] == [800, 1600, 2400, 3200]
    assert resumed["evals"][:2] == [tuple(e) for e in first["evals"]]
    monkeypatch.setattr(presets, "resume_seed", lambda seed, frames: seed)  # SB3's own reseed
    replayed = presets.run_sb3(
        presets.Sb3Job(**{**job.__dict__, "frames": 3200, "save_dir": str(again)})
    )
    assert [m for _, m, _ in replayed["evals"][2:]] != [m for _, m, _ in resumed["evals"][2:]]


class Inline:
    """A process pool that runs its one job here, so a test can stand in for SB3's run."""

    def __init__(self, *args, **kwargs) -> None:
        pass

    def __enter__(self) -> Inline:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def submit(self, fn, *args):
        class Done:
            def result(self):
                return fn(*args)

        return Done()


@pytest.mark.parametrize("point", [None, "write", "replace"])
def test_a_finished_run_leaves_its_record_and_no_saves(presets, tmp_path, monkeypatch, point):
    """Once ``sb3.json`` is whole, the saves (kept in git for ARS) go; a kill while the record is
    written leaves no record, torn or whole, and the saves to resume from."""
    preset = importlib.import_module("presets_table").PRESETS["ars_bipedal"]
    cfg = type("Cfg", (), {"total_frames": 2000, "eval_every": 1000, "eval_episodes": 2})
    presets.Sb3Saves(tmp_path / "sb3-saves").save(FakeModel(1000), [[1000, -5.0, 1.5]])
    result = {"evals": [[1000, -5.0, 1.5], [2000, -3.0, 3.0]], "final": -2.5}
    monkeypatch.setattr(presets, "ProcessPoolExecutor", Inline)
    monkeypatch.setattr(presets, "run_sb3", lambda job, parent: result)
    die_at(monkeypatch, point == "write", point == "replace")
    if point is None:
        run = presets.sb3_job(preset, cfg, 100, 2, tmp_path)
        assert (run.evals, run.final) == ([tuple(e) for e in result["evals"]], -2.5)
        assert json.loads((tmp_path / "sb3.json").read_text())["final"] == -2.5
        assert not (tmp_path / "sb3-saves").exists()
    else:
        with pytest.raises(Killed):
            presets.sb3_job(preset, cfg, 100, 2, tmp_path)
        assert not presets.sb3_finished(tmp_path)
        assert presets.Sb3Saves(tmp_path / "sb3-saves").newest().evals == [[1000, -5.0, 1.5]]
