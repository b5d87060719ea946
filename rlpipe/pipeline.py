"""Runs from configs: ``train(cfg, run_dir)`` builds env, algorithm, logger and runner from a
:class:`Config` and trains; ``load_run(run_dir)`` rebuilds a trained run's algorithm."""

from __future__ import annotations

from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import torch
from torch import nn

from rlpipe.algos import make_algorithm
from rlpipe.algos.base import Algorithm
from rlpipe.callbacks import make_callbacks
from rlpipe.config import RUN_KEYS, Config
from rlpipe.console import say
from rlpipe.envs import make_env
from rlpipe.envs.backends import resolve_backend
from rlpipe.episodes import EVALUATION, episodes_seed, eval_envs
from rlpipe.lineage import continued, extension_line, init_parts, read_parent, start_line
from rlpipe.loggers import make_logger, run_card
from rlpipe.models import object_record
from rlpipe.outcomes import RunResult
from rlpipe.rundir import RunDir
from rlpipe.runner import Runner
from rlpipe.runtime import env_threads, resolve_device, seed_everything


def train(
    cfg: Config,
    run_dir: str | Path,
    *,
    network: nn.Module | None = None,
    on_start: Callable[[RunDir], None] | None = None,
) -> RunResult:
    """Train ``cfg.algo`` on ``cfg.env`` for ``cfg.total_frames`` frames, writing into ``run_dir``.

    Null run keys take the algorithm's values (:meth:`Config.resolved`); the resolved config is
    what ``config.yaml`` records. A run dir holding a run continues it from its newest good
    checkpoint (``resume=<dir>`` requires one); it must be the same run (same
    :func:`~rlpipe.config.fingerprint`) and no other process may be writing it. Everything is
    checked and built, and the checkpoint applied, before anything in the dir is written
    (:meth:`RunDir.open`, then :meth:`RunDir.session`), so a bad config or a mismatched
    checkpoint changes nothing. ``on_start(run_dir)`` runs then (the command line records
    Hydra's files with it). ``cfg.init_from``: a new run that starts from that run's checkpoint
    (:mod:`rlpipe.lineage`); a run continued keeps its parent and its schedules' frames.

    ``network``: your module in place of the algorithm's default network (a Python object:
    ``config.yaml`` cannot hold it, so pass it again to resume or to :func:`load_run`;
    ``cfg.algo.network``, a ``_target_`` spec, needs neither).
    """
    cfg = cfg.resolved()
    if network is not None:  # config.yaml records its class, and asks for it on loading
        cfg = replace(cfg, algo=replace(cfg.algo, network=object_record(network)))
    device = resolve_device(cfg.device)
    run = RunDir(cfg.resume or run_dir)
    recorded = run.read_config(allow_code=True) if run.is_run() else None
    # auto becomes the backend used (config.yaml records it); a run continued keeps its own
    env_cfg, backend_line = resolve_backend(
        cfg.env, recorded and recorded.env.backend, cfg.stepped_copies()
    )
    cfg = replace(cfg, env=env_cfg)
    if recorded is not None:  # and how it began: its parent, its schedules' frames
        cfg = continued(cfg, recorded, run.path)
    start = run.open(cfg, required=bool(cfg.resume))
    parent = read_parent(cfg) if cfg.init_from and start is None else None
    if parent is not None:
        cfg = replace(cfg, init_from=parent.spec)  # config.yaml pins its checkpoint
    frames = 0 if start is None else start.frames
    seed_everything(cfg.seed)
    envs = partial(make_env, cfg.env, threads=env_threads(cfg.threads))
    with ExitStack() as stack:  # the runner seeds every evaluation from cfg.seed and its frames
        first = episodes_seed(cfg.seed, EVALUATION)
        eval_env = envs(num_envs=eval_envs(cfg.eval_episodes), seed=first)
        stack.callback(eval_env.close)
        algo = make_algorithm(  # a resumed run restarts its episodes as the checkpoint says
            partial(envs, seed=cfg.seed),
            cfg.algo,
            device=device,
            network=network,
            threads=cfg.threads,  # torch's, process-wide (the Runner applies the same)
            compile=cfg.compile,
        )
        stack.callback(algo.close)
        runner = Runner(
            algo,
            eval_env,
            run,
            **{key: getattr(cfg, key) for key in RUN_KEYS},
            keep_checkpoints=cfg.keep_checkpoints,
            log_every=cfg.log_every,
            callbacks=make_callbacks(cfg),  # before the logger: a bad video setting writes nothing
            progress=cfg.progress,
            config=cfg,  # config.yaml, and in every checkpoint
            eval_seed=cfg.seed,
        )
        if start is not None:
            with start.applying():
                runner.restore(start.state)
        elif parent is not None:
            with parent.applying(cfg):
                algo.start_from(parent.checkpoint.state["algo"], init_parts(cfg), parent.cfg.algo)
        with run.session(cfg, frames, cfg.keep_checkpoints):  # checked: from here on it is written
            say(f"rlpipe: {backend_line}")
            if parent is not None:
                say(start_line(parent, cfg))
            if start is not None and not runner.finished:  # a finished run says so itself
                say(f"rlpipe: resuming {run.path} from {start.path.name} at {frames:,} frames")
                extended = extension_line(cfg)
                if extended is not None:
                    say(extended)
            if on_start is not None:
                on_start(run)
            runner.logger = make_logger(cfg.logger, run.path, run_card(cfg, run.overrides()))
            return runner.run()


@dataclass
class LoadedRun:
    """A run rebuilt from its directory: config, algorithm (weights loaded), checkpoint used."""

    cfg: Config
    algo: Algorithm
    checkpoint: Path


def load_run(
    run_dir: str | Path,
    checkpoint: str | None = None,
    *,
    device: str | torch.device = "cpu",
    num_envs: int = 1,
    allow_env_import: bool = False,
    network: nn.Module | None = None,
    backend: str | None = None,
) -> LoadedRun:
    """Rebuild a run from its ``config.yaml`` and a checkpoint, as a :class:`LoadedRun`.

    The algorithm is built on ``num_envs`` fresh env copies and loads its checkpoint
    (``checkpoint``: a file name in ``run_dir/checkpoints``, ``"best"``: the best evaluation's;
    None: the newest that loads).

    ``allow_env_import``: see :meth:`RunDir.read_config`. ``network``: the module a run was
    trained with in place of the default (a Python object, which ``config.yaml`` cannot hold; a
    ``algo.network`` spec is rebuilt from the config). The caller owns ``LoadedRun.algo`` and
    must ``close()`` it. ``backend``: the env backend to rebuild it on (``env.backend``'s
    choices; None: the one the run recorded), which ``LoadedRun.cfg`` then names. The run's
    ``threads`` set torch's intra-op threads, process-wide, as ``train`` does.
    """
    run = RunDir(run_dir)
    cfg = run.read_config(allow_code=allow_env_import)
    if backend is not None:
        cfg = replace(cfg, env=replace(cfg.env, backend=backend))
    found = run.read_checkpoint(checkpoint)
    factory = partial(
        make_env, cfg.env, num_envs=num_envs, seed=cfg.seed, threads=env_threads(cfg.threads)
    )
    algo = make_algorithm(factory, cfg.algo, device=device, network=network, threads=cfg.threads)
    try:
        with found.applying():
            algo.load_state_dict(found.state["algo"])
    except BaseException:
        algo.close()
        raise
    return LoadedRun(cfg, algo, found.path)
