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
    ALGORITHMS       the registry (a mapping): name -> (config class, algorithm class)
    register         add an algorithm from outside the package to the registry
    DQN              deep Q-learning (discrete actions)
    Reinforce        REINFORCE, Monte-Carlo policy gradient (discrete or continuous)
    ARS              augmented random search, the runner's algorithm around an ARSSearch
    MBRL             model-based RL: a learned model and a planner
    PPO              proximal policy optimisation, clipped, with GAE
    SAC              soft actor-critic: twin Q, automatic entropy tuning
    Algorithm        the base class of what the Runner drives: every hook it uses, declared
    Runner           the one training loop: evaluations, metrics, signals, divergence checks
    RunResult        what a run reports: eval mean and std, frames, wall time, run dir
    Callback         hooks on the Runner: on_eval after each evaluation, on_end at the end
    make_logger      the TorchRL logger a LoggerConfig names
    seed_everything  seed Python's, NumPy's and torch's global generators
    evaluate         exactly n greedy episodes of a policy on an env; an EvalResult
    EvalResult       returns and lengths of evaluated episodes, their mean and std
    RlpipeError      a problem the user can fix (a ValueError); the CLIs print one line

Run directories:
    RunDir           one run's directory: its layout and every read and write of it
    load_run         a run rebuilt from its config.yaml and a checkpoint; a LoadedRun
    LoadedRun        a loaded run's cfg, algo (weights loaded) and checkpoint file
    find_runs        run dirs in or below some dirs (a sweep dir) that logged a metric
    group_runs       runs grouped when they differ only by seed
    plot_groups      learning curves of groups: mean or IQM over seeds, 95% bootstrap band
    plot_run         a run's curve.png

Exporting a trained policy (python -m rlpipe.export):
    export_policy    a run's greedy policy as one TorchScript, ONNX or state-dict file, checked
    ExportResult     what export_policy wrote: the file, its format and spec; summary_line()
    greedy_policy    a plain torch module: raw observations -> the greedy actions of an algorithm

ARS pieces, usable on any policy:
    ARSSearch        augmented random search on a TensorDictModule's parameters; step()
    Normalizer       running observation mean and variance, standardising observations

``__version__`` is the package's version. Every name is imported on first use: ``import rlpipe``
loads no torch (the command line answers ``--help`` and config errors before torch loads).
"""

from __future__ import annotations

import importlib
import os
from typing import Any

__version__ = "0.1.0"

# TorchRL logs INFO lines (in colour) to stdout from its import on, with a handler it resets then:
# rlpipe's console is its progress bar and summary line. WARNING unless you set the variable.
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
# SDL (pygame: gymnasium's renderers, moviepy's preview, which TensorBoard's video support
# imports) opens the sound card at import, and without one ALSA prints "Unknown PCM default"
# lines: rlpipe plays no sound. Unless you set the variable.
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")

# public name -> the module that defines it
_MODULES = {
    **dict.fromkeys(("Config", "EnvConfig", "LoggerConfig"), "rlpipe.config"),
    **dict.fromkeys(
        ("ARSConfig", "DQNConfig", "MBRLConfig", "PPOConfig", "ReinforceConfig", "SACConfig"),
        "rlpipe.algos.configs",
    ),
    "ALGORITHMS": "rlpipe.registry",
    "register": "rlpipe.registry",
    "make_algorithm": "rlpipe.algos",
    "Algorithm": "rlpipe.algos.base",
    "ARS": "rlpipe.algos.ars",
    "ARSSearch": "rlpipe.algos.ars",
    "DQN": "rlpipe.algos.dqn",
    "MBRL": "rlpipe.algos.mbrl",
    "PPO": "rlpipe.algos.ppo",
    "Reinforce": "rlpipe.algos.reinforce",
    "SAC": "rlpipe.algos.sac",
    "Callback": "rlpipe.runner",
    "Runner": "rlpipe.runner",
    "RunResult": "rlpipe.outcomes",
    "RunDir": "rlpipe.rundir",
    "compose_run": "rlpipe.cli",
    "make_env": "rlpipe.envs",
    "EvalResult": "rlpipe.episodes",
    "evaluate": "rlpipe.episodes",
    "RlpipeError": "rlpipe.errors",
    "plot_groups": "rlpipe.figures",
    "plot_run": "rlpipe.figures",
    "make_logger": "rlpipe.loggers",
    "find_runs": "rlpipe.runs",
    "group_runs": "rlpipe.runs",
    "Normalizer": "rlpipe.normalizer",
    "LoadedRun": "rlpipe.pipeline",
    "load_run": "rlpipe.pipeline",
    "train": "rlpipe.pipeline",
    "seed_everything": "rlpipe.runtime",
    "ExportResult": "rlpipe.export_formats",
    "export_policy": "rlpipe.export_formats",
    "greedy_policy": "rlpipe.greedy",
}

__all__ = sorted(_MODULES)


def __getattr__(name: str) -> Any:
    if name not in _MODULES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_MODULES[name]), name)
    if name != "evaluate":  # rlpipe.evaluate is also a submodule: see rlpipe/evaluate.py
        globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_MODULES])
