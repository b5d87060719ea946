"""Metric loggers: TorchRL's CSV, TensorBoard, W&B and MLflow loggers behind ``logger=...``.

The CSV files under ``<run dir>/metrics/scalars/`` are written for every backend but ``none``:
``curve.png`` and ``python -m rlpipe.plot`` read them. The other backends get the same metrics
(and evaluation videos, where they take video) on top.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from torch import Tensor
from torchrl.record.loggers import (
    CSVLogger,
    Logger,
    MLFlowLogger,
    TensorboardLogger,
    WandbLogger,
)

from rlpipe.config import LoggerConfig
from rlpipe.errors import RlpipeError

METRICS_DIR = "metrics"  # CSVLogger's experiment name: <run dir>/metrics/scalars/<name>.csv

# pip extra -> modules it provides (checked before anything is built)
EXTRAS: dict[str, tuple[str, ...]] = {
    "tensorboard": ("tensorboard", "moviepy.editor"),
    "wandb": ("wandb", "moviepy"),
    "mlflow": ("mlflow", "sqlalchemy", "alembic"),
    "video": ("imageio", "imageio_ffmpeg"),
}


def require_extra(extra: str, what: str) -> None:
    """Raise a one-line :class:`RlpipeError` with the install command if ``extra`` is missing."""
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ImportError as err:
            raise RlpipeError(
                f"{what} needs the {extra!r} extra ({module} is missing: {err}); "
                f'install it with: pip install "rlpipe[{extra}]"'
            ) from err


class TeeLogger(Logger):
    """Forwards every call to several TorchRL loggers (the CSV files plus one backend)."""

    def __init__(self, loggers: Sequence[Logger]) -> None:
        self.loggers = list(loggers)
        super().__init__(exp_name=loggers[0].exp_name, log_dir=loggers[0].log_dir)

    def _create_experiment(self) -> None:
        return None

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        for logger in self.loggers:
            logger.log_scalar(name, value, step=step)

    def log_video(self, name: str, video: Tensor, step: int | None = None, **kwargs: Any) -> None:
        for logger in self.loggers:
            if takes_video(logger):
                logger.log_video(name, video, step=step, **kwargs)

    def log_hparams(self, cfg: dict) -> None:
        for logger in self.loggers:
            logger.log_hparams(cfg)

    def log_histogram(self, name: str, data: Sequence, **kwargs: Any) -> None:
        raise NotImplementedError("rlpipe logs no histograms")

    def shutdown(self, timeout: float | None = None) -> None:
        for logger in self.loggers:
            logger.shutdown(timeout)
        super().shutdown(timeout)

    def __repr__(self) -> str:
        return f"TeeLogger({self.loggers!r})"


def takes_video(logger: Logger | None) -> bool:
    """Whether ``logger`` (or one it forwards to) can show videos: TensorBoard and W&B can."""
    if isinstance(logger, TeeLogger):
        return any(takes_video(inner) for inner in logger.loggers)
    return isinstance(logger, (TensorboardLogger, WandbLogger))


def make_logger(cfg: LoggerConfig, run_dir: str | Path) -> Logger | None:
    """The TorchRL logger chosen by ``cfg.backend``, writing into ``run_dir``.

    ``csv``: ``CSVLogger``; ``none``: no logger; ``tensorboard`` / ``wandb`` / ``mlflow``: the
    CSV files plus that backend (a :class:`TeeLogger`). A backend whose pip extra is missing
    raises :class:`RlpipeError` naming the install command.
    """
    if cfg.backend == "none":
        return None
    if cfg.backend != "csv":
        require_extra(cfg.backend, f"logger={cfg.backend}")
    run_dir = Path(run_dir).absolute()
    csv = CSVLogger(exp_name=METRICS_DIR, log_dir=str(run_dir))
    if cfg.backend == "csv":
        return csv
    return TeeLogger([csv, _backend(cfg, run_dir)])


def _backend(cfg: LoggerConfig, run_dir: Path) -> Logger:
    name = run_dir.name
    if cfg.backend == "tensorboard":
        return TensorboardLogger(exp_name=name, log_dir=str(run_dir / "tensorboard"))
    if cfg.backend == "wandb":
        # offline unless a project or a mode says otherwise
        mode = cfg.mode or ("online" if cfg.project else "offline")
        return WandbLogger(
            exp_name=name,
            save_dir=str(run_dir),
            project=cfg.project or "rlpipe",
            mode=mode,
            log_env_packages=False,
        )
    uri = cfg.tracking_uri or f"sqlite:///{run_dir / 'mlflow.db'}"
    artifacts = None if cfg.tracking_uri else (run_dir / "mlartifacts").as_uri()
    return MLFlowLogger(
        exp_name=cfg.project or "rlpipe", tracking_uri=uri, artifact_location=artifacts
    )
