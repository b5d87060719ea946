"""One run's directory: its layout and every read and write of it, in :class:`RunDir`.

A run dir holds one run: ``config.yaml`` (the whole resolved config), ``checkpoints/``
(``ckpt_<frames>.pt`` resume points, ``best_<frames>.pt`` the best evaluation's),
``metrics/scalars/`` (one CSV per metric), ``summary.json``, Hydra's record ``.hydra/`` and, while
a process trains in it, ``.lock``. A run dir is data: nothing in it is imported unless the caller
says it trusts the dir. Imports no torch and nothing of the algorithms.
"""

from __future__ import annotations

import fcntl
import json
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from rlpipe.checkpoint import CorruptCheckpoint, fitting, load_checkpoint, loads, save_checkpoint
from rlpipe.config import Config, config_from_yaml, config_to_dict, fingerprint, fingerprint_diff
from rlpipe.errors import RlpipeError, RunDirConflict, check
from rlpipe.files import TEMP_SUFFIX, write_atomic
from rlpipe.metrics import read_metric, truncate_metrics
from rlpipe.outcomes import RunResult

if TYPE_CHECKING:
    import numpy as np


@dataclass
class Checkpoint:
    """A checkpoint read back: its file and the state it holds (``state["frames"]`` frames in)."""

    path: Path
    state: dict[str, Any]

    @property
    def frames(self) -> int:
        return int(self.state["frames"])

    @contextmanager
    def applying(self) -> Iterator[None]:
        """Any error while applying :attr:`state` becomes one line naming the file."""
        with fitting(self.path):
            yield


class RunDir:
    """The directory ``path`` of one run, and the only code that reads or writes it.

    Training opens it in two steps: :meth:`open` checks that a config is this dir's run and
    reads the checkpoint to resume from (nothing is written), and :meth:`session`, once the run
    is built, takes the lock and begins the run (``config.yaml``, metrics cut back to the
    checkpoint, old checkpoints pruned, a best checkpoint from the part being redone removed);
    :meth:`save_checkpoint`, :meth:`save_best` and :meth:`write_summary` need the session. The
    read side (:meth:`read_config`, :meth:`read_checkpoint`, :meth:`metric`, :meth:`read_summary`,
    :meth:`overrides`) serves ``load_run``, ``rlpipe.evaluate``, ``rlpipe.plot`` and sweeps.
    """

    CONFIG = "config.yaml"
    LOCK = ".lock"
    CHECKPOINTS = "checkpoints"
    METRICS = "metrics"  # metrics/scalars/<name>.csv (TorchRL CSVLogger's layout)
    SUMMARY = "summary.json"
    HYDRA = ".hydra"
    VIDEOS = "videos"  # videos/eval_<frames>.mp4 (video=true)
    EVALUATION = "evaluation"  # evaluation/<policy>.json (python -m rlpipe.evaluate)
    CURVE = "curve.png"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._lock: int | None = None  # the lock file's descriptor while a session holds it
        self._opened: tuple | None = None  # the checkpoints open() saw (None: not opened)
        self._keep = 3

    def __fspath__(self) -> str:
        return str(self.path)

    def __repr__(self) -> str:
        return f"RunDir({str(self.path)!r})"

    # -- layout
    @property
    def checkpoints_dir(self) -> Path:
        return self.path / self.CHECKPOINTS

    @property
    def scalars_dir(self) -> Path:
        return self.path / self.METRICS / "scalars"

    def metric_path(self, name: str) -> Path:
        """Where metric ``name`` (e.g. ``eval/return_mean``) is logged."""
        return self.scalars_dir / f"{name}.csv"

    # -- reading
    def is_run(self) -> bool:
        """Whether a run was started here (``config.yaml`` exists)."""
        return (self.path / self.CONFIG).is_file()

    def read_config(self, *, allow_code: bool = False) -> Config:
        """The :class:`Config` the run was started with.

        A run dir is data: an ``env.id`` of the form ``module:Id`` (which makes gymnasium import
        ``module``) or an ``algo.network`` (whose ``_target_`` is imported and called) is refused
        unless ``allow_code`` (only for run dirs you trust).
        """
        path = self.path / self.CONFIG
        check(self.path.is_dir(), f"run directory {self.path} does not exist")
        check(
            path.is_file(),
            f"{self.path} is not an rlpipe run directory (no {self.CONFIG}); "
            "pass a directory a training run wrote, e.g. outputs/<date>/<time>",
        )
        return config_from_yaml(path.read_bytes(), path, allow_code=allow_code)

    def identity(self) -> tuple[str, str]:
        """``(env id, algorithm)`` as ``config.yaml`` names them ("?" where unknown), for
        titles: read as plain data, whatever the config's state."""
        path = self.path / self.CONFIG
        cfg = OmegaConf.load(path) if path.is_file() else OmegaConf.create()
        return tuple(
            str(OmegaConf.select(cfg, key, default="?")) for key in ("env.id", "algo.name")
        )

    def check_same_run(self, cfg: Config) -> None:
        """Unless ``cfg`` is the run this dir holds (same fingerprint), :class:`RunDirConflict`
        naming the keys that differ."""
        ours, theirs = fingerprint(cfg), fingerprint(self.read_config(allow_code=True))
        if ours != theirs:
            raise RunDirConflict(
                f"{self.path} belongs to another run: it differs in "
                f"{fingerprint_diff(ours, theirs)}; resume it with the overrides it was started "
                f"with ({self.original_command()} resume={self.path}) or pick another run dir "
                "(hydra.run.dir=<dir>)"
            )

    def checkpoints(self) -> list[Path]:
        """The resume points (``ckpt_<frames>.pt``: names sort by frames), oldest first."""
        return sorted(self.checkpoints_dir.glob("ckpt_*.pt"))

    def bests(self) -> list[Path]:
        """The best evaluation's checkpoints (``best_<frames>.pt``, not resume points), oldest
        first: the last is the best (one, unless a process died between writing a new one and
        removing the old)."""
        return sorted(self.checkpoints_dir.glob("best_*.pt"))

    def latest_checkpoint(self) -> Path | None:
        found = self.checkpoints()
        return found[-1] if found else None

    def read_checkpoint(self, name: str | None = None) -> Checkpoint:
        """The newest checkpoint that loads (``name`` None), the best evaluation's (``"best"``),
        or ``checkpoints/<name>``."""
        if name == "best":
            best = self.bests()
            check(
                bool(best),
                f"{self.path} has no best checkpoint (checkpoints/best_*.pt, kept at each "
                "evaluation better than the ones before); evaluate the newest with checkpoint=null",
            )
            return Checkpoint(best[-1], load_checkpoint(best[-1]))
        if name is None:
            check(
                bool(self.checkpoints()),
                f"{self.path} has no checkpoint yet (nothing in {self.checkpoints_dir}); "
                "train first",
            )
            return self._newest()
        path = self.checkpoints_dir / name if not Path(name).is_absolute() else Path(name)
        check(path.is_file(), f"checkpoint {path} does not exist")
        return Checkpoint(path, load_checkpoint(path))

    def metric(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """``(frames, values)`` of one logged metric; empty arrays when the run has none."""
        return read_metric(self.metric_path(name))

    def read_summary(self) -> RunResult | None:
        """What ``summary.json`` reports, or None (not written, or not readable)."""
        try:
            data = json.loads((self.path / self.SUMMARY).read_text())
            return RunResult(**{"run_dir": str(self.path), **data})
        except (OSError, ValueError, TypeError):
            return None

    def overrides(self) -> list[str]:
        """The command-line overrides the run was started with (Hydra's record; none from
        Python)."""
        path = self.path / self.HYDRA / "overrides.yaml"
        return [str(o) for o in OmegaConf.load(path)] if path.is_file() else []

    def original_command(self) -> str:
        """``python -m rlpipe <the overrides the run was started with>``."""
        return " ".join(["python -m rlpipe", *self.overrides()])

    # -- training
    def open(self, cfg: Config, *, required: bool) -> Checkpoint | None:
        """Check that ``cfg`` is the run this dir holds, if it holds one, and return the
        checkpoint to resume from (None: start at zero). Writes nothing.

        ``required`` (``resume=<dir>``): a dir without any checkpoint is an error. Damaged
        checkpoints are skipped with a warning; one written by another run is refused.
        """
        if required or self.is_run():
            self.check_same_run(cfg)
        self._opened = self._checkpoint_files()
        if not self.checkpoints():
            check(not required, f"{self.path} has no checkpoint to resume from; start a new run")
            return None
        found = self._newest()
        stored = found.state.get("config") if isinstance(found.state, dict) else None
        if isinstance(stored, dict) and fingerprint(cfg) != fingerprint(stored):
            raise RunDirConflict(
                f"checkpoint {found.path} was written by another run: it differs in "
                f"{fingerprint_diff(fingerprint(cfg), fingerprint(stored))}; pick another run "
                "dir (hydra.run.dir=<dir>)"
            )
        return found

    @contextmanager
    def session(self, config: Config | None, frames: int, keep: int) -> Iterator[None]:
        """Hold the lock and begin the run at ``frames`` (see the class docstring); a session
        already held by this object is joined. ``config`` (None: not known) is written to
        ``config.yaml``; ``keep`` checkpoints are kept."""
        if self._lock is not None:
            yield
            return
        with self._locked():
            self._keep = keep
            if self._opened is not None and self._checkpoint_files() != self._opened:
                raise RunDirConflict(
                    f"{self.path} changed while this run was being built (another process "
                    "wrote checkpoints since it was opened); start it again"
                )
            try:
                if config is not None:
                    self.save_config(config)
                truncate_metrics(self.scalars_dir, frames)
                self._prune()
                best = self.bests()
                kept = [path for path in best if _frames(path) <= frames][-1:]
                for path in best:
                    if path not in kept:
                        path.unlink()
            except OSError as err:
                raise self.unwritable(err) from err
            yield

    @contextmanager
    def _locked(self) -> Iterator[None]:
        """The lock file, held: a second process trying to lock the dir gets
        :class:`RunDirConflict` naming the holder's PID (the OS drops the lock with the process,
        however it dies)."""
        path = self.path / self.LOCK
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as err:
            raise self.unwritable(err) from err
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                raise RunDirConflict(
                    f"{self.path} is in use by another rlpipe process (pid {holder}); wait for "
                    "it to end or pick another run dir (hydra.run.dir=<dir>)"
                ) from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
            self._lock = fd
            yield
        finally:
            self._lock = None
            os.close(fd)  # closing the descriptor releases the lock

    def save_config(self, cfg: Config) -> Path:
        """Write ``config.yaml`` unless it already holds ``cfg`` (atomically)."""
        path = self.path / self.CONFIG
        data = OmegaConf.to_yaml(config_to_dict(cfg)).encode()
        try:
            if path.is_file() and path.read_bytes() == data:
                return path
            self.path.mkdir(parents=True, exist_ok=True)
            write_atomic(path, data)
        except OSError as err:
            raise self.unwritable(err) from err
        return path

    def save_checkpoint(self, state: dict[str, Any], frames: int) -> Path:
        """Write the resume point at ``frames`` (atomically) and prune to the newest ``keep``."""
        self._check_session()
        path = save_checkpoint(state, self.checkpoints_dir / f"ckpt_{frames:012d}.pt")
        self._prune()
        return path

    def save_best(self, state: dict[str, Any], frames: int) -> Path:
        """Write the best evaluation's checkpoint (``best_<frames>.pt``), then drop older ones."""
        self._check_session()
        older = self.bests()
        path = self.checkpoints_dir / f"best_{frames:012d}.pt"
        save_checkpoint(state, path, fault="best_write")
        for stale in older:
            stale.unlink(missing_ok=True)
        return path

    def write_summary(self, result: RunResult) -> None:
        """Write ``summary.json`` (atomically)."""
        self._check_session()
        text = json.dumps(asdict(result), indent=2) + "\n"
        write_atomic(self.path / self.SUMMARY, text.encode(), fault="summary")

    def write_hydra_record(self, job_cfg: DictConfig, hydra_cfg: DictConfig) -> None:
        """Hydra's record of the job (``.hydra/config.yaml``, ``hydra.yaml``,
        ``overrides.yaml``) unless the dir has one: a resumed run keeps the record of its start.

        ``conf/config.yaml`` turns Hydra's own writing off (``hydra.output_subdir: null``):
        Hydra writes before a job can check that the dir is its own."""
        record = self.path / self.HYDRA
        try:
            record.mkdir(parents=True)
        except FileExistsError:
            return
        OmegaConf.save(job_cfg, record / "config.yaml")
        OmegaConf.save(OmegaConf.create({"hydra": hydra_cfg}), record / "hydra.yaml")
        OmegaConf.save(hydra_cfg.overrides.task, record / "overrides.yaml")

    def unwritable(self, err: OSError) -> RlpipeError:
        """The one-line error for a run dir that cannot be written."""
        return RlpipeError(
            f"cannot write the run directory {self.path}: {err.strerror or err}; "
            "pick a writable one with hydra.run.dir=<dir>"
        )

    def _newest(self) -> Checkpoint:
        """The newest resume point that loads, past damaged ones (a warning each)."""
        found = self.checkpoints()
        check(bool(found), f"no checkpoint in {self.checkpoints_dir}")
        damaged = []
        for path in reversed(found):
            try:
                state = load_checkpoint(path)
            except CorruptCheckpoint as err:
                damaged.append(str(err))
                continue
            for message in damaged:
                print(f"rlpipe: warning: {message}; using {path.name} instead", file=sys.stderr)
            return Checkpoint(path, state)
        raise RlpipeError(
            f"every checkpoint in {self.checkpoints_dir} is damaged ({len(found)} files); "
            "cannot resume"
        )

    def _prune(self) -> None:
        """Keep the newest ``keep`` resume points that load, delete older ones, move damaged (or
        refused) ones to ``checkpoints/damaged/`` with a warning, and remove the temp files of
        killed writes."""
        for temp in self.checkpoints_dir.glob(f".*.pt{TEMP_SUFFIX}"):  # of a ckpt or a best
            temp.unlink(missing_ok=True)
        kept = 0
        for path in reversed(self.checkpoints()):
            if kept >= self._keep:
                path.unlink()
            elif loads(path):
                kept += 1
            else:
                aside = self.checkpoints_dir / "damaged" / path.name
                aside.parent.mkdir(exist_ok=True)
                os.replace(path, aside)
                print(
                    f"rlpipe: warning: moved damaged checkpoint {path} to {aside}", file=sys.stderr
                )

    def _checkpoint_files(self) -> tuple[tuple[str, int, int], ...]:
        """Name, size and modification time of every resume point."""
        return tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in self.checkpoints())

    def _check_session(self) -> None:
        assert self._lock is not None, "RunDir writes need a session (RunDir.session)"


def _frames(checkpoint: Path) -> int:
    """The frames in a checkpoint's name (``ckpt_<frames>.pt``, ``best_<frames>.pt``)."""
    return int(checkpoint.stem.rpartition("_")[2])
