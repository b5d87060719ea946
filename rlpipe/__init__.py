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
from rlpipe.config import Config, EnvConfig, LoggerConfig
from rlpipe.curves import find_runs, group_runs, plot_groups, plot_run
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.evaluation import EvalResult, evaluate
from rlpipe.evolution import ARSSearch, Normalizer
from rlpipe.rundir import LoadedRun, load_run
from rlpipe.runner import Runner, RunResult
from rlpipe.train import make_logger, seed_everything, train

__version__ = "0.1.0"

__all__ = [
    "ALGORITHMS",
    "ARS",
    "ARSConfig",
    "ARSSearch",
    "DQN",
    "Algorithm",
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
