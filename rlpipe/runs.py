"""Many run dirs at once: the runs below some directories (a sweep), the newest one, and runs
grouped by the overrides that made them (the seeds of one setting together)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from omegaconf import OmegaConf

from rlpipe.config import flatten
from rlpipe.errors import check
from rlpipe.metrics import EVAL_METRIC, parse_rows, read_metric_bytes
from rlpipe.rundir import RunDir

# overrides that never tell experiments apart: seeds are what a group averages over, and a resumed
# run is the run it continues
NOT_GROUPED = ("seed", "resume")
T = TypeVar("T")


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

    runs = [path.parent for path in Path(root).glob(f"**/{RunDir.CONFIG}")]
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
    return override.split("=")[0].lstrip("+~")


def group_by_overrides(
    items: Sequence[T], overrides_of: Callable[[T], Sequence[str]]
) -> list[tuple[str, list[T]]]:
    """``items`` grouped by their overrides but for ``seed`` and ``resume``, each group with its
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
    """Group runs that differ only by ``seed`` (or ``resume``), labelled by what sets them apart.

    The groups and labels of :func:`group_by_overrides`, over the overrides that made each run."""
    return [Group(label, members) for label, members in group_by_overrides(runs, run_overrides)]
