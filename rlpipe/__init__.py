"""rlpipe: reinforcement-learning pipelines from TorchRL parts, composed with Hydra.

``rlpipe.train(rlpipe.Config(), run_dir)`` is ``python -m rlpipe`` without Hydra; docs/api.md
has the examples. The public names (``rlpipe.__all__``):

Configs (dataclasses; bad values raise RlpipeError on construction):
    Config           a whole run: env, algo, logger and the runner's keys (seed, frames, ...)
    EnvConfig        gymnasium id, num_envs copies stepped as one batch, time limit, kwargs
    LoggerConfig     where metrics go: csv, tensorboard, wandb, mlflow or none
    DQNConfig        DQN's hyper-parameters, run length and cadence
    ReinforceConfig  REINFORCE's hyper-parameters, run length and cadence
    ARSConfig        ARS's hyper-parameters, run length and cadence
    MBRLConfig       model-based RL's hyper-parameters, run length and cadence
    PPOConfig        PPO's hyper-parameters, run length and cadence
    SACConfig        SAC's hyper-parameters, run length and cadence

Building and running:
    train            the whole pipeline from a Config into a run dir; returns a RunResult
    compose_run      the Config python -m rlpipe <overrides> would run (presets from Python)
    make_env         num_envs copies of a gymnasium env as one batched TorchRL env
    make_algorithm   the algorithm named by cfg.name, built on envs from an env factory
    ALGORITHMS       the registry (a dict): name -> (config class, algorithm class)
    DQN              deep Q-learning (discrete actions)
    Reinforce        REINFORCE, Monte-Carlo policy gradient (discrete or continuous)
    ARS              augmented random search, the runner's algorithm around an ARSSearch
    MBRL             model-based RL: a learned model and a planner
    PPO              proximal policy optimisation, clipped, with GAE
    SAC              soft actor-critic: twin Q, automatic entropy tuning
    Algorithm        the protocol the Runner drives (isinstance checks it)
    Runner           the one training loop: evaluations, metrics, checkpoints, summary.json
    RunResult        what a run reports: eval mean and std, frames, wall time, run dir
    Callback         hooks on the Runner: on_eval after each evaluation, on_end at the end
    make_logger      the TorchRL logger a LoggerConfig names
    seed_everything  seed Python's, NumPy's and torch's global generators
    evaluate         exactly n greedy episodes of a policy on an env; an EvalResult
    EvalResult       returns and lengths of evaluated episodes, their mean and std
    RlpipeError      a problem the user can fix (a ValueError); the CLIs print one line

Reading runs back:
    load_run         a run rebuilt from its config.yaml and a checkpoint; a LoadedRun
    LoadedRun        a loaded run's cfg, algo (weights loaded) and checkpoint file
    find_runs        run dirs in or below some dirs (a sweep dir) that logged a metric
    group_runs       runs grouped when they differ only by seed
    plot_groups      learning curves of groups: mean or IQM over seeds, 95% bootstrap band
    plot_run         a run's curve.png

ARS pieces, usable on any policy:
    ARSSearch        augmented random search on a TensorDictModule's parameters; step()
    Normalizer       running observation mean and variance, standardising observations

``__version__`` is the package's version.
"""

from rlpipe.algos import (
    ALGORITHMS,
    ARS,
    DQN,
    MBRL,
    PPO,
    SAC,
    Algorithm,
    ARSConfig,
    DQNConfig,
    MBRLConfig,
    PPOConfig,
    Reinforce,
    ReinforceConfig,
    SACConfig,
    make_algorithm,
)
from rlpipe.algos.ars import ARSSearch
from rlpipe.callbacks import Callback
from rlpipe.cli import compose_run
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
    "PPO",
    "PPOConfig",
    "Reinforce",
    "ReinforceConfig",
    "RlpipeError",
    "RunResult",
    "SAC",
    "SACConfig",
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
    "compose_run",
    "seed_everything",
    "train",
]
