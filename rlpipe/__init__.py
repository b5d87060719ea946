"""rlpipe: reinforcement-learning pipelines from TorchRL parts, composed with Hydra."""

from rlpipe.algos import (
    ALGORITHMS,
    ARS,
    DQN,
    MBRL,
    Algorithm,
    ARSConfig,
    DQNConfig,
    MBRLConfig,
    Reinforce,
    ReinforceConfig,
    make_algorithm,
)
from rlpipe.algos.ars import ARSSearch
from rlpipe.callbacks import Callback
from rlpipe.config import Config, EnvConfig, LoggerConfig
from rlpipe.envs import make_env
from rlpipe.episodes import EvalResult, evaluate
from rlpipe.errors import RlpipeError
from rlpipe.figures import plot_groups, plot_run
from rlpipe.loggers import make_logger
from rlpipe.metrics import find_runs, group_runs
from rlpipe.normalizer import Normalizer
from rlpipe.pipeline import train
from rlpipe.rundir import LoadedRun, load_run
from rlpipe.runner import Runner, RunResult
from rlpipe.runtime import seed_everything

__version__ = "0.1.0"

__all__ = [
    "ALGORITHMS",
    "ARS",
    "ARSConfig",
    "ARSSearch",
    "DQN",
    "Algorithm",
    "Callback",
    "Config",
    "DQNConfig",
    "EnvConfig",
    "EvalResult",
    "LoadedRun",
    "LoggerConfig",
    "MBRL",
    "MBRLConfig",
    "Normalizer",
    "Reinforce",
    "ReinforceConfig",
    "RlpipeError",
    "RunResult",
    "Runner",
    "evaluate",
    "find_runs",
    "group_runs",
    "load_run",
    "make_algorithm",
    "make_env",
    "make_logger",
    "plot_groups",
    "plot_run",
    "seed_everything",
    "train",
]
