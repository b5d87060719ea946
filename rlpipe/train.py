"""``train(cfg, run_dir)``: build env, algorithm, logger and runner from a :class:`Config`."""

from __future__ import annotations

import random
from functools import partial
from pathlib import Path

import numpy as np
import torch

from rlpipe.algos import make_algorithm
from rlpipe.config import Config
from rlpipe.curves import make_callbacks
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.loggers import make_logger
from rlpipe.rundir import (
    CONFIG_FILE,
    config_to_dict,
    resume_state,
    save_config,
    truncate_metrics,
)
from rlpipe.runner import Runner, RunResult, check_budget

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


def train(cfg: Config, run_dir: str | Path) -> RunResult:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.total_frames`` frames, writing into ``run_dir``.

    Null run keys take the algorithm's values (:meth:`Config.resolved`); the resolved config is
    what ``config.yaml`` records. Everything is validated and built before anything is written,
    so a bad config leaves no checkpoint or metrics behind.
    """
    cfg = cfg.resolved()
    device = resolve_device(cfg.device)
    run_dir = Path(cfg.resume or run_dir)
    state = None
    if cfg.resume or (run_dir / CONFIG_FILE).exists():  # resume=<dir>, or a rerun in that dir
        state = resume_state(cfg, run_dir, required=bool(cfg.resume))
    frames = state["frames"] if state else 0
    seed_everything(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    eval_env = make_env(
        cfg.env, num_envs=min(cfg.eval_episodes, MAX_EVAL_ENVS), seed=cfg.seed + 10_000
    )
    try:  # a resumed run meets fresh episodes: the seed moves with the frames
        algo = make_algorithm(
            partial(make_env, cfg.env, seed=cfg.seed + frames), cfg.algo, device=device
        )
    except BaseException:
        eval_env.close()
        raise
    try:
        check_budget(algo, cfg.total_frames)
        try:
            save_config(cfg, run_dir)
        except OSError as err:
            raise RlpipeError(
                f"cannot write the run directory {run_dir}: {err.strerror or err}; "
                "pick a writable one with hydra.run.dir=<dir>"
            ) from err
        truncate_metrics(run_dir, frames)
        runner = Runner(
            algo,
            eval_env,
            run_dir,
            total_frames=cfg.total_frames,
            eval_every=cfg.eval_every,
            eval_episodes=cfg.eval_episodes,
            checkpoint_every=cfg.checkpoint_every,
            keep_checkpoints=cfg.keep_checkpoints,
            callbacks=make_callbacks(cfg),  # before the logger: a bad video setting writes nothing
            logger=make_logger(cfg.logger, run_dir),
            progress=cfg.progress,
            extra_state={"config": config_to_dict(cfg)},
        )
        if state is not None:
            runner.restore(state)
        return runner.run()
    finally:
        algo.close()
        eval_env.close()
