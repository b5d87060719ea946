"""Metric loggers: rlpipe's CSV files, TorchRL's TensorBoard, W&B and MLflow loggers behind
``logger=...``.

The CSV files under ``<run dir>/metrics/scalars/`` are written for every backend but ``none``
(:class:`CsvLogger`, in TorchRL ``CSVLogger``'s layout and format): ``curve.png`` and
``python -m rlpipe.plot`` read them. The other backends get the same metrics (and evaluation
videos, where they take video) on top.
"""

from __future__ import annotations

import importlib
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from io import FileIO
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf
from torch import Tensor
from torchrl.record.loggers import (
    Logger,
    MLFlowLogger,
    TensorboardLogger,
    WandbLogger,
)

from rlpipe.config import NOT_FINGERPRINTED, Config, LoggerConfig, flatten
from rlpipe.errors import RlpipeError
from rlpipe.files import NotOwnFile, open_append, reached_directly
from rlpipe.rundir import RunDir

MAX_OPEN_FILES = 64  # CsvLogger keeps at most this many metric files open (runs log < 30)

# pip extra -> modules it provides (checked before anything is built)
EXTRAS: dict[str, tuple[str, ...]] = {
    "tensorboard": ("tensorboard", "moviepy.editor"),
    "wandb": ("wandb", "moviepy"),
    "mlflow": ("mlflow", "sqlalchemy", "alembic"),
    "video": ("imageio", "imageio_ffmpeg"),
    "onnx": ("onnx", "onnxscript", "onnxruntime"),  # python -m rlpipe.export format=onnx
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


class CsvLogger(Logger):
    """One CSV file per metric, ``<log_dir>/<exp_name>/scalars/<name>.csv``, one ``step,value``
    line per :meth:`log_scalar`: TorchRL ``CSVLogger``'s files and format, without its costs.

    Each row is appended with one unbuffered ``write`` as it is logged and nothing is kept in
    memory (TorchRL's logger keeps every row). Files are opened on first use, at most
    :data:`MAX_OPEN_FILES` at a time (least recently used closed first). A write error
    (``ENOSPC``, ``EIO``) propagates from :meth:`log_scalar` and closes that file: no buffered
    data is left to fail again when the logger is garbage collected. Videos are not CSV data
    (:func:`takes_video` is false); hyper-parameters are in the run dir's ``config.yaml``.
    """

    def __init__(self, exp_name: str = RunDir.METRICS, log_dir: str | Path = ".") -> None:
        self._files: dict[str, FileIO] = {}  # metric name -> open file, least recent first
        self._counts: dict[str, int] = {}  # rows logged without a step, per metric
        super().__init__(exp_name=exp_name, log_dir=str(log_dir))

    def _create_experiment(self) -> None:
        return None

    @property
    def scalars_dir(self) -> Path:
        """The directory holding the CSV files."""
        return Path(self.log_dir) / self.exp_name / "scalars"

    def path(self, name: str) -> Path:
        """The CSV file of metric ``name``: ``eval/return_mean`` -> ``.../eval/return_mean.csv``."""
        return self.scalars_dir / f"{name}.csv"

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        """Append ``step,value`` to ``name``'s file (step: rows so far when ``None``)."""
        if step is None:
            step = self._counts.get(name, 0)
            self._counts[name] = step + 1
        line = f"{int(step)},{float(value)}\n".encode()
        file = self._file(name)
        try:
            view = memoryview(line)
            while view:  # a regular file takes it in one write; a short one is continued
                view = view[file.write(view) :]
        except OSError:
            self._close(name)
            raise

    def _file(self, name: str) -> FileIO:
        file = self._files.pop(name, None)
        if file is None:
            if len(self._files) >= MAX_OPEN_FILES:
                self._close(next(iter(self._files)))
            path = self.path(name)
            path.parent.mkdir(parents=True, exist_ok=True)
            if not reached_directly(self.log_dir, path):
                raise NotOwnFile(f"{path} is reached through a symbolic link: not written")
            file = open_append(path, buffering=0)  # itself: not a link, FIFO or hard link
        self._files[name] = file  # now the most recently used
        return file

    def _close(self, name: str) -> None:
        file = self._files.pop(name, None)
        if file is not None:
            try:
                file.close()
            except OSError:  # nothing is buffered; a close error has no data to lose
                pass

    def flush(self, timeout: float | None = None) -> None:
        """Nothing to do: every row is written when it is logged."""

    def log_video(self, name: str, video: Tensor, step: int | None = None, **kwargs: Any) -> None:
        raise NotImplementedError(
            "CSV files hold no videos (takes_video() is false; rlpipe writes mp4s itself)"
        )

    def log_hparams(self, cfg: dict) -> None:
        """Nothing to write: the run dir's ``config.yaml`` holds the whole config."""

    def log_histogram(self, name: str, data: Sequence, **kwargs: Any) -> None:
        raise NotImplementedError("rlpipe logs no histograms")

    def shutdown(self, timeout: float | None = None) -> None:
        """Close every file (logging again reopens them)."""
        for name in list(self._files):
            self._close(name)
        super().shutdown(timeout)

    def __del__(self) -> None:
        for name in list(getattr(self, "_files", ())):
            self._close(name)

    def __repr__(self) -> str:
        return f"CsvLogger({str(self.scalars_dir)!r})"


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


@dataclass
class RunCard:
    """What a tracker is told about a run: a name, tags and the hyper-parameters (flat)."""

    name: str
    tags: dict[str, str]
    params: dict[str, Any]  # the resolved config, dotted keys -> scalars


def run_card(cfg: Config, overrides: Sequence[str] = ()) -> RunCard:
    """The card of run ``cfg``: named ``<algo> <env id> seed=<s>`` plus the command line's other
    overrides that decide the results (not budgets, cadences, logging), tagged with algo, env
    and seed, its resolved config as the hyper-parameters."""

    def told(override: str) -> bool:  # not in the name already, and deciding the results
        key = override.lstrip("+~").split("=")[0]
        named = key in ("seed", "algo", "env") or key.startswith("hydra")
        return not named and key.split(".")[0] not in NOT_FINGERPRINTED

    extra = ["untuned" if o == "~tuned" else o for o in overrides if told(o)]
    name = f"{cfg.algo.name} {cfg.env.id} seed={cfg.seed}"
    name += f" [{' '.join(extra)}]" if extra else ""
    flat = flatten(OmegaConf.to_container(OmegaConf.structured(cfg)))
    params = {k: v if isinstance(v, int | float | str | bool) else str(v) for k, v in flat.items()}
    tags = {"algo": cfg.algo.name, "env": cfg.env.id, "seed": str(cfg.seed)}
    return RunCard(name[:250], tags, params)


def make_logger(
    cfg: LoggerConfig, run_dir: str | Path, card: RunCard | None = None
) -> Logger | None:
    """The TorchRL logger chosen by ``cfg.backend``, writing into ``run_dir``.

    ``csv``: :class:`CsvLogger`; ``none``: no logger; ``tensorboard`` / ``wandb`` / ``mlflow``: the
    CSV files plus that backend (a :class:`TeeLogger`), which gets the ``card``'s name, tags and
    hyper-parameters (TensorBoard's hparams, W&B's config, MLflow's params). A backend whose pip
    extra is missing raises :class:`RlpipeError` naming the install command.
    """
    if cfg.backend == "none":
        return None
    if cfg.backend == "mlflow":  # before its import: its INFO lines go to the run's log file
        os.environ.setdefault("MLFLOW_CONFIGURE_LOGGING", "false")
    if cfg.backend != "csv":
        require_extra(cfg.backend, f"logger={cfg.backend}")
    run_dir = Path(run_dir).absolute()
    csv = CsvLogger(exp_name=RunDir.METRICS, log_dir=run_dir)
    if cfg.backend == "csv":
        return csv
    card = card or RunCard(run_dir.name, {}, {})
    return TeeLogger([csv, _backend(cfg, run_dir, card)])


def _backend(cfg: LoggerConfig, run_dir: Path, card: RunCard) -> Logger:
    if cfg.backend == "tensorboard":
        folder = re.sub(r"[^A-Za-z0-9._=,-]+", "_", card.name)
        logger = TensorboardLogger(exp_name=folder, log_dir=str(run_dir / "tensorboard"))
        if card.params:
            logger.log_hparams(card.params)
        return logger
    if cfg.backend == "wandb":
        # offline unless a project or a mode says otherwise
        mode = cfg.mode or ("online" if cfg.project else "offline")
        return WandbLogger(
            exp_name=card.name,
            save_dir=str(run_dir),
            project=cfg.project or "rlpipe",
            mode=mode,
            log_env_packages=False,
            config=card.params,
            tags=[f"{key}:{value}" for key, value in card.tags.items()],
        )
    import mlflow

    uri = cfg.tracking_uri or f"sqlite:///{run_dir / 'mlflow.db'}"
    artifacts = None if cfg.tracking_uri else (run_dir / "mlartifacts").as_uri()
    logger = MLFlowLogger(
        exp_name=cfg.project or "rlpipe", tracking_uri=uri, artifact_location=artifacts
    )
    run_id = logger.experiment.info.run_id
    client = mlflow.MlflowClient(uri)
    client.set_tag(run_id, "mlflow.runName", card.name)
    for key, value in card.tags.items():
        client.set_tag(run_id, key, value)
    for key, value in card.params.items():
        client.log_param(run_id, key, str(value)[:6000])
    return logger


def log_artifacts(logger: Logger | None, paths: Sequence[Path]) -> None:
    """Give the tracker behind ``logger`` files of the run (``curve.png``, videos): W&B and
    MLflow keep them as artifacts, TensorBoard shows PNGs as images."""
    backends = logger.loggers if isinstance(logger, TeeLogger) else [logger]
    for backend in backends:
        for path in paths:
            if isinstance(backend, WandbLogger):
                backend.experiment.save(str(path), base_path=str(path.parent), policy="now")
            elif isinstance(backend, MLFlowLogger):
                import mlflow

                mlflow.MlflowClient().log_artifact(backend.experiment.info.run_id, str(path))
            elif isinstance(backend, TensorboardLogger) and path.suffix == ".png":
                import matplotlib.image as mpimg

                image = mpimg.imread(path)[..., :3]  # H W C floats in [0, 1]
                backend.experiment.add_image(path.stem, image, dataformats="HWC")
