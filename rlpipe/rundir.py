"""What a run directory holds and how to load it back: ``config.yaml`` and ``checkpoints/``.

Every run writes ``config.yaml`` (the whole :class:`Config`, the algorithm's ``name``
included) before training; ``evaluate``, ``resume`` and research code rebuild the run from it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, is_dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch
from omegaconf import OmegaConf

from rlpipe.algos import ALGORITHMS, Algorithm, make_algorithm
from rlpipe.checkpoint import list_checkpoints, load_checkpoint, load_latest
from rlpipe.config import Config, EnvConfig, LoggerConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError, check

CONFIG_FILE = "config.yaml"


def config_to_dict(cfg: Config) -> dict[str, Any]:
    """``cfg`` as plain containers (what ``config.yaml`` and checkpoints store)."""
    return OmegaConf.to_container(OmegaConf.structured(cfg))


def config_from_dict(data: dict[str, Any]) -> Config:
    """Rebuild a :class:`Config` (value checks included) from :func:`config_to_dict` output."""
    data = dict(data)
    algo = dict(data.pop("algo"))
    check(algo.get("name") in ALGORITHMS, f"unknown algorithm {algo.get('name')!r} in config")
    return Config(
        env=_build(EnvConfig, data.pop("env")),
        algo=_build(ALGORITHMS[algo["name"]][0], algo),
        logger=_build(LoggerConfig, data.pop("logger")),
        **{k: v for k, v in data.items() if k in _names(Config)},
    )


def _names(cls: type) -> set[str]:
    return {f.name for f in fields(cls)}


def _build(cls: type, data: dict[str, Any]) -> Any:
    # keys a newer/older version does not know are dropped; missing ones take the default
    assert is_dataclass(cls)
    return cls(**{k: v for k, v in data.items() if k in _names(cls)})


def save_config(cfg: Config, run_dir: str | Path) -> Path:
    """Write ``run_dir/config.yaml``."""
    path = Path(run_dir) / CONFIG_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(OmegaConf.to_yaml(config_to_dict(cfg)))
    return path


def load_config(run_dir: str | Path) -> Config:
    """The :class:`Config` a run was started with (``run_dir/config.yaml``)."""
    path = Path(run_dir) / CONFIG_FILE
    check(Path(run_dir).is_dir(), f"run directory {run_dir} does not exist")
    check(
        path.is_file(),
        f"{run_dir} is not an rlpipe run directory (no {CONFIG_FILE}); "
        "pass a directory a training run wrote, e.g. outputs/<date>/<time>",
    )
    return config_from_dict(OmegaConf.to_container(OmegaConf.load(path)))


@dataclass
class LoadedRun:
    """A run rebuilt from its directory: config, algorithm (weights loaded), checkpoint used."""

    cfg: Config
    algo: Algorithm
    checkpoint: Path


def find_checkpoint(run_dir: str | Path, name: str | None = None) -> Path:
    """``run_dir/checkpoints/<name>``, or the newest checkpoint when ``name`` is None."""
    directory = Path(run_dir) / "checkpoints"
    if name is not None:
        path = directory / name if not Path(name).is_absolute() else Path(name)
        check(path.is_file(), f"checkpoint {path} does not exist")
        return path
    found = list_checkpoints(directory)
    check(bool(found), f"{run_dir} has no checkpoint yet (nothing in {directory}); train first")
    return found[-1]


def load_run(
    run_dir: str | Path,
    checkpoint: str | None = None,
    *,
    device: str | torch.device = "cpu",
    num_envs: int = 1,
) -> LoadedRun:
    """Rebuild a run's algorithm on ``num_envs`` fresh env copies and load its checkpoint.

    The caller owns ``LoadedRun.algo`` and must ``close()`` it.
    """
    cfg = load_config(run_dir)
    path = find_checkpoint(run_dir, checkpoint)
    try:
        state = load_checkpoint(path)
    except Exception as err:  # noqa: BLE001  (torch raises many kinds on a damaged file)
        raise RlpipeError(f"cannot load checkpoint {path}: {err}".splitlines()[0]) from err
    factory = partial(make_env, cfg.env, num_envs=num_envs, seed=cfg.seed)
    algo = make_algorithm(factory, cfg.algo, device=device)
    algo.load_state_dict(state["algo"])
    return LoadedRun(cfg, algo, path)


def original_command(run_dir: str | Path) -> str:
    """``python -m rlpipe <the overrides the run was started with>`` (from Hydra's record)."""
    path = Path(run_dir) / ".hydra" / "overrides.yaml"
    overrides = OmegaConf.load(path) if path.is_file() else []
    return " ".join(["python -m rlpipe", *map(str, overrides)])


def resume_state(cfg: Config, run_dir: str | Path, *, required: bool) -> dict[str, Any] | None:
    """The checkpoint to continue ``run_dir`` from, after checking ``cfg`` is the same run.

    The run must have been the same algorithm on the same env (other keys, e.g. a larger
    ``total_frames``, may differ). Damaged checkpoints are skipped with a warning; with
    ``required`` (``resume=<dir>``) a run dir without any checkpoint is an error, otherwise
    the run starts from zero.
    """
    run_dir = Path(run_dir)
    stored = load_config(run_dir)
    if (stored.algo.name, stored.env.id) != (cfg.algo.name, cfg.env.id):
        raise RlpipeError(
            f"{run_dir} holds a run of algo={stored.algo.name} on {stored.env.id}, not "
            f"algo={cfg.algo.name} on {cfg.env.id}; resume it with the overrides it was started "
            f"with ({original_command(run_dir)} resume={run_dir}) or pick another run dir"
        )
    if not list_checkpoints(run_dir / "checkpoints"):
        check(not required, f"{run_dir} has no checkpoint to resume from; start a new run")
        return None
    _, state = load_latest(run_dir / "checkpoints")
    return state


def truncate_metrics(run_dir: str | Path, frames: int) -> None:
    """Drop CSV metric rows logged after ``frames`` (they belong to the lost part of a run)."""
    for path in (Path(run_dir) / "metrics" / "scalars").rglob("*.csv"):
        lines = path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if line.strip() and float(line.split(",", 1)[0]) <= frames]
        if len(kept) != len(lines):
            path.write_text("".join(kept))
