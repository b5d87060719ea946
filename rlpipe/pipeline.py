"""``train(cfg, run_dir)``: build env, algorithm, logger and runner from a :class:`Config`."""

from __future__ import annotations

from functools import partial
from pathlib import Path

from rlpipe.algos import make_algorithm
from rlpipe.callbacks import make_callbacks
from rlpipe.config import RUN_KEYS, Config
from rlpipe.envs import make_env
from rlpipe.episodes import eval_envs
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
from rlpipe.runtime import resolve_device, seed_everything, set_threads


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
    set_threads(cfg.threads, device)
    eval_env = make_env(cfg.env, num_envs=eval_envs(cfg.eval_episodes), seed=cfg.seed + 10_000)
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
            **{key: getattr(cfg, key) for key in RUN_KEYS},
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
