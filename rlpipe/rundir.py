"""What a run directory holds and how to load it back: ``config.yaml`` and ``checkpoints/``.

Every run writes ``config.yaml`` (the whole :class:`Config`, the algorithm's ``name``
included) before training; ``evaluate``, ``resume`` and research code rebuild the run from it.
A run dir belongs to one run: its :func:`fingerprint` (the keys that decide the results) must
match to resume in it, and :func:`lock_run_dir` keeps a second process out while one writes.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, fields, is_dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import OmegaConf
from torch import nn

from rlpipe.algos import ALGORITHMS, Algorithm, make_algorithm
from rlpipe.checkpoint import fitting, list_best, list_checkpoints, load_checkpoint, load_latest
from rlpipe.config import RUN_KEYS, Config, EnvConfig, LoggerConfig, flatten
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError, check
from rlpipe.files import write_atomic
from rlpipe.models import object_record

CONFIG_FILE = "config.yaml"
LOCK_FILE = ".lock"
# top-level keys that do not decide a run's results: its length and cadences, logging,
# progress, and where it runs (the algorithm's own are AlgoConfig.not_fingerprinted)
NOT_FINGERPRINTED = (
    *RUN_KEYS,
    "keep_checkpoints",
    "log_every",
    "progress",
    "video",
    "threads",
    "device",
    "resume",
    "logger",
)


class RunDirConflict(RlpipeError):
    """The run dir belongs to another run, or another process is writing it."""


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


def describe_run(algo: Algorithm, **run: Any) -> Config | None:
    """The :class:`Config` of a run a hand-built :class:`~rlpipe.runner.Runner` drives, or None.

    Known when ``algo`` is an rlpipe algorithm (its ``cfg`` a registered algorithm config)
    built on an env factory made as ``functools.partial(make_env, EnvConfig(...), seed=s)``
    (``seed`` left out: torch's initial seed, what :func:`~rlpipe.seed_everything` set). ``run``:
    the runner's :data:`~rlpipe.config.RUN_KEYS`, ``keep_checkpoints`` and ``progress``.
    """
    cfg, factory = getattr(algo, "cfg", None), getattr(algo, "env_factory", None)
    network = getattr(algo, "_network", None)  # given as an object: recorded by its class
    known = cfg is not None and ALGORITHMS.get(getattr(cfg, "name", None), (None,))[0] is type(cfg)
    by_make_env = isinstance(factory, partial) and factory.func is make_env
    if not (known and by_make_env and factory.args and isinstance(factory.args[0], EnvConfig)):
        return None
    env, options = factory.args[0], factory.keywords
    if options.get("num_envs"):
        env = replace(env, num_envs=options["num_envs"])
    seed = options.get("seed")
    return Config(
        env=env,
        algo=replace(
            cfg,
            **{key: run[key] for key in RUN_KEYS},
            **({} if network is None else {"network": object_record(network)}),
        ),
        seed=torch.initial_seed() % 2**32 if seed is None else seed,
        device=str(getattr(algo, "device", "auto")),
        **run,
    )


def fingerprint(cfg: Config | dict[str, Any]) -> dict[str, Any]:
    """What decides a run's results, flat (``{"algo.lr": 0.0001, "seed": 0, ...}``): algorithm,
    env, architecture, hyper-parameters and seed; not budgets, cadences, logging or progress."""
    data = config_to_dict(cfg) if isinstance(cfg, Config) else dict(cfg)
    algo = dict(data.get("algo") or {})
    schema = ALGORITHMS[algo["name"]][0] if algo.get("name") in ALGORITHMS else None
    for key in (*RUN_KEYS, *(schema.not_fingerprinted if schema else ())):
        algo.pop(key, None)
    data = {k: v for k, v in data.items() if k not in NOT_FINGERPRINTED}
    return flatten({**data, "algo": algo})


def fingerprint_diff(ours: dict[str, Any], theirs: dict[str, Any]) -> str:
    """The keys in which two fingerprints differ, as ``key (ours here, theirs there)``."""
    keys = [k for k in {**theirs, **ours} if ours.get(k) != theirs.get(k)]
    keys.sort(key=lambda k: k not in ("algo.name", "env.id"))  # what tells runs apart first
    shown = [f"{k} ({ours.get(k)!r} here, {theirs.get(k)!r} there)" for k in keys[:3]]
    more = f" and {len(keys) - 3} more" if len(keys) > 3 else ""
    return ", ".join(shown) + more


def check_same_run(cfg: Config, run_dir: str | Path) -> Config:
    """The config stored in ``run_dir``, after checking ``cfg`` is the same run (same
    fingerprint); otherwise :class:`RunDirConflict` names the differing keys."""
    stored = load_config(run_dir, allow_env_import=True)  # compared, not built
    ours, theirs = fingerprint(cfg), fingerprint(stored)
    if ours != theirs:
        raise RunDirConflict(
            f"{run_dir} belongs to another run: it differs in {fingerprint_diff(ours, theirs)}; "
            f"resume it with the overrides it was started with ({original_command(run_dir)} "
            f"resume={run_dir}) "
            "or pick another run dir (hydra.run.dir=<dir>)"
        )
    return stored


@contextmanager
def lock_run_dir(run_dir: str | Path) -> Iterator[None]:
    """Hold ``run_dir``'s lock file while the block runs: a second process trying to lock it
    gets :class:`RunDirConflict` naming the holder's PID (the OS drops the lock with the
    process, however it dies)."""
    path = Path(run_dir) / LOCK_FILE
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        raise unwritable(run_dir, err) from err
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise RunDirConflict(
                f"{run_dir} is in use by another rlpipe process (pid {holder}); wait for it to "
                "end or pick another run dir (hydra.run.dir=<dir>)"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def unwritable(run_dir: str | Path, err: OSError) -> RlpipeError:
    """The one-line error for a run dir that cannot be written."""
    return RlpipeError(
        f"cannot write the run directory {run_dir}: {err.strerror or err}; "
        "pick a writable one with hydra.run.dir=<dir>"
    )


def save_config(cfg: Config, run_dir: str | Path) -> Path:
    """Write ``run_dir/config.yaml`` unless it already holds ``cfg`` (atomically: a reader sees
    the old file or the new); an :class:`RlpipeError` if the dir cannot be written."""
    path = Path(run_dir) / CONFIG_FILE
    data = OmegaConf.to_yaml(config_to_dict(cfg)).encode()
    try:
        if path.is_file() and path.read_bytes() == data:
            return path
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, data)
    except OSError as err:
        raise unwritable(run_dir, err) from err
    return path


def load_config(run_dir: str | Path, *, allow_env_import: bool = False) -> Config:
    """The :class:`Config` a run was started with (``run_dir/config.yaml``).

    A run dir is data: an ``env.id`` of the form ``module:Id`` (which makes gymnasium import
    ``module``) or an ``algo.network`` (whose ``_target_`` is imported and called) is refused
    unless ``allow_env_import`` (only for run dirs you trust).
    """
    path = Path(run_dir) / CONFIG_FILE
    check(Path(run_dir).is_dir(), f"run directory {run_dir} does not exist")
    check(
        path.is_file(),
        f"{run_dir} is not an rlpipe run directory (no {CONFIG_FILE}); "
        "pass a directory a training run wrote, e.g. outputs/<date>/<time>",
    )
    try:
        data = yaml.safe_load(path.read_text())
        if not (isinstance(data, dict) and isinstance(data.get("algo"), dict)):
            raise ValueError("not a run config")
        cfg = config_from_dict(data)
    except (RlpipeError, yaml.YAMLError, TypeError, ValueError, KeyError, AttributeError) as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RlpipeError(f"{path} is damaged ({reason}); it is not a config rlpipe wrote") from err
    code = [f"env.id={cfg.env.id!r}"] if ":" in cfg.env.id else []
    if cfg.algo.network.get("_target_"):
        code.append(f"algo.network._target_={cfg.algo.network.get('_target_')!r}")
    check(
        allow_env_import or not code,
        f"{path} names {code[0] if code else ''}, which would import its module: a run dir "
        "is data, not code; pass allow_env_import=true if you trust this run dir",
    )
    return cfg


def latest_run(root: str | Path = "outputs") -> Path:
    """The run dir under ``root`` (Hydra's ``outputs/``, sweeps included) that was written last:
    by the newest of its ``config.yaml``, ``summary.json`` and checkpoints."""

    def written(run: Path) -> float:
        files = [run / CONFIG_FILE, run / "summary.json", *run.glob("checkpoints/*.pt")]
        return max(f.stat().st_mtime for f in files if f.is_file())

    runs = [path.parent for path in Path(root).glob(f"**/{CONFIG_FILE}")]
    check(
        bool(runs),
        f"run_dir=latest found no run under {root}/ (no {CONFIG_FILE}); train first "
        "(python -m rlpipe) in this directory, or pass run_dir=<dir>",
    )
    return max(runs, key=written)


@dataclass
class LoadedRun:
    """A run rebuilt from its directory: config, algorithm (weights loaded), checkpoint used."""

    cfg: Config
    algo: Algorithm
    checkpoint: Path


def read_checkpoint(run_dir: str | Path, name: str | None = None) -> tuple[Path, dict[str, Any]]:
    """``run_dir/checkpoints/<name>`` and its state, the best-eval one (``name`` ``"best"``), or
    the newest one that loads (``name`` None)."""
    directory = Path(run_dir) / "checkpoints"
    if name == "best":
        best = list_best(directory)
        check(
            bool(best),
            f"{run_dir} has no best checkpoint (checkpoints/best_*.pt, kept at each evaluation "
            "better than the ones before); evaluate the newest with checkpoint=null",
        )
        return best[-1], load_checkpoint(best[-1])
    if name is None:
        check(
            bool(list_checkpoints(directory)),
            f"{run_dir} has no checkpoint yet (nothing in {directory}); train first",
        )
        return load_latest(directory)
    path = directory / name if not Path(name).is_absolute() else Path(name)
    check(path.is_file(), f"checkpoint {path} does not exist")
    return path, load_checkpoint(path)


def load_run(
    run_dir: str | Path,
    checkpoint: str | None = None,
    *,
    device: str | torch.device = "cpu",
    num_envs: int = 1,
    allow_env_import: bool = False,
    network: nn.Module | None = None,
) -> LoadedRun:
    """Rebuild a run from its ``config.yaml`` and a checkpoint, as a :class:`LoadedRun`.

    The algorithm is built on ``num_envs`` fresh env copies and loads its checkpoint
    (``checkpoint``: a file name in ``run_dir/checkpoints``; None: the newest that loads).

    ``allow_env_import``: see :func:`load_config`. ``network``: the module a run was trained
    with in place of the default (a Python object, which ``config.yaml`` cannot hold; a
    ``algo.network`` spec is rebuilt from the config). The caller owns ``LoadedRun.algo`` and
    must ``close()`` it.
    """
    cfg = load_config(run_dir, allow_env_import=allow_env_import)
    path, state = read_checkpoint(run_dir, checkpoint)
    factory = partial(make_env, cfg.env, num_envs=num_envs, seed=cfg.seed)
    algo = make_algorithm(factory, cfg.algo, device=device, network=network)
    try:
        with fitting(path):
            algo.load_state_dict(state["algo"])
    except BaseException:
        algo.close()
        raise
    return LoadedRun(cfg, algo, path)


def hydra_overrides(run_dir: str | Path) -> list[str]:
    """The command-line overrides the run was started with (Hydra's record; none from Python)."""
    path = Path(run_dir) / ".hydra" / "overrides.yaml"
    return [str(o) for o in OmegaConf.load(path)] if path.is_file() else []


def original_command(run_dir: str | Path) -> str:
    """``python -m rlpipe <the overrides the run was started with>`` (from Hydra's record)."""
    return " ".join(["python -m rlpipe", *hydra_overrides(run_dir)])


def resume_state(
    cfg: Config, run_dir: str | Path, *, required: bool
) -> tuple[Path, dict[str, Any]] | None:
    """The checkpoint to continue ``run_dir`` from (path and state), or None to start at zero.

    ``cfg`` must be the run the dir holds (:func:`check_same_run`; e.g. a larger
    ``total_frames`` may differ), and so must the checkpoint's own record of its config.
    Damaged checkpoints are skipped with a warning; with ``required`` (``resume=<dir>``) a run
    dir without any checkpoint is an error. Nothing in the dir is changed.
    """
    run_dir = Path(run_dir)
    if required or (run_dir / CONFIG_FILE).exists():
        check_same_run(cfg, run_dir)
    if not list_checkpoints(run_dir / "checkpoints"):
        check(not required, f"{run_dir} has no checkpoint to resume from; start a new run")
        return None
    path, state = load_latest(run_dir / "checkpoints")
    if isinstance(state, dict) and isinstance(state.get("config"), dict):
        ours, theirs = fingerprint(cfg), fingerprint(state["config"])
        if ours != theirs:
            raise RunDirConflict(
                f"checkpoint {path} was written by another run: it differs in "
                f"{fingerprint_diff(ours, theirs)}; pick another run dir (hydra.run.dir=<dir>)"
            )
    return path, state
