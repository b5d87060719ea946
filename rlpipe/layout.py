"""A run dir's layout: where each of its files lives, and which of its entries are its own
(a real directory or a regular file, reached through no symbolic link). Reading and writing
them: :class:`rlpipe.rundir.RunDir`, which is a :class:`RunLayout`."""

from __future__ import annotations

import os
from pathlib import Path

from rlpipe.console import warn
from rlpipe.errors import RlpipeError, check
from rlpipe.files import REFUSED_SUFFIX, reached_directly, set_aside, strange


class RunLayout:
    """The directory ``path`` of one run: the names in it, the listing of its checkpoints, and
    the guard that keeps every read and write inside it (:meth:`check_layout`, links and special
    files set aside)."""

    CONFIG = "config.yaml"
    LOCK = ".lock"
    CHECKPOINTS = "checkpoints"
    METRICS = "metrics"  # metrics/scalars/<name>.csv (TorchRL CSVLogger's layout)
    SUMMARY = "summary.json"
    HYDRA = ".hydra"
    VIDEOS = "videos"  # videos/eval_<frames>.mp4 (video=true)
    EVALUATION = "evaluation"  # evaluation/<policy>.json (python -m rlpipe.evaluate)
    EXPORT = "export"  # export/policy-<checkpoint>.pt, .onnx (python -m rlpipe.export)
    CURVE = "curve.png"
    LOG = "rlpipe.log"  # Hydra's job log (hydra.job.name: rlpipe)
    DIRS = (CHECKPOINTS, METRICS, f"{METRICS}/scalars", VIDEOS, EVALUATION, EXPORT, HYDRA)
    TRACKERS = ("tensorboard", "wandb", "mlartifacts", "mlflow.db")  # the loggers' own files

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __fspath__(self) -> str:
        return str(self.path)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"

    @property
    def checkpoints_dir(self) -> Path:
        return self.path / self.CHECKPOINTS

    @property
    def scalars_dir(self) -> Path:
        return self.path / self.METRICS / "scalars"

    def metric_path(self, name: str) -> Path:
        """Where metric ``name`` (e.g. ``eval/return_mean``) is logged."""
        return self.scalars_dir / f"{name}.csv"

    def check_layout(self) -> None:
        """One line unless the run dir and its directories are real directories and
        ``config.yaml`` a regular file (none a symbolic link, a file in a directory's place, a
        FIFO, ...): nothing is read or written through them."""
        what = strange(self.path, directory=True)
        if what is not None:
            raise RlpipeError(
                f"run directory {self.path} is {what}; rlpipe reads and writes a run dir only "
                f"as the directory itself: pass {os.path.realpath(self.path)}"
                if what.startswith("a symbolic link")
                else f"run directory {self.path} is {what}; pass a directory"
            )
        scalars = [Path(root, d) for root, dirs, _ in os.walk(self.scalars_dir) for d in dirs]
        trackers = [self.path / name for name in self.TRACKERS[:-1]]
        for directory in [*(self.path / name for name in self.DIRS), *trackers, *scalars]:
            what = strange(directory, directory=True)
            check(
                what is None,
                f"{directory} is {what}, where the run keeps a directory: rlpipe reads and writes "
                f"nothing through it; move it away (mv {directory} {directory}.bad) to go on, "
                "or pick another run dir (hydra.run.dir=<dir>)",
            )
        what = strange(self.path / self.CONFIG)
        check(
            what is None,
            f"{self.path / self.CONFIG} is {what}: rlpipe reads a run's config only from its own "
            "regular file; put the file itself there, or pick another run dir "
            "(hydra.run.dir=<dir>)",
        )

    def _inside(self, path: Path) -> bool:
        """Whether ``path`` (below the run dir) is reached through no symbolic link."""
        return reached_directly(self.path, path)

    def is_run(self) -> bool:
        """Whether a run was started here (``config.yaml`` is there, of whatever kind)."""
        return os.path.lexists(self.path / self.CONFIG)

    def checkpoints(self) -> list[Path]:
        """The resume points (``ckpt_<frames>.pt``: names sort by frames), oldest first: the
        run's own regular files only (a link or special file is never one)."""
        return self._own("ckpt_*.pt")

    def bests(self) -> list[Path]:
        """The best evaluation's checkpoints (``best_<frames>.pt``, not resume points), oldest
        first: the last is the best (one, unless a process died between writing a new one and
        removing the old)."""
        return self._own("best_*.pt")

    def _own(self, pattern: str, *, say: bool = False) -> list[Path]:
        """The checkpoints matching ``pattern`` that are the run's own regular files (``say``:
        a warning names each one that is not)."""
        if strange(self.checkpoints_dir, directory=True):
            return []
        own = []
        for path in sorted(self.checkpoints_dir.glob(pattern)):
            what = strange(path)
            if what is None:
                own.append(path)
            elif say:
                warn(f"skipped {path}: it is {what}, not a checkpoint of this run")
        return own

    def latest_checkpoint(self) -> Path | None:
        found = self.checkpoints()
        return found[-1] if found else None

    def _set_aside_strangers(self) -> None:
        """Set aside (``<name>.refused``, a warning each) every link or special file where the
        run keeps files: its own files and the entries of its directories (CSVs: at
        :func:`~rlpipe.metrics.truncate_metrics`)."""
        named = [self.path / name for name in (self.SUMMARY, self.CURVE, self.LOG, "mlflow.db")]
        listed = [
            entry
            for name in (self.CHECKPOINTS, self.VIDEOS, self.EVALUATION, self.EXPORT, self.HYDRA)
            if (self.path / name).is_dir()
            for entry in sorted((self.path / name).iterdir())
            if not entry.is_dir() or entry.is_symlink()
        ]
        for path in [*named, *listed]:
            what = strange(path)
            if what is not None and REFUSED_SUFFIX not in path.name:
                aside = set_aside(path)
                warn(
                    f"{path} was {what}, not a file of this run: moved it to {aside.name} "
                    "(nothing was read or written through it)"
                )

    def _checkpoint_files(self) -> tuple[tuple[str, int, int], ...]:
        """Name, size and modification time of every resume point."""
        return tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in self.checkpoints())


def frames_of(checkpoint: Path) -> int:
    """The frames in a checkpoint's name (``ckpt_<frames>.pt``, ``best_<frames>.pt``)."""
    return int(checkpoint.stem.rpartition("_")[2])
