"""``train(cfg, run_dir)``: build env, algorithm, logger and runner from a :class:`Config`."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import torch
from torch import nn
from tqdm.auto import tqdm

from rlpipe.algos import make_algorithm
from rlpipe.callbacks import make_callbacks
from rlpipe.checkpoint import fitting, prune_checkpoints
from rlpipe.config import RUN_KEYS, Config
from rlpipe.envs import make_env
from rlpipe.episodes import eval_envs
from rlpipe.loggers import make_logger, run_card
from rlpipe.metrics import truncate_metrics
from rlpipe.models import object_record
from rlpipe.rundir import (
    CONFIG_FILE,
    check_same_run,
    hydra_overrides,
    lock_run_dir,
    resume_state,
    save_config,
    unwritable,
)
from rlpipe.runner import Runner, RunResult, check_budget
from rlpipe.runtime import resolve_device, seed_everything, set_threads

SEED_RANGE = 2**32  # environment seeds derived from cfg.seed wrap around at numpy's limit


def train(
    cfg: Config,
    run_dir: str | Path,
    *,
    network: nn.Module | None = None,
    on_start: Callable[[Path], None] | None = None,
) -> RunResult:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.total_frames`` frames, writing into ``run_dir``.

    Null run keys take the algorithm's values (:meth:`Config.resolved`); the resolved config is
    what ``config.yaml`` records. A run dir holding a run continues it from its newest good
    checkpoint (``resume=<dir>`` requires one); it must be the same run (same
    :func:`~rlpipe.rundir.fingerprint`) and no other process may be writing it. Everything is
    checked and built, and the checkpoint applied, before anything in the dir is written, so a
    bad config or a mismatched checkpoint changes nothing. ``on_start(run_dir)`` runs then (the
    command line records Hydra's files with it).

    ``network``: your module in place of the algorithm's default network (a Python object:
    ``config.yaml`` cannot hold it, so pass it again to resume or to :func:`~rlpipe.load_run`;
    ``cfg.algo.network``, a ``_target_`` spec, needs neither).
    """
    cfg = cfg.resolved()
    if network is not None:  # config.yaml records its class, and asks for it on loading
        cfg = replace(cfg, algo=replace(cfg.algo, network=object_record(network)))
    device = resolve_device(cfg.device)
    run_dir = Path(cfg.resume or run_dir)
    if cfg.resume or (run_dir / CONFIG_FILE).exists():
        check_same_run(cfg, run_dir)  # before the lock file is written
    with lock_run_dir(run_dir):
        found = resume_state(cfg, run_dir, required=bool(cfg.resume))
        return _train_locked(cfg, run_dir, device, found, network, on_start)


def _train_locked(
    cfg: Config,
    run_dir: Path,
    device: torch.device,
    found: tuple[Path, dict[str, Any]] | None,
    network: nn.Module | None,
    on_start: Callable[[Path], None] | None,
) -> RunResult:
    frames = found[1]["frames"] if found else 0
    seed_everything(cfg.seed)
    set_threads(cfg.threads, device)
    eval_env = make_env(
        cfg.env, num_envs=eval_envs(cfg.eval_episodes), seed=(cfg.seed + 10_000) % SEED_RANGE
    )
    try:  # a resumed run meets fresh episodes: the seed moves with the frames
        algo = make_algorithm(
            partial(make_env, cfg.env, seed=(cfg.seed + frames) % SEED_RANGE),
            cfg.algo,
            device=device,
            network=network,
        )
    except BaseException:
        eval_env.close()
        raise
    try:
        check_budget(algo, cfg.total_frames)
        runner = Runner(
            algo,
            eval_env,
            run_dir,
            **{key: getattr(cfg, key) for key in RUN_KEYS},
            keep_checkpoints=cfg.keep_checkpoints,
            log_every=cfg.log_every,
            callbacks=make_callbacks(cfg),  # before the logger: a bad video setting writes nothing
            progress=cfg.progress,
            config=cfg,  # config.yaml, and in every checkpoint
        )
        if found is not None:
            with fitting(found[0]):
                runner.restore(found[1])
            if not runner.finished:  # a finished run says so itself
                tqdm.write(f"rlpipe: resuming {run_dir} from {found[0].name} at {frames:,} frames")
        # checked: from here on the run dir is written
        try:
            save_config(cfg, run_dir)
            truncate_metrics(run_dir, frames)
            prune_checkpoints(run_dir / "checkpoints", cfg.keep_checkpoints)
        except OSError as err:
            raise unwritable(run_dir, err) from err
        if on_start is not None:
            on_start(run_dir)
        card = run_card(cfg, hydra_overrides(run_dir))  # name, tags, hyper-parameters
        runner.logger = make_logger(cfg.logger, run_dir, card)
        return runner.run()
    finally:
        algo.close()
        eval_env.close()
