"""Many run dirs at once: the runs below some directories (a sweep), the newest one, runs
grouped by the overrides that made them (the seeds of one setting together), and a fine-tuned
run's history through the runs it began from."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

from omegaconf import OmegaConf

from rlpipe.config import flatten
from rlpipe.console import warn
from rlpipe.errors import check
from rlpipe.metrics import EVAL_METRIC, parse_rows, read_metric_bytes
from rlpipe.rundir import RunDir

# overrides that never tell experiments apart: seeds are what a group averages over, a resumed
# run is the run it continues, and the rest change what is shown or kept, not what is learnt
NOT_GROUPED = ("seed", "resume", "progress", "log_every", "keep_checkpoints", "logger")
T = TypeVar("T")
MAX_GENERATIONS = 100  # init_from links followed at most (a hand-edited loop ends there)

if TYPE_CHECKING:
    import numpy as np


@dataclass
class Group:
    """Runs that differ only by seed (or a resume), and the overrides that set them apart."""

    label: str
    runs: list[Path]


def find_runs(dirs: Sequence[str | Path], metric: str = EVAL_METRIC) -> list[Path]:
    """Run dirs in ``dirs`` or below them (a multirun sweep dir) that logged ``metric``."""
    runs: list[Path] = []
    relative = RunDir("").metric_path(metric)
    for directory in map(Path, dirs):
        check(directory.is_dir(), f"{directory} is not a directory")
        found = sorted(
            p.parents[len(relative.parts) - 1]
            for p in directory.rglob(str(relative))
            if parse_rows(read_metric_bytes(p))
        )
        check(
            bool(found),
            f"no metrics under {directory}: no run dir with {relative} (runs with logger=none "
            "write none)",
        )
        runs += found
    return list(dict.fromkeys(runs))


def latest_run(root: str | Path = "outputs") -> Path:
    """The run dir under ``root`` (Hydra's ``outputs/``, sweeps included) that was written last:
    by the newest of its ``config.yaml``, ``summary.json`` and checkpoints."""

    def written(run: Path) -> float:
        rundir = RunDir(run)
        files = [run / RunDir.CONFIG, run / RunDir.SUMMARY, *rundir.checkpoints()]
        return max((os.lstat(f).st_mtime for f in files if os.path.lexists(f)), default=0.0)

    found = Path(root).glob(f"**/{RunDir.CONFIG}")  # Hydra's .hydra/config.yaml is no run dir
    runs = [path.parent for path in found if path.parent.name != RunDir.HYDRA]
    check(
        bool(runs),
        f"run_dir=latest found no run under {root}/ (no {RunDir.CONFIG}); train first "
        "(python -m rlpipe) in this directory, or pass run_dir=<dir>",
    )
    return max(runs, key=written)


def run_overrides(run_dir: Path) -> list[str]:
    """``key=value`` overrides that made ``run_dir``: Hydra's record, else its whole config."""
    rundir = RunDir(run_dir)
    if (run_dir / RunDir.HYDRA / "overrides.yaml").is_file():
        return rundir.overrides()
    config = rundir.read_yaml(RunDir.CONFIG)
    if config is None:
        return []
    flat = flatten(OmegaConf.to_container(config))
    return [f"{key}={value}" for key, value in flat.items()]


def _key(override: str) -> str:
    """The top-level key an override sets (``logger.project=x``: ``logger``)."""
    return override.split("=")[0].lstrip("+~").split(".")[0]


def group_by_overrides(
    items: Sequence[T], overrides_of: Callable[[T], Sequence[str]]
) -> list[tuple[str, list[T]]]:
    """``items`` grouped by their overrides but for :data:`NOT_GROUPED`'s, each group with its
    label: its overrides that not every group shares (a single group: its overrides, or
    "defaults"), in the order the groups first appear."""
    keyed: dict[frozenset[str], list[T]] = {}
    for item in items:
        overrides = frozenset(o for o in overrides_of(item) if _key(o) not in NOT_GROUPED)
        keyed.setdefault(overrides, []).append(item)
    common = frozenset.intersection(*keyed) if keyed else frozenset()
    return [
        (" ".join(sorted(overrides - common if len(keyed) > 1 else overrides)) or "defaults", group)
        for overrides, group in keyed.items()
    ]


def group_runs(runs: Sequence[Path]) -> list[Group]:
    """Group runs that differ only by ``seed``, labelled by what sets them apart.

    The groups and labels of :func:`group_by_overrides` (which also groups across the other keys
    of :data:`NOT_GROUPED`), over the overrides that made each run."""
    return [Group(label, members) for label, members in group_by_overrides(runs, run_overrides)]


def generations(run: str | Path) -> list[tuple[Path, int | None]]:
    """``run`` and the runs it was fine-tuned from (``init_from``), oldest first, each with the
    frames of its checkpoint that the next one began from (``run``'s: None). A parent that is
    no longer there ends the chain, with a warning."""
    chain: list[tuple[Path, int | None]] = [(Path(run), None)]
    while len(chain) <= MAX_GENERATIONS:
        child = chain[0][0]
        parent = RunDir(child).parent() if child.is_dir() else None
        if parent is None:
            break
        chain.insert(0, parent)
        if not parent[0].is_dir():
            warn(f"{parent[0]}, the run {child} began from, is not there: its curve is left out")
    return chain


def history(run: str | Path, metric: str) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """``(frames, values, starts)`` of ``metric`` over ``run``'s :func:`generations`: each
    parent's rows up to the checkpoint its child began from, then the child's, their frames
    counted on from there; ``starts``: the frames where each child began."""
    import numpy as np  # here: the command line reads no metric and loads no numpy

    frames, values, starts, offset = [], [], [], 0
    for path, cut in generations(run):
        at, value = RunDir(path).metric(metric)
        kept = at <= cut if cut is not None else np.ones(len(at), dtype=bool)
        frames.append(at[kept] + offset)
        values.append(value[kept])
        if cut is not None:
            offset += cut
            starts.append(offset)
    return np.concatenate(frames), np.concatenate(values), starts
