"""A run's logged metrics, read back: one metric's CSV, the runs below a directory, and runs
grouped by the overrides that made them (seeds of one setting together).

Metrics are TorchRL ``CSVLogger`` files, ``<run dir>/metrics/scalars/<name>.csv``, one
``frames,value`` row per logged value and no header.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from rlpipe.errors import check
from rlpipe.loggers import METRICS_DIR

EVAL_METRIC = "eval/return_mean"


def metric_path(run_dir: str | Path, name: str) -> Path:
    """Where ``name`` (e.g. ``eval/return_mean``) lives in ``run_dir``."""
    return Path(run_dir) / METRICS_DIR / "scalars" / f"{name}.csv"


def read_metric(run_dir: str | Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(frames, values)`` of one metric; empty arrays when the run did not log it."""
    path = metric_path(run_dir, name)
    if not path.is_file() or path.stat().st_size == 0:
        return np.empty(0), np.empty(0)
    rows = np.loadtxt(path, delimiter=",", ndmin=2)
    return rows[:, 0], rows[:, 1]


@dataclass
class Group:
    """Runs that differ only by seed, and the overrides that set them apart from other groups."""

    label: str
    runs: list[Path]


def find_runs(dirs: Sequence[str | Path], metric: str = EVAL_METRIC) -> list[Path]:
    """Run dirs in ``dirs`` or below them (a multirun sweep dir) that logged ``metric``."""
    runs: list[Path] = []
    for directory in map(Path, dirs):
        check(directory.is_dir(), f"{directory} is not a directory")
        relative = metric_path("", metric)
        found = sorted(
            p.parents[len(relative.parts) - 1]
            for p in directory.rglob(str(relative))
            if p.stat().st_size > 0
        )
        check(
            bool(found),
            f"no metrics under {directory}: no run dir with {METRICS_DIR}/scalars/{metric}.csv "
            "(runs with logger=none write none)",
        )
        runs += found
    return list(dict.fromkeys(runs))


def run_overrides(run_dir: Path) -> list[str]:
    """``key=value`` overrides that made ``run_dir``: Hydra's record, else its whole config."""
    hydra_record = run_dir / ".hydra" / "overrides.yaml"
    if hydra_record.is_file():
        return list(OmegaConf.load(hydra_record))
    config = run_dir / "config.yaml"
    if not config.is_file():
        return []
    flat = _flatten(OmegaConf.to_container(OmegaConf.load(config)))
    return [f"{key}={value}" for key, value in flat.items()]


def _flatten(node: dict, prefix: str = "") -> dict[str, object]:
    flat: dict[str, object] = {}
    for key, value in node.items():
        if isinstance(value, dict) and value:
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _key(override: str) -> str:
    return override.split("=")[0].lstrip("+~")


def group_runs(runs: Sequence[Path]) -> list[Group]:
    """Group runs whose overrides agree but for ``seed``; label groups by what differs."""
    keyed: dict[frozenset[str], list[Path]] = {}
    for run in runs:
        overrides = frozenset(o for o in run_overrides(run) if _key(o) != "seed")
        keyed.setdefault(overrides, []).append(run)
    common = frozenset.intersection(*keyed) if keyed else frozenset()
    groups = []
    for overrides, members in keyed.items():
        label = " ".join(sorted(overrides - common))
        groups.append(Group(label or members[0].parent.name + "/" + members[0].name, members))
    return groups
