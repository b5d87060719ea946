"""``train(cfg, run_dir)``: build env, algorithm, logger and runner from a :class:`Config`."""

from __future__ import annotations

import random
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from torchrl.record.loggers import CSVLogger, Logger

from rlpipe.algos import make_algorithm
from rlpipe.config import Config, LoggerConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.runner import Runner, RunResult

MAX_EVAL_ENVS = 32


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu; anything else must be a valid torch device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise RlpipeError(f"device must be auto, cpu, cuda or cuda:N; got {name!r}") from err
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RlpipeError(f"device={name} asked for, but no CUDA device is available; use auto")
    return device


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def make_logger(cfg: LoggerConfig, run_dir: str | Path) -> Logger | None:
    """The TorchRL logger chosen by ``cfg.backend``, writing into ``run_dir``."""
    if cfg.backend == "csv":
        return CSVLogger(exp_name="metrics", log_dir=str(run_dir))
    return None


def train(cfg: Config, run_dir: str | Path) -> RunResult:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.total_frames`` frames, writing into ``run_dir``.

    Everything is validated and built before anything is written, so a bad config leaves no
    checkpoint or metrics behind.
    """
    device = resolve_device(cfg.device)
    seed_everything(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    env = make_env(cfg.env, seed=cfg.seed)
    eval_env = make_env(
        cfg.env, num_envs=min(cfg.eval_episodes, MAX_EVAL_ENVS), seed=cfg.seed + 10_000
    )
    try:
        algo = make_algorithm(env, cfg.algo, device=device)  # from here on, algo owns env
    except BaseException:
        env.close()
        eval_env.close()
        raise
    try:
        runner = Runner(
            algo,
            eval_env,
            run_dir,
            total_frames=cfg.total_frames,
            eval_every=cfg.eval_every,
            eval_episodes=cfg.eval_episodes,
            checkpoint_every=cfg.checkpoint_every,
            keep_checkpoints=cfg.keep_checkpoints,
            logger=make_logger(cfg.logger, run_dir),
            progress=cfg.progress,
            extra_state={"config": asdict(cfg)},
        )
        return runner.run()
    finally:
        algo.close()
        eval_env.close()
