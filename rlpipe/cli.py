"""Hydra glue for the command line: config registration and composition, the entry points'
shared opening, and one-line error reporting."""

from __future__ import annotations

import dataclasses
import importlib
import importlib.resources
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any, NoReturn

from hydra import compose, initialize_config_module
from hydra.core.config_search_path import ConfigSearchPath
from hydra.core.config_store import ConfigStore
from hydra.core.plugins import Plugins
from hydra.errors import HydraException, MissingConfigException
from hydra.plugins.search_path_plugin import SearchPathPlugin
from omegaconf import MISSING, DictConfig, OmegaConf, open_dict
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from rlpipe.config import AlgoConfig, Config, EnvConfig
from rlpipe.console import console_may_close, say
from rlpipe.errors import RlpipeError, check
from rlpipe.outcomes import Interrupted
from rlpipe.registry import ALGORITHMS, how_to_register

USER_ERRORS = (RlpipeError, HydraException, OmegaConfBaseException)
# Hydra launcher/sweeper plugins and the rlpipe extra that installs each
PLUGIN_EXTRAS = {
    "joblib": "joblib",
    "submitit_local": "submitit",
    "submitit_slurm": "submitit",
    "ray": "ray",
    "optuna": "optuna",
}


class PluginSearchPath(SearchPathPlugin):
    """Hydra's config search path plus the config folders of registered algorithms
    (``rlpipe.register(..., conf=...)``): a plug-in's tuned settings and presets."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        for entry in ALGORITHMS.search_path():
            search_path.append("rlpipe-plugin", entry)


def register_configs() -> None:
    """Store the dataclass schemas so Hydra type-checks every config file and override, add the
    registered algorithms' config folders to Hydra's search path, and make each algorithm
    without an ``algo/<name>.yaml`` there an ``algo`` option: its schema."""
    store = ConfigStore.instance()
    # env.id has no default on the command line: every conf/env file (or env.id=...) sets it
    store.store(name="rlpipe_config", node=Config(env=EnvConfig(id=MISSING), algo=MISSING))
    Plugins.instance().register(PluginSearchPath)
    files = set(ALGORITHMS.conf_options("algo"))
    for name in ALGORITHMS:  # their configs only: no algorithm module (nor torch) is imported
        schema = ALGORITHMS.config(name)
        store.store(group="schema/algo", name=name, node=schema)
        if name not in files:  # a file and a schema of one name: Hydra's deprecated matching
            store.store(group="algo", name=name, node=schema)
    # hydra/sweeper=optuna: Hydra's plugin scan finds it in an installed rlpipe, not in an
    # editable one (whose import hook the scan does not see); importing it stores its configs
    from rlpipe.optuna_search import PLUGIN

    importlib.import_module(PLUGIN)


def register_sweeper() -> None:
    """Hand Hydra rlpipe's Optuna sweeper class (before a sweep: Hydra's first use of its plugins
    scans them all)."""
    from rlpipe.optuna_search import PLUGIN

    Plugins.instance().register(importlib.import_module(PLUGIN).OptunaSweeper)


def unknown_keys(node: DictConfig, prefix: str = "") -> Iterator[str]:
    """Keys added with ``+key=...`` that the node's dataclass schema does not have."""
    schema = OmegaConf.get_type(node)
    if not dataclasses.is_dataclass(schema):
        return
    names = {f.name for f in dataclasses.fields(schema)}
    for key in node.keys():
        if key not in names:
            yield f"{prefix}{key}"
        elif isinstance(node._get_node(key), DictConfig):
            yield from unknown_keys(node[key], f"{prefix}{key}.")


def to_config(cfg: DictConfig) -> Config:
    """Turn Hydra's composed config into :class:`Config` objects (running their checks)."""
    unknown = list(unknown_keys(cfg))
    if unknown:
        raise RlpipeError(f"unknown config key {unknown[0]!r}; see `python -m rlpipe --cfg job`")
    return OmegaConf.to_object(cfg)


# dict-valued keys whose entries are the user's (gymnasium kwargs, a network's _target_ and
# kwargs): `key.name=value` adds the entry, as `++key.name=value` would
OPEN_KEYS = ("algo.network.", "env.kwargs.")


def open_entries(overrides: Sequence[str]) -> list[str]:
    """``algo.network._target_=...`` and ``env.kwargs.x=...`` without Hydra's ``+``."""
    return [f"++{arg}" if arg.startswith(OPEN_KEYS) else arg for arg in overrides]


def compose_run(*overrides: str) -> Config:
    """The :class:`Config` that ``python -m rlpipe <overrides>`` would run.

    Tuned settings included (``conf/tuned/<algo>_<env>.yaml``; ``"~tuned"``: the algorithm's
    own defaults). The presets from Python: ``compose_run("algo=dqn", "seed=1")``."""
    register_configs()
    with initialize_config_module(config_module="rlpipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=open_entries(overrides), return_hydra_config=True)
    check_choices(cfg.hydra.runtime.choices, OmegaConf.select(cfg, "env.id", default=None))
    return to_config(without_hydra(cfg))


def without_hydra(cfg: DictConfig) -> DictConfig:
    """A composed config without the ``hydra`` node that ``return_hydra_config`` adds."""
    with open_dict(cfg):
        del cfg["hydra"]
    return cfg


def check_choices(choices: DictConfig, env_id: str | None) -> None:
    """A ``+experiment=<preset>`` names its algo and env: an ``algo=`` or ``env=`` that
    contradicts them is refused in one line (it would run something else under its name), as is
    an ``env.id=`` other than the env option's own where tuned settings were picked for it."""
    check_tuned_id(choices, env_id)
    preset = choices.get("experiment")
    if not preset:
        return
    source = ALGORITHMS.conf_file("experiment", preset)
    if source is None:  # a preset from a folder on hydra.searchpath: not ours to check
        return
    wanted = {
        next(iter(entry)).split()[-1].strip("/"): next(iter(entry.values()))
        for entry in OmegaConf.load(source).get("defaults", [])
        if isinstance(entry, DictConfig)
    }
    for group, option in wanted.items():
        check(
            choices.get(group) == option,
            f"+experiment={preset} is {wanted.get('algo')} on env={wanted.get('env')}, but "
            f"{group}={choices.get(group)} was asked for: drop one of them (the tuned settings "
            f"of any algo x env are picked by algo=... env=... alone)",
        )


def env_option(option: str) -> tuple[str | None, dict]:
    """The id (None where it sets none) and ``kwargs`` that ``conf/env/<option>.yaml`` (or a
    plug-in's) sets."""
    source = ALGORITHMS.conf_file("env", option)
    if source is None:
        return None, {}
    node = OmegaConf.load(source)
    env_id = OmegaConf.select(node, "id", default=None, throw_on_resolution_failure=False)
    kwargs = node.get("kwargs")
    kwargs = OmegaConf.to_container(kwargs) if isinstance(kwargs, DictConfig) else {}
    return (env_id if isinstance(env_id, str) else None), kwargs


def other_options(option: str, env_id: str) -> list[tuple[str, dict]]:
    """The env options other than ``option`` that set ``env_id``, each with its ``kwargs``."""
    found = [(o, env_option(o)) for o in ALGORITHMS.conf_options("env") if o != option]
    return [(o, kwargs) for o, (their_id, kwargs) in found if their_id == env_id]


def check_tuned_id(choices: DictConfig, env_id: str | None) -> None:
    """Tuned settings belong to their env option's id: ``env.id=`` another id beside them is
    refused in one line, naming the env option of that id, if any, and ``~tuned``."""
    tuned, env = choices.get("tuned"), choices.get("env")
    if not tuned or ALGORITHMS.conf_file("tuned", tuned) is None or env_id is None:
        return
    own = env_option(env)[0]
    if own is None or own == env_id:
        return
    algo = choices.get("algo")
    same = [o for o, _ in other_options(env, env_id)]
    fix = f"add ~tuned ({algo}'s defaults)"
    if same and ALGORITHMS.conf_file("tuned", f"{algo}_{same[0]}") is not None:
        fix = f"use env={same[0]} (tuned/{algo}_{same[0]}.yaml) or {fix}"
    elif same:
        fix = f"use env={same[0]} ({algo}'s defaults there)"
    raise RlpipeError(
        f"env.id={env_id} with env={env}: the tuned settings picked for algo={algo} env={env} "
        f"(tuned/{tuned}.yaml) are {own}'s; for {env_id} {fix}"
    )


# envs on which algorithms' own defaults are known to fail, why, and the algorithms (of those
# that can act there) whose defaults fail: the run says so at start
EXPLORATION_TRAPS: dict[str, tuple[str, tuple[str, ...]]] = {
    "MountainCar-v0": (
        "a known exploration trap: every step costs -1 until the car first reaches the flag, and "
        "random pushes one step at a time undo each other's swing, so it rarely gets there "
        "(episodes of -200 with nothing to learn from); DQN with each random action held for "
        "many steps gets there (rlpipe: algo=dqn env=mountaincar, tuned with εz-greedy), and "
        "so do ARS's defaults",
        ("dqn", "ppo", "reinforce"),
    ),
    "MountainCarContinuous-v0": (
        "a known exploration trap: every action costs reward until the car first reaches the "
        "flag, so exploration that stays local learns to stand still (a return near 0); SAC "
        "with exploration noise correlated in time gets there (the RL Zoo: gSDE; rlpipe: "
        "algo=sac env=mountaincar_continuous, tuned with pink noise)",
        ("ars", "mbrl", "ppo", "reinforce", "sac"),
    ),
}
# the algorithm settings that escape those traps where they are set (exploration correlated in
# time: coloured noise, held random actions): a run setting one is off its defaults' exploration
TRAP_ESCAPES = {"sac": "noise_color", "dqn": "eps_zeta"}


def trap_notice(algo: AlgoConfig, env_id: str) -> str | None:
    """The line a run without tuned settings starts with where ``algo``'s defaults are known to
    fail on ``env_id`` (:data:`EXPLORATION_TRAPS`) and it does not set what escapes the trap
    (:data:`TRAP_ESCAPES`); None elsewhere, and for an algorithm that cannot act there (its
    own error says so)."""
    why, trapped = EXPLORATION_TRAPS.get(env_id.split(":")[-1], ("", ()))
    escape = TRAP_ESCAPES.get(algo.name)
    if algo.name not in trapped or (escape is not None and getattr(algo, escape)):
        return None
    return f"rlpipe: note: {algo.name}'s defaults on {env_id}: {why}"


def tuned_notice(choices: DictConfig) -> str | None:
    """The line a run with tuned settings starts with (None: the algorithm's own defaults)."""
    tuned = choices.get("tuned")  # Hydra names the optional option even where no file is
    if not tuned or ALGORITHMS.conf_file("tuned", tuned) is None:
        return None
    algo = choices.get("algo")
    ours = importlib.resources.files("rlpipe.conf") / "tuned" / f"{tuned}.yaml"
    where = (
        f"conf/tuned/{tuned}.yaml, results in BENCHMARKS.md"
        if ours.is_file()
        else f"tuned/{tuned}.yaml in {algo}'s config folder"
    )
    return (
        f"rlpipe: {algo} on env={choices.get('env')} with its tuned settings ({where}); the "
        "algorithm's own defaults instead: add ~tuned"
    )


def tuned_elsewhere_notice(choices: DictConfig, env: EnvConfig) -> str | None:
    """The line a run on the algorithm's defaults starts with where another env option of the
    same env (id and kwargs) has tuned settings for it (``env=gym env.id=CartPole-v1``); None
    elsewhere and under ``~tuned``."""
    tuned, option, algo = choices.get("tuned"), choices.get("env"), choices.get("algo")
    if not tuned or ALGORITHMS.conf_file("tuned", tuned) is not None:
        return None
    for other, kwargs in other_options(option, env.id):
        if kwargs == env.kwargs and ALGORITHMS.conf_file("tuned", f"{algo}_{other}") is not None:
            return (
                f"rlpipe: note: {algo}'s own defaults on {env.id}; env={other} instead of "
                f"env={option} picks its tuned settings (tuned/{algo}_{other}.yaml)"
            )
    return None


def compose_config(name: str, overrides: Sequence[str]) -> Any:
    """Compose ``conf/<name>.yaml`` with ``key=value`` overrides into its dataclass object.

    For the small commands (``rlpipe.evaluate``, ``rlpipe.play``): Hydra's composition without
    ``@hydra.main``'s run directory and logging.
    """
    for arg in overrides:
        check(
            re.match(r"^[+~]{0,2}[\w.]+=", arg) is not None,
            f"expected key=value arguments, got {arg!r}; see python -m rlpipe.{name} --help",
        )
    with initialize_config_module("rlpipe.conf", version_base="1.3"):
        cfg = compose(name, overrides=list(overrides))
    unknown = list(unknown_keys(cfg))
    if unknown:
        raise RlpipeError(f"unknown key {unknown[0]!r}; see python -m rlpipe.{name} --help")
    if "env" in cfg and OmegaConf.is_missing(cfg.env, "id"):
        cfg.env = None  # no env option chosen
    return OmegaConf.to_object(cfg)


def run_entry_point(
    doc: str, argv: Sequence[str] | None, body: Callable[[list[str]], None]
) -> None:
    """The opening of ``python -m rlpipe.<command>``: ``-h``/``--help`` prints ``doc``, else
    ``body(args)`` runs; its user errors print one line, exit 2. A console that closes ends
    neither."""
    args = sys.argv[1:] if argv is None else list(argv)
    with console_may_close():
        if {"-h", "--help"} & set(args):
            print(doc.strip())
            return
        try:
            body(args)
        except USER_ERRORS as err:
            fail(err)


def format_error(err: BaseException) -> str:
    """Squeeze a user error into one line naming the problem (and the valid choices)."""
    if isinstance(err, MissingConfigException) and err.options and err.missing_cfg_file:
        group, _, name = err.missing_cfg_file.rpartition("/")
        message = f"unknown {group} option {name!r}; choose one of: {', '.join(err.options)}"
        if group.startswith("hydra/") and name in PLUGIN_EXTRAS:
            message += f'; install it with: pip install "rlpipe[{PLUGIN_EXTRAS[name]}]"'
        elif group == "algo":
            message += f"; an algorithm from outside rlpipe: {how_to_register(name)}"
        return message
    if isinstance(err, MissingMandatoryValue):
        return f"{err.full_key} must be set, e.g. python -m rlpipe {err.full_key}=<value>"
    lines = [line.strip() for line in str(err).splitlines() if line.strip()] or [type(err).__name__]
    added = re.match(
        r"Could not override '(experiment|sweep)'\. No match in the defaults list", lines[0]
    )
    if added:  # a group that is not in the defaults list: it is added with +
        group = added.group(1)
        typed = next((a for a in sys.argv[1:] if a.startswith(f"{group}=")), f"{group}=<name>")
        return f"{group} is not in the defaults list, so it is added with a +: use +{typed}"
    # Hydra's "... raised while composing config:" says what failed on the next line
    first = " ".join(lines[:2]) if lines[0].endswith(":") else lines[0]
    cause = err.__cause__
    if isinstance(err, RlpipeError):  # already one line of ours (it may name a file it read)
        return first
    if isinstance(cause, RlpipeError):
        return str(cause)
    if isinstance(cause, (MissingMandatoryValue, OmegaConfBaseException)):
        return f"{first.rstrip('.')}: {format_error(cause)}"
    return first


def fail(err: BaseException) -> NoReturn:
    """Print ``rlpipe: error: <one line>`` to stderr and exit with code 2; an interrupted run
    prints how to resume and exits with 128 + the signal number."""
    if isinstance(err, Interrupted):
        say(f"rlpipe: {err}", err=True)
        sys.exit(err.exit_code)
    print(f"rlpipe: error: {format_error(err)}", file=sys.stderr)
    sys.exit(2)
