"""Where a run begins: fine-tuned from another run's checkpoint (``init_from``), or continued in
its own dir (``resume``), keeping how it began. Imports no torch."""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from rlpipe.config import Config, split_init_from
from rlpipe.errors import RlpipeError, RunDirConflict, check
from rlpipe.rundir import Checkpoint, RunDir

# what init_from takes besides the weights and the observation normaliser: the keys that ask
INIT_PARTS = {"optimizer": "init_optimizer", "buffer": "init_buffer"}
PART_NAMES = {"optimizer": "optimizer state", "buffer": "replay buffer"}


@dataclass
class Parent:
    """The run a new run starts from (``init_from``): its config and checkpoint."""

    path: Path
    cfg: Config
    checkpoint: Checkpoint

    @property
    def spec(self) -> str:
        """``init_from`` pinned: the absolute run dir and the checkpoint's file name."""
        return f"{os.path.abspath(self.path)}:{self.checkpoint.path.name}"

    @contextmanager
    def applying(self, cfg: Config) -> Iterator[None]:
        """Any error while the new run ``cfg`` takes this state becomes one line."""
        try:
            yield
        except RlpipeError:
            raise
        except Exception as err:  # noqa: BLE001  (load_state_dict raises many kinds)
            reason = str(err).strip().splitlines()[0][:200] if str(err).strip() else ""
            kwargs = self.cfg.env.kwargs
            differ = "" if cfg.env.kwargs == kwargs else f" (env.kwargs there: {kwargs})"
            raise RlpipeError(
                f"init_from={cfg.init_from}: {self.checkpoint.path.name} does not fit this run "
                f"({type(err).__name__}: {reason}); its env's observation and action shapes and "
                f"its networks must be the parent's{differ}"
            ) from err


def read_parent(cfg: Config) -> Parent:
    """The run ``cfg.init_from`` names, with its checkpoint (the newest by default), checked to
    fit ``cfg``: the same algorithm, env id and network shapes. Reads, writes nothing."""
    where, name = split_init_from(cfg.init_from)
    run = RunDir(where)
    try:
        parent = Parent(run.path, run.read_config(allow_code=True), run.read_checkpoint(name))
    except RlpipeError as err:
        colon = name is None and ":" in cfg.init_from  # a colon, but no checkpoint after it
        hint = " (after a colon: a frame count, best, or ckpt_<frames>.pt)" if colon else ""
        raise RlpipeError(f"init_from={cfg.init_from}: {err}{hint}") from err
    check_fits(cfg, parent.cfg)
    return parent


def check_fits(cfg: Config, parent: Config) -> None:
    """One line unless a run ``cfg`` can start from a run ``parent``'s weights: the same
    algorithm, env id and network-shaping keys (``architecture`` of the algorithm's config)."""
    ours, theirs, spec = cfg.algo, parent.algo, cfg.init_from
    check(
        ours.name == theirs.name,
        f"init_from={spec} is a {theirs.name} run and this one is {ours.name}: a fine-tuned run "
        f"keeps its parent's algorithm (algo={theirs.name})",
    )
    check(
        cfg.env.id == parent.env.id,
        f"init_from={spec} was trained on {parent.env.id} and this run is on {cfg.env.id}: a "
        f"fine-tuned run keeps its parent's env (env.id={parent.env.id}; env.kwargs may differ)",
    )
    differ = _first_difference(type(ours).architecture, ours, theirs)
    if differ is not None:
        key, here, there = differ
        raise RlpipeError(
            f"init_from={spec}: this run's networks differ from the parent's in algo.{key} "
            f"({here!r} here, {there!r} there); fine-tune with the parent's "
            f"({_override(f'algo.{key}', there)})"
        )
    differ = _first_difference(type(ours).buffer_keys if cfg.init_buffer else (), ours, theirs)
    if differ is not None:
        key, here, there = differ
        raise RlpipeError(
            f"init_buffer=true takes the parent's replay buffer as it was filled, but algo.{key} "
            f"differs ({here!r} here, {there!r} there): keep the parent's "
            f"({_override(f'algo.{key}', there)}) or drop init_buffer"
        )


def _first_difference(keys: Iterable[str], ours: Any, theirs: Any) -> tuple[str, Any, Any] | None:
    """The first of ``keys`` (those the configs have) whose values differ, with ours and theirs
    (None: none does)."""
    for key in keys:
        if hasattr(ours, key) and getattr(ours, key) != getattr(theirs, key):
            return key, getattr(ours, key), getattr(theirs, key)
    return None


def _override(key: str, value: Any) -> str:
    """``key=value`` as the command line takes it (a dict: "the parent's <key>")."""
    if isinstance(value, dict):
        return f"the parent's {key}"
    if isinstance(value, list):
        return f"{key}=[{','.join(map(str, value))}]"
    return f"{key}={str(value).lower() if isinstance(value, bool) else value}"


def init_parts(cfg: Config) -> list[str]:
    """What ``cfg`` takes of its parent besides the weights: ``"optimizer"``, ``"buffer"``."""
    return [part for part, key in INIT_PARTS.items() if getattr(cfg, key)]


def start_line(parent: Parent, cfg: Config) -> str:
    """The line a fine-tuned run starts with: where from, and what it took."""
    taken = ["networks (with any observation normaliser)"]
    taken += [PART_NAMES[part] for part in init_parts(cfg)]
    return (
        f"rlpipe: a new run from {parent.path} at {parent.checkpoint.frames:,} frames "
        f"({parent.checkpoint.path.name}): its {', '.join(taken)}; this run's hyper-parameters, "
        "with its frames and schedules from 0"
    )


def continued(cfg: Config, recorded: Config, run_dir: Path) -> Config:
    """``cfg`` continuing the run whose ``config.yaml`` is ``recorded``, in ``run_dir``: with the
    start that run had (``init_*``: a resume does not start again) and its schedules' axis
    (``algo.total_frames``, the frames it began with: a larger ``total_frames`` extends the run,
    it does not stretch its schedules). An ``init_from`` naming another parent is refused."""
    if cfg.init_from is not None and not _same_dir(cfg.init_from, recorded.init_from):
        began = f"from {recorded.init_from}" if recorded.init_from else "from scratch"
        raise RunDirConflict(
            f"init_from={cfg.init_from} starts a new run, but {run_dir} holds a run (begun "
            f"{began}) that this would continue: drop init_from to continue it, or give the new "
            "run a new run dir (hydra.run.dir=<dir>, no resume=)"
        )
    began = {key: getattr(recorded, key) for key in ("init_from", *INIT_PARTS.values())}
    algo = replace(cfg.algo, total_frames=recorded.algo.total_frames)
    return replace(cfg, algo=algo, **began)


def _same_dir(given: str, recorded: str | None) -> bool:
    """Whether two ``init_from`` values name the same run dir."""
    return recorded is not None and os.path.abspath(split_init_from(given)[0]) == os.path.abspath(
        split_init_from(recorded)[0]
    )


def extension_line(cfg: Config) -> str | None:
    """The line a continued run says when its length is not the one its schedules span."""
    axis = cfg.algo.total_frames
    if axis is None or cfg.total_frames is None or cfg.total_frames == axis:
        return None
    return (
        f"rlpipe: {cfg.total_frames:,} frames, where the run began with {axis:,}: its schedules "
        f"(a decaying learning rate, PPO's annealing) stay on those {axis:,} frames, at their end "
        "values past them"
    )
