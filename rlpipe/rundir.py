"""One run's directory: its layout and every read and write of it, in :class:`RunDir`.

A run dir holds one run: ``config.yaml`` (the whole resolved config), ``checkpoints/``
(``ckpt_<frames>.pt`` resume points, ``best_<frames>.pt`` the best evaluation's),
``metrics/scalars/`` (one CSV per metric), ``summary.json``, Hydra's record ``.hydra/`` and, while
a process trains in it, ``.lock``. A run dir is data: nothing in it is imported unless the caller
says it trusts the dir, and nothing is read or written through a symbolic link or special file
in it (the run dir itself, its directories and its files): such a directory, or such a
``config.yaml``, is refused in one line; such a file is skipped when reading and set aside
(``<name>.refused``, with a warning) when a run begins. Imports no torch and nothing of the
algorithms.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from omegaconf import DictConfig, OmegaConf

from rlpipe.checkpoint import CorruptCheckpoint, fitting, load_checkpoint, loads, save_checkpoint
from rlpipe.config import (
    Config,
    config_from_yaml,
    config_to_dict,
    fingerprint,
    fingerprint_diff,
    split_init_from,
)
from rlpipe.console import warn
from rlpipe.errors import RlpipeError, RunDirConflict, check
from rlpipe.files import TEMP_SUFFIX, NotOwnFile, read_regular, strange, write_atomic
from rlpipe.layout import RunLayout, frames_of
from rlpipe.lock import locked
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


class RunDir(RunLayout):
    """The directory ``path`` of one run, and the only code that reads or writes it.

    Training opens it in two steps: :meth:`open` checks that a config is this dir's run and
    reads the checkpoint to resume from (nothing is written), and :meth:`session`, once the run
    is built, takes the lock and begins the run (links and special files set aside,
    ``config.yaml``, metrics cut back to the checkpoint, old checkpoints pruned, a best
    checkpoint from the part being redone removed); :meth:`save_checkpoint`, :meth:`save_best`
    and :meth:`write_summary` need the session. The read side (:meth:`read_config`,
    :meth:`read_checkpoint`, :meth:`metric`, :meth:`read_summary`, :meth:`overrides`) serves
    ``load_run``, ``rlpipe.evaluate``, ``rlpipe.plot`` and sweeps. Its layout, and which of its
    entries are its own: :class:`~rlpipe.layout.RunLayout`.
    """

    def __init__(self, path: str | Path) -> None:
        super().__init__(path)
        self._lock = False  # whether a session holds the lock
        self._opened: tuple | None = None  # the checkpoints open() saw (None: not opened)
        self._keep = 3

    # -- reading
    def read_config(self, *, allow_code: bool = False) -> Config:
        """The :class:`Config` the run was started with.

        A run dir is data: an ``env.id`` of the form ``module:Id`` (which makes gymnasium import
        ``module``) or an ``algo.network`` (whose ``_target_`` is imported and called) is refused
        unless ``allow_code`` (only for run dirs you trust).
        """
        path = self.path / self.CONFIG
        check(os.path.lexists(self.path), f"run directory {self.path} does not exist")
        self.check_layout()
        check(
            path.is_file(),
            f"{self.path} is not an rlpipe run directory (no {self.CONFIG}); "
            "pass a directory a training run wrote, e.g. outputs/<date>/<time>",
        )
        return config_from_yaml(read_regular(path), path, allow_code=allow_code)

    def identity(self) -> tuple[str, str]:
        """``(env id, algorithm)`` as ``config.yaml`` names them ("?" where unknown), for
        titles: read as plain data, whatever the config's state."""
        cfg = self.read_yaml(self.CONFIG) or OmegaConf.create()
        return tuple(
            str(OmegaConf.select(cfg, key, default="?")) for key in ("env.id", "algo.name")
        )

    def check_same_run(self, cfg: Config, recorded: Config) -> None:
        """Unless ``cfg`` is the run this dir holds (``recorded``, its config: same fingerprint),
        :class:`RunDirConflict` naming the keys that differ."""
        ours, theirs = fingerprint(cfg), fingerprint(recorded)
        if ours != theirs:
            raise RunDirConflict(
                f"{self.path} belongs to another run: it differs in "
                f"{fingerprint_diff(ours, theirs)}; resume it with the overrides it was started "
                f"with ({self.original_command()} resume={self.path}) or pick another run dir "
                "(hydra.run.dir=<dir>)"
            )

    def read_checkpoint(self, name: str | None = None) -> Checkpoint:
        """The newest checkpoint that loads (``name`` None), the best evaluation's (``"best"``),
        the one at a frame count (``"4096"``: ``ckpt_000000004096.pt``), or
        ``checkpoints/<name>``."""
        self.check_layout()
        if name is not None and name.isdigit():
            name = self._at_frames(int(name))
        if name in (None, "best"):
            self._own("best_*.pt" if name else "ckpt_*.pt", say=True)
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
        check(os.path.lexists(path), f"checkpoint {path} does not exist")
        return Checkpoint(path, load_checkpoint(path))

    def _at_frames(self, frames: int) -> str:
        """The name of the resume point at ``frames``; one line listing those there if none."""
        name, found = f"ckpt_{frames:012d}.pt", self.checkpoints()
        there = [f"{frames_of(path):,}" for path in found]
        check(
            name in [path.name for path in found],
            f"{self.path} has no checkpoint at {frames:,} frames (checkpoints/{name}); it has "
            f"{', '.join(there) or 'none'} (keep_checkpoints keeps the newest), or best",
        )
        return name

    def parent(self) -> tuple[Path, int] | None:
        """The run this one was fine-tuned from (``init_from`` in ``config.yaml``) and the
        frames of the checkpoint it started from; None for a run started from scratch."""
        spec = OmegaConf.select(self.read_yaml(self.CONFIG) or OmegaConf.create(), "init_from")
        if not spec:
            return None
        where, name = split_init_from(str(spec))
        if name is None or not name.endswith(".pt"):  # not pinned: not written by train
            return None
        return Path(where), frames_of(Path(name))

    def metric(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """``(frames, values)`` of one logged metric; empty arrays when the run has none (or
        its file is reached through a link: then a warning says so)."""
        path = self.metric_path(name)
        if os.path.lexists(path) and not self._inside(path):
            warn(f"skipped {path}: reached through a symbolic link")
            path = self.path / "missing"
        return read_metric(path)

    def read_summary(self) -> RunResult | None:
        """What ``summary.json`` reports, or None (not written, or not readable)."""
        try:
            data = json.loads(read_regular(self.path / self.SUMMARY))
            return RunResult(**{"run_dir": str(self.path), **data})
        except (OSError, ValueError, TypeError):
            return None

    def overrides(self) -> list[str]:
        """The command-line overrides the run was started with (Hydra's record; none from
        Python)."""
        record = self.read_yaml(f"{self.HYDRA}/overrides.yaml")
        return [str(o) for o in record] if record is not None else []

    def read_yaml(self, name: str) -> Any:
        """The run dir's file ``name`` (e.g. ``.hydra/hydra.yaml``) loaded as plain YAML data,
        or None (missing, unreadable, not the run's own)."""
        path = self.path / name
        try:
            return OmegaConf.load(io.BytesIO(read_regular(path))) if self._inside(path) else None
        except (OSError, ValueError, TypeError):
            return None

    def original_command(self) -> str:
        """``python -m rlpipe <the overrides the run was started with>``."""
        return " ".join(["python -m rlpipe", *self.overrides()])

    # -- training
    def precheck(self, *, required: bool) -> Config | None:
        """:meth:`open`'s first, torch-free step: the dir's layout and, where it holds a run (or
        ``required``: ``resume=``), its config, returned (None: no run here yet). The command
        line calls it before torch loads: a bad run dir fails at once, not after the imports."""
        if required or self.is_run():
            return self.read_config(allow_code=True)
        if os.path.lexists(self.path):
            self.check_layout()
        return None

    def open(self, cfg: Config, *, required: bool) -> Checkpoint | None:
        """Check that ``cfg`` is the run this dir holds, if it holds one, and return the
        checkpoint to resume from (None: start at zero). Writes nothing.

        ``required`` (``resume=<dir>``): a dir without any checkpoint is an error. Damaged
        checkpoints are skipped with a warning; one written by another run is refused.
        """
        recorded = self.precheck(required=required)
        if recorded is not None:
            self.check_same_run(cfg, recorded)
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
        if self._lock:
            yield
            return
        self.check_layout()
        with ExitStack() as stack:
            try:
                stack.enter_context(locked(self.path, self.LOCK))
            except OSError as err:
                raise self.unwritable(err) from err
            self._lock, self._keep = True, keep
            stack.callback(setattr, self, "_lock", False)
            self._begin(config, frames)
            yield

    def _begin(self, config: Config | None, frames: int) -> None:
        """What a session does first, holding the lock (see the class docstring)."""
        if self._opened is not None and self._checkpoint_files() != self._opened:
            raise RunDirConflict(
                f"{self.path} changed while this run was being built (another process "
                "wrote checkpoints since it was opened); start it again"
            )
        try:
            self._set_aside_strangers()
            if config is not None:
                self.save_config(config)
            truncate_metrics(self.scalars_dir, frames)
            self._prune()
            best = self.bests()
            kept = [path for path in best if frames_of(path) <= frames][-1:]
            for path in best:
                if path not in kept:
                    path.unlink()
        except OSError as err:
            raise self.unwritable(err) from err

    def save_config(self, cfg: Config) -> Path:
        """Write ``config.yaml`` unless it already holds ``cfg`` (atomically)."""
        path = self.path / self.CONFIG
        data = OmegaConf.to_yaml(config_to_dict(cfg)).encode()
        try:
            if path.is_file() and not strange(path) and read_regular(path) == data:
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
        for name, data in (
            ("config.yaml", job_cfg),
            ("hydra.yaml", OmegaConf.create({"hydra": hydra_cfg})),
            ("overrides.yaml", hydra_cfg.overrides.task),
        ):
            write_atomic(record / name, OmegaConf.to_yaml(data).encode())

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
            except (CorruptCheckpoint, NotOwnFile) as err:
                damaged.append(str(err))
                continue
            for message in damaged:
                warn(f"{message}; using {path.name} instead")
            return Checkpoint(path, state)
        raise RlpipeError(
            f"every checkpoint in {self.checkpoints_dir} is damaged ({len(found)} files); "
            "cannot resume"
        )

    def _prune(self) -> None:
        """Keep the newest ``keep`` resume points that load, delete older ones, move damaged (or
        refused) ones to ``checkpoints/damaged/`` with a warning, and remove the temp files of
        killed writes. Only the run's own regular files count (:meth:`checkpoints`)."""
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
                warn(f"moved damaged checkpoint {path} to {aside}")

    def _check_session(self) -> None:
        assert self._lock, "RunDir writes need a session (RunDir.session)"
