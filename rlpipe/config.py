"""Configs as dataclasses: fields with value rules, :class:`AlgoConfig` (the base of every
algorithm's config, :mod:`rlpipe.algos.configs`), and a run's :class:`Config` (env, algorithm,
logger and the runner's keys), also as the plain containers ``config.yaml`` and checkpoints hold,
with the fingerprint that ties a run dir to one run. Imports no torch.

Every schema is a plain dataclass, so research code builds configs without Hydra
(``DQNConfig(lr=3e-4)``). The command line registers them in Hydra's ConfigStore: a typo'd key
or a value of the wrong type fails at start-up naming the key, and value checks in
``__post_init__`` run when the composed config is turned into these objects.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import yaml
from omegaconf import OmegaConf

from rlpipe.errors import RULES, RlpipeError, check, check_choice
from rlpipe.registry import ALGORITHMS, PluginError, UnknownAlgorithm, config_class

# the run's length and cadence: top-level keys of Config that default to the algorithm's own
RUN_KEYS = ("total_frames", "eval_every", "eval_episodes", "checkpoint_every")


def checked(default: Any, rule: str | None = None, *, choices: Iterable[Any] = ()) -> Any:
    """A dataclass field with its default and its value rule: one of :data:`rlpipe.errors.RULES`
    (e.g. ``lr: float = checked(1e-4, "positive")``) or a set of ``choices``; see
    :func:`check_rules`. A list default becomes a default factory."""
    assert rule in RULES or (rule is None and choices), rule
    meta = {"rule": rule, "choices": tuple(choices)}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


def check_rules(cfg: object, prefix: str) -> None:
    """Check every :func:`checked` field of the dataclass ``cfg``; errors name the key as
    ``<prefix><field>``."""
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        if f.metadata.get("choices"):
            check_choice(value, prefix + f.name, f.metadata["choices"])
        elif f.metadata.get("rule"):
            test, requirement = RULES[f.metadata["rule"]]
            check(test(value), f"{prefix}{f.name} {requirement}, got {value}")


def flatten(node: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested dicts as one dict of dotted keys (``{"algo.lr": 0.001, ...}``); empty dicts and
    ``kwargs`` (gymnasium's, opaque) stay values."""
    flat: dict[str, Any] = {}
    for key, value in node.items():
        if isinstance(value, dict) and value and key != "kwargs":
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def check_run_keys(cfg: object, prefix: str) -> None:
    """Value checks of the :data:`RUN_KEYS` (null allowed: at the top level it means "the
    algorithm's"; for ``total_frames`` it means "the algorithm's own budget")."""
    for key, low in zip(RUN_KEYS, (1, 0, 1, 0)):
        value = getattr(cfg, key)
        check(value is None or value >= low, f"{prefix}{key} must be >= {low}, got {value}")


@dataclass
class AlgoConfig:
    """What every algorithm config holds besides its hyper-parameters: its registry ``name`` and
    the run length and cadence it needs, used where :class:`~rlpipe.config.Config` leaves them
    null."""

    # keys that do not decide the results (budgets, where rollouts run): left out of the
    # fingerprint that ties a run dir to one run (fingerprint below), like RUN_KEYS
    not_fingerprinted: ClassVar[tuple[str, ...]] = ()
    # keys that shape the networks (those the config has): a run fine-tuned from another
    # (init_from) keeps their values
    architecture: ClassVar[tuple[str, ...]] = ("hidden_sizes", "network")
    # keys that shape the replay buffer and what it holds: init_buffer keeps the parent's values
    buffer_keys: ClassVar[tuple[str, ...]] = ()

    name: str = ""
    total_frames: int | None = None  # None: the algorithm's own budget (epochs, iterations)
    eval_every: int = 10_000  # frames between greedy evaluations (0: only at the end)
    eval_episodes: int = 10
    checkpoint_every: int = 25_000  # frames between checkpoints (0: only at the end)
    # your network in place of the default: {_target_: my_pkg.MyNet, **kwargs}, built by Hydra's
    # instantiate with in_features/out_features from the env (docs/api.md); {}: the default
    network: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_run_keys(self, "algo.")
        check_rules(self, "algo.")

    def for_copies(self, copies: int) -> AlgoConfig:
        """This config as it runs on ``copies`` env copies stepped together (unchanged here;
        an algorithm whose batches round up to whole steps of the copies says what follows)."""
        return self

    def stepped_copies(self, num_envs: int) -> int:
        """How many env copies one step of the algorithm's envs moves when the run has
        ``num_envs``: ``env.backend=auto`` takes gymnasium's envs for one (an algorithm that
        steps copies of its own, as ARS its population, says how many)."""
        return num_envs


ENV_BACKENDS = ("auto", "gymnasium", "envpool")
DICT_OBS = ("flatten", "keys")


@dataclass
class EnvConfig:
    """Which gymnasium env to build, how many copies to step as one batch, and on what engine.

    ``backend``: see :mod:`rlpipe.envs.backends`."""

    id: str = "CartPole-v1"
    num_envs: int = checked(1, "at_least_one")
    max_episode_steps: int | None = checked(None, "optional_at_least_one")  # None: the env's own
    kwargs: dict[str, Any] = field(default_factory=dict)  # passed to gymnasium.make
    # auto: EnvPool where it is installed and runs the id, else gymnasium, and gymnasium for a
    # run of one env copy (a run records the one it used); gymnasium; envpool
    backend: str = checked("auto", choices=ENV_BACKENDS)
    # observations (docs/api.md "Observations"): a Dict's keys as one flat vector; flatten: the
    # networks see it whole; keys: they encode each key apart (an MLP each, a CNN per image)
    dict_obs: str = checked("flatten", choices=DICT_OBS)
    # images (3-D uint8, HWC): frames stacked (null: 4), resized to [height, width] (null: as
    # they come), to one grey channel
    frame_stack: int | None = checked(None, "optional_at_least_one")
    resize: list[int] | None = None
    grayscale: bool = False

    def __post_init__(self) -> None:
        check_rules(self, "env.")
        check(
            self.resize is None or (len(self.resize) == 2 and min(self.resize) >= 1),
            f"env.resize must be [height, width] of positive sizes or null, got {self.resize}",
        )


LOGGER_BACKENDS = ("csv", "tensorboard", "wandb", "mlflow", "none")
WANDB_MODES = ("online", "offline", "disabled")


@dataclass
class LoggerConfig:
    """Where metrics go: ``csv``, ``tensorboard``, ``wandb``, ``mlflow`` or ``none``.

    ``csv`` is :class:`rlpipe.loggers.CsvLogger` in the run dir; the services also write the
    CSV files."""

    backend: str = checked("csv", choices=LOGGER_BACKENDS)
    project: str | None = None  # W&B project / MLflow experiment (default "rlpipe")
    mode: str | None = checked(None, choices=(*WANDB_MODES, None))  # W&B; null: offline unless
    # a project is set
    tracking_uri: str | None = None  # MLflow; null: sqlite:///<run dir>/mlflow.db

    def __post_init__(self) -> None:
        check_rules(self, "logger.")


@dataclass
class Config:
    """A whole training run: environment, algorithm, logger and the runner's knobs.

    ``Config()`` is ``python -m rlpipe`` with no overrides: DQN on CartPole-v1. The run keys
    (:data:`RUN_KEYS`) left null take the algorithm config's values (see :meth:`resolved`).
    """

    env: EnvConfig = field(default_factory=EnvConfig)
    algo: Any = field(
        default_factory=lambda: ALGORITHMS.config("dqn")()
    )  # AlgoConfig  # an AlgoConfig (DQNConfig, ARSConfig, ...)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    seed: int = checked(0, "seed")
    device: str = checked("auto", "device")  # auto: cuda when available, else cpu
    total_frames: int | None = None  # null: algo.total_frames
    eval_every: int | None = None  # null: algo.eval_every
    eval_episodes: int | None = None  # null: algo.eval_episodes
    checkpoint_every: int | None = None  # null: algo.checkpoint_every
    keep_checkpoints: int = checked(3, "at_least_one")
    # frames between two rows of the training scalars (train/loss, time/fps, ...): their mean
    log_every: int = checked(1_000, "at_least_one")
    progress: bool = True
    video: Any = False  # false | true (every evaluation) | N (every N frames); always at the end
    # torch intra-op threads: auto (1 on CPU: small networks gain nothing from more, and idle
    # OpenMP threads spin against every other process), N, or 0 (torch's default: one per core)
    threads: Any = "auto"
    # torch.compile of the loss: false, true (an error where torch cannot compile), auto (where
    # it can, else one warning); false by default: on CPU it was slower (BENCHMARKS.md)
    compile: Any = False
    resume: str | None = None  # a run dir to continue from its last good checkpoint
    # a NEW run from a trained run's weights and observation normaliser:
    # <run dir>[:<frames>|best|<checkpoint file>] (newest by default; config.yaml pins the file)
    init_from: str | None = None
    init_optimizer: bool = False  # with init_from: also its optimizer state (Adam's moments)
    init_buffer: bool = False  # with init_from: also its replay buffer (DQN, SAC, MBRL)

    def __post_init__(self) -> None:
        check_run_keys(self, "")
        check_rules(self, "")
        check(
            self.init_from is None or bool(split_init_from(self.init_from)[0]),
            f"init_from must be a run dir, optionally with :<frames>, :best or :<checkpoint "
            f"file>, got {self.init_from!r}",
        )
        for key in ("init_optimizer", "init_buffer"):
            check(
                not getattr(self, key) or self.init_from is not None,
                f"{key}=true takes a part of the run init_from names; add init_from=<run dir>",
            )
        cores = os.cpu_count() or 1
        check(
            self.threads == "auto" or (type(self.threads) is int and 0 <= self.threads <= cores),
            f"threads must be auto or a number from 0 (torch's default) to {cores} (the cores "
            f"here), got {self.threads!r}",
        )
        check(
            isinstance(self.compile, bool) or self.compile == "auto",
            f"compile must be true, false or auto, got {self.compile!r}",
        )
        check(
            isinstance(self.video, bool) or (isinstance(self.video, int) and self.video >= 0),
            f"video must be true, false or a frame cadence N >= 1, got {self.video!r}",
        )

    def resolved(self) -> Config:
        """This config with every null run key taken from ``algo`` (``total_frames`` may stay
        null: the algorithm's own budget of epochs or iterations then ends the run), ``algo``'s
        run keys set to the result, and ``algo`` as it runs on ``env.num_envs`` copies
        (:meth:`AlgoConfig.for_copies`): what ``config.yaml`` records."""
        own = {key: getattr(self.algo, key) for key in RUN_KEYS if getattr(self, key) is None}
        run = replace(self, **own)
        # the algorithm sees the run's keys too (e.g. a schedule spanning total_frames), and
        # what its batches become on the env's copies
        algo = replace(self.algo, **{key: getattr(run, key) for key in RUN_KEYS})
        return replace(run, algo=algo.for_copies(self.env.num_envs))

    def stepped_copies(self) -> int:
        """How many env copies a run of this config steps at once: its algorithm's say on
        ``env.num_envs`` (:meth:`AlgoConfig.stepped_copies`; ``env.backend=auto``'s choice)."""
        return self.algo.stepped_copies(self.env.num_envs)


# top-level keys that do not decide a run's results: its length and cadences, logging,
# progress, and where it runs (the algorithm's own are AlgoConfig.not_fingerprinted)
NOT_FINGERPRINTED = (
    *RUN_KEYS,
    "keep_checkpoints",
    "log_every",
    "progress",
    "video",
    "threads",
    "compile",
    "device",
    "resume",
    "logger",
)


# what may follow init_from's run dir after a colon: a frame count, best, or a checkpoint's name
CHECKPOINT_NAME = re.compile(r"\d+|best|(ckpt|best)_\d+\.pt")


def split_init_from(spec: str) -> tuple[str, str | None]:
    """``init_from``'s ``(run dir, checkpoint)``: ``"runs/a:4096"`` -> ``("runs/a", "4096")``;
    ``"runs/a"`` -> ``("runs/a", None)`` (the newest)."""
    where, colon, name = spec.rpartition(":")
    if colon and where and CHECKPOINT_NAME.fullmatch(name):
        return where, name
    return spec, None


def config_to_dict(cfg: Config) -> dict[str, Any]:
    """``cfg`` as plain containers (what ``config.yaml`` and checkpoints store)."""
    return OmegaConf.to_container(OmegaConf.structured(cfg))


def config_from_yaml(data: bytes, path: Path, *, allow_code: bool = False) -> Config:
    """The :class:`Config` a ``config.yaml`` (its bytes ``data``, read from ``path``) holds; one
    line naming ``path`` if it is damaged. A config that names code to import (an ``env.id`` of the
    form ``module:Id``, an ``algo.network`` ``_target_``) is refused unless ``allow_code``."""
    try:
        loaded = yaml.safe_load(data.decode())
        if not (isinstance(loaded, dict) and isinstance(loaded.get("algo"), dict)):
            raise ValueError("not a run config")
        cfg = config_from_dict(loaded)
    except PluginError as err:  # rlpipe wrote it, for an algorithm from outside rlpipe
        raise RlpipeError(f"{path}: {err}") from err
    except (RlpipeError, yaml.YAMLError, TypeError, ValueError, KeyError, AttributeError) as err:
        reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RlpipeError(f"{path} is damaged ({reason}); it is not a config rlpipe wrote") from err
    code = [f"env.id={cfg.env.id!r}"] if ":" in cfg.env.id else []
    if cfg.algo.network.get("_target_"):
        code.append(f"algo.network._target_={cfg.algo.network.get('_target_')!r}")
    check(
        allow_code or not code,
        f"{path} names {code[0] if code else ''}, which would import its module: a run dir "
        "is data, not code; pass allow_env_import=true if you trust this run dir",
    )
    return cfg


def config_from_dict(data: dict[str, Any]) -> Config:
    """Rebuild a :class:`Config` (value checks included) from :func:`config_to_dict` output;
    keys a newer or older version does not know are dropped, missing ones take the default.
    An algorithm name that is not registered raises :class:`~rlpipe.registry.UnknownAlgorithm`."""
    data = _with_legacy_env(data)
    algo = dict(data.pop("algo"))
    name = algo.get("name")
    check(isinstance(name, str) and name.isidentifier(), f"no algorithm name, got {name!r}")
    if name not in ALGORITHMS:
        raise UnknownAlgorithm(name)
    return Config(
        env=_build(EnvConfig, data.pop("env")),
        algo=_build(ALGORITHMS.config(algo["name"]), algo),
        logger=_build(LoggerConfig, data.pop("logger")),
        **{k: v for k, v in data.items() if k in _names(Config)},
    )


def _with_legacy_env(data: dict[str, Any]) -> dict[str, Any]:
    """A copy of a config's containers; an ``env`` without ``backend`` (written before there
    was a choice) ran on gymnasium; a config without ``init_from`` (written before there was
    one) started from scratch."""
    data = {"init_from": None, "init_optimizer": False, "init_buffer": False, **data}
    if isinstance(data.get("env"), dict):
        data["env"] = {"backend": "gymnasium", **data["env"]}
    return data


def _names(cls: type) -> set[str]:
    return {f.name for f in fields(cls)}


def _build(cls: type, data: dict[str, Any]) -> Any:
    assert is_dataclass(cls)
    return cls(**{k: v for k, v in data.items() if k in _names(cls)})


def fingerprint(cfg: Config | dict[str, Any]) -> dict[str, Any]:
    """What decides a run's results, flat (``{"algo.lr": 0.0001, "seed": 0, ...}``): algorithm,
    env, architecture, hyper-parameters and seed; not budgets, cadences, logging or progress."""
    data = config_to_dict(cfg) if isinstance(cfg, Config) else _with_legacy_env(cfg)
    algo = dict(data.get("algo") or {})
    schema = config_class(algo.get("name"))
    if schema is not None and not isinstance(cfg, Config):
        # a field added since the config was stored: the run had its default then
        algo = {**OmegaConf.to_container(OmegaConf.structured(schema)), **algo}
    for key in (*RUN_KEYS, *(schema.not_fingerprinted if schema else ())):
        algo.pop(key, None)
    data = {k: v for k, v in data.items() if k not in NOT_FINGERPRINTED}
    return flatten({**data, "algo": algo})


def fingerprint_diff(ours: dict[str, Any], theirs: dict[str, Any]) -> str:
    """The keys in which two fingerprints differ, as ``key (ours here, theirs there)``."""
    keys = [k for k in {**theirs, **ours} if ours.get(k) != theirs.get(k)]
    keys.sort(key=lambda k: k not in ("algo.name", "env.id"))  # what tells runs apart first
    shown = [f"{k} ({ours.get(k)!r} here, {theirs.get(k)!r} there)" for k in keys[:3]]
    more = f" and {len(keys) - 3} more" if len(keys) > 3 else ""
    return ", ".join(shown) + more
