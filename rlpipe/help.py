"""``python -m rlpipe --help``: the config groups and their options, the top-level keys with
their defaults, the other entry points and a few examples (Hydra's own: ``--hydra-help``)."""

from __future__ import annotations

import textwrap
from dataclasses import MISSING, fields

from rlpipe.config import Config
from rlpipe.registry import ALGORITHMS

# the groups a user picks from, as the command line names them, and what each holds
GROUPS = {
    "env": "the environment",
    "algo": "the algorithm (its keys: python -m rlpipe algo=<name> --cfg job)",
    "logger": "where metrics go besides the CSV files",
    "tuned": "settings tuned for an algo x env, picked with them (~tuned: the algo's own)",
    "+experiment": "a tuned preset by name (added with +): the same as its algo=... env=...",
    "+sweep": "an Optuna hyper-parameter search (added with +, run with -m)",
}
DEFAULTS = {"env": "cartpole", "algo": "dqn", "logger": "csv"}  # conf/config.yaml's defaults
# what each top-level key of Config means (tests/test_cli.py checks every field has a line)
KEYS = {
    "seed": "seeds Python, NumPy, torch and the environments",
    "device": "auto (cuda when present), cpu, cuda, cuda:N",
    "total_frames": "environment frames to train for (null: algo.total_frames)",
    "eval_every": "frames between greedy evaluations (null: the algorithm's)",
    "eval_episodes": "episodes per evaluation (null: the algorithm's)",
    "checkpoint_every": "frames between checkpoints (null: the algorithm's)",
    "keep_checkpoints": "newest checkpoints kept",
    "log_every": "frames between rows of training scalars (train/loss, time/fps)",
    "progress": "the progress bar",
    "video": "true: an mp4 at every evaluation; N: every N frames (video extra)",
    "threads": "torch intra-op threads: auto (1 on CPU), N, or 0 (torch's default)",
    "compile": "torch.compile the loss (DQN, SAC, PPO): false, true, auto (where it can)",
    "resume": "a run dir to continue from its newest intact checkpoint",
    "init_from": "a NEW run from a run dir's weights: <dir>[:<frames>|best] (newest)",
    "init_optimizer": "with init_from: also its optimizer state",
    "init_buffer": "with init_from: also its replay buffer (DQN, SAC, MBRL)",
}
ENTRY_POINTS = {
    "python -m rlpipe.evaluate run_dir=<dir>": "evaluate a trained run (or policy=random)",
    "python -m rlpipe.export run_dir=<dir>": "the trained policy as a TorchScript or ONNX file",
    "python -m rlpipe.plot <run or sweep dirs>": "learning curves, seeds averaged",
    "python -m rlpipe.play": "play CartPole or MountainCar with the keyboard",
}
EXAMPLES = {
    "python -m rlpipe algo=ars env=bipedal": "ARS teaches BipedalWalker to walk (the main job)",
    "python -m rlpipe algo=ars env=bipedal ~tuned": "the same with the notebook's own settings",
    "python -m rlpipe +experiment=dqn_cartpole seed=1": "a tuned preset, another seed",
    "python -m rlpipe -m algo=dqn,reinforce seed=0,1,2": "a sweep: 6 runs, then a summary",
}


def options(group: str) -> list[str]:
    """The options of a config group: the registered algorithms for ``algo`` (plug-ins
    included), else the YAML files under ``<group>/`` of rlpipe's and the plug-ins' config
    folders."""
    return sorted(ALGORITHMS) if group == "algo" else ALGORITHMS.conf_options(group.lstrip("+"))


def help_text() -> str:
    """The whole ``--help`` text."""
    lines = [
        "rlpipe: reinforcement-learning pipelines from TorchRL parts, composed with Hydra.",
        "",
        "usage: python -m rlpipe [group=option ...] [key=value ...]   (-m: a sweep over a,b,c)",
        "",
        "Config groups:",
    ]
    for group, what in GROUPS.items():
        names = [f"{n} (default)" if n == DEFAULTS.get(group) else n for n in options(group)]
        lines.append(f"  {group:<13}{what}")
        lines += textwrap.wrap(
            ", ".join(names), 96, initial_indent=" " * 17, subsequent_indent=" " * 17
        )
    lines += ["", "Top-level keys (default):"]
    for f in fields(Config):
        if f.name in KEYS:
            default = f.default if f.default is not MISSING else f.default_factory()
            value = "null" if default is None else str(default).lower()
            lines.append(f"  {f'{f.name}={value}':<24}{KEYS[f.name]}")
    lines += ["", "Entry points:"]
    lines += [f"  {command:<44} {what}" for command, what in ENTRY_POINTS.items()]
    lines += ["", "Examples:"]
    lines += [f"  {command:<52} {what}" for command, what in EXAMPLES.items()]
    lines += [
        "",
        "python -m rlpipe [overrides] --cfg job prints the composed config; --hydra-help: Hydra's",
        "own flags. README.md and docs/ explain every key. Algorithms from your own modules: name",
        "them in RLPIPE_PLUGINS=<module>, or install a package with an rlpipe.algorithms entry",
        "point (docs/api.md, plug-ins).",
    ]
    return "\n".join(lines)
