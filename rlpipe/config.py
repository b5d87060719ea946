"""Structured config schemas.

Every schema is a plain dataclass, so research code builds configs without Hydra
(``DQNConfig(lr=3e-4)``). The command line registers them in Hydra's ConfigStore: a typo'd key
or a value of the wrong type fails at start-up naming the key, and value checks in
``__post_init__`` run when the composed config is turned into these objects.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from rlpipe.errors import check


@dataclass
class EnvConfig:
    """Which gymnasium environment to build and how many copies to step as one batch."""

    id: str = "CartPole-v1"
    num_envs: int = 1
    max_episode_steps: int | None = None  # None: the environment's own time limit
    kwargs: dict[str, Any] = field(default_factory=dict)  # passed to gymnasium.make

    def __post_init__(self) -> None:
        check(self.num_envs >= 1, f"env.num_envs must be >= 1, got {self.num_envs}")
        check(
            self.max_episode_steps is None or self.max_episode_steps >= 1,
            f"env.max_episode_steps must be >= 1 or null, got {self.max_episode_steps}",
        )


LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "mlflow", "none")
WANDB_MODES = ("online", "offline", "disabled")


@dataclass
class LoggerConfig:
    """Where metrics go: ``csv`` (TorchRL's CSVLogger in the run directory), ``tensorboard``,
    ``wandb`` or ``mlflow`` (each on top of the CSV files), or ``none``."""

    backend: str = "csv"
    project: str | None = None  # W&B project / MLflow experiment (default "rlpipe")
    mode: str | None = None  # W&B mode; null: offline unless a project is set
    tracking_uri: str | None = None  # MLflow; null: sqlite:///<run dir>/mlflow.db

    def __post_init__(self) -> None:
        check(
            self.backend in LOGGER_BACKENDS,
            f"logger.backend must be one of {', '.join(LOGGER_BACKENDS)}; got {self.backend!r}",
        )
        check(
            self.mode is None or self.mode in WANDB_MODES,
            f"logger.mode must be one of {', '.join(WANDB_MODES)} or null; got {self.mode!r}",
        )


@dataclass
class Config:
    """A whole training run: environment, algorithm, logger and the runner's knobs."""

    env: EnvConfig = field(default_factory=EnvConfig)
    algo: Any = MISSING  # an algorithm config (e.g. DQNConfig), chosen by the ``algo`` group
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    seed: int = 0
    device: str = "auto"  # auto: cuda when available, else cpu
    total_frames: int | None = None  # None: the algorithm's own budget (epochs, iterations)
    eval_every: int = 10_000  # frames between greedy evaluations (0: only at the end)
    eval_episodes: int = 10
    checkpoint_every: int = 25_000  # frames between checkpoints (0: only at the end)
    keep_checkpoints: int = 3
    progress: bool = True
    video: Any = False  # false | true (every evaluation) | N (every N frames); always at the end
    threads: int = 0  # torch intra-op threads; 0: torch's default (one per core)
    resume: str | None = None  # a run dir to continue from its last good checkpoint

    def __post_init__(self) -> None:
        check(
            self.total_frames is None or self.total_frames >= 1,
            f"total_frames must be >= 1 (or null: the algorithm's own budget), got "
            f"{self.total_frames}",
        )
        check(self.eval_every >= 0, f"eval_every must be >= 0, got {self.eval_every}")
        check(self.eval_episodes >= 1, f"eval_episodes must be >= 1, got {self.eval_episodes}")
        check(
            self.checkpoint_every >= 0,
            f"checkpoint_every must be >= 0, got {self.checkpoint_every}",
        )
        check(self.threads >= 0, f"threads must be >= 0, got {self.threads}")
        check(
            self.keep_checkpoints >= 1,
            f"keep_checkpoints must be >= 1, got {self.keep_checkpoints}",
        )
        check(
            isinstance(self.video, bool) or (isinstance(self.video, int) and self.video >= 0),
            f"video must be true, false or a frame cadence N >= 1, got {self.video!r}",
        )
