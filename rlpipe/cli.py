"""Hydra glue for the command line: config registration and composition, the entry points'
shared opening, and one-line error reporting."""

from __future__ import annotations

import dataclasses
import logging
import os
import re
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NoReturn

from hydra import compose, initialize_config_module
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException, MissingConfigException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from rlpipe.algos import ALGORITHMS
from rlpipe.config import Config, EnvConfig
from rlpipe.errors import RlpipeError, check
from rlpipe.runner import Interrupted

USER_ERRORS = (RlpipeError, HydraException, OmegaConfBaseException)
# Hydra launcher/sweeper plugins and the rlpipe extra that installs each
PLUGIN_EXTRAS = {
    "joblib": "joblib",
    "submitit_local": "submitit",
    "submitit_slurm": "submitit",
    "optuna": "optuna",
}


def register_configs() -> None:
    """Store the dataclass schemas so Hydra type-checks every config file and override."""
    store = ConfigStore.instance()
    # env.id has no default on the command line: every conf/env file (or env.id=...) sets it
    store.store(name="rlpipe_config", node=Config(env=EnvConfig(id=MISSING), algo=MISSING))
    for name, (schema, _) in ALGORITHMS.items():
        store.store(group="schema/algo", name=name, node=schema)


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

    The presets from Python: ``compose_run("+experiment=dqn_cartpole", "seed=1")``."""
    register_configs()
    with initialize_config_module(config_module="rlpipe.conf", version_base="1.3"):
        return to_config(compose("config", overrides=open_entries(overrides)))


def write_hydra_record(run_dir: str | Path, job_cfg: DictConfig) -> None:
    """Write Hydra's record of the job (``.hydra/config.yaml`` from ``job_cfg``, ``hydra.yaml``,
    ``overrides.yaml``) into ``run_dir`` unless it has one.

    ``conf/config.yaml`` turns Hydra's own writing off (``hydra.output_subdir: null``): Hydra
    writes before a job can check that the dir is its own. rlpipe writes the same files once
    the run dir is checked, and a resumed run keeps the record of the run it continues.
    """
    record = Path(run_dir) / ".hydra"
    try:
        record.mkdir(parents=True)
    except FileExistsError:
        return
    hydra_cfg = HydraConfig.get()
    OmegaConf.save(job_cfg, record / "config.yaml")
    OmegaConf.save(OmegaConf.create({"hydra": hydra_cfg}), record / "hydra.yaml")
    OmegaConf.save(hydra_cfg.overrides.task, record / "overrides.yaml")


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


def validate_overrides(argv: Sequence[str]) -> None:
    """Compose ``python -m rlpipe``'s config from ``argv``'s overrides (flags, their values and
    ``hydra`` keys left out) and run every check :func:`to_config` runs."""
    overrides, skip = [], False
    for arg in argv:
        if skip or arg.startswith("-"):
            skip = arg in ("-c", "--cfg", "-p", "--package", "-cn", "--config-name", "-cp")
            continue
        if not re.match(r"^[+~]{0,2}hydra[./]", arg):
            overrides.append(arg)
    with initialize_config_module("rlpipe.conf", version_base="1.3"):
        to_config(compose("config", overrides=overrides))


def check_launcher(argv: Sequence[str]) -> None:
    """Refuse ``hydra/launcher=submitit_slurm`` where Slurm is not (no ``srun`` on the PATH)."""
    launchers = [arg.partition("=")[2] for arg in argv if re.match(r"^\+{0,2}hydra/launcher=", arg)]
    check(
        not launchers or launchers[-1] != "submitit_slurm" or shutil.which("srun") is not None,
        "hydra/launcher=submitit_slurm needs a Slurm cluster, and srun is not on the PATH here: "
        "run the sweep on a Slurm login node, or here with hydra/launcher=submitit_local (or "
        "joblib)",
    )


def run_entry_point(
    doc: str, argv: Sequence[str] | None, body: Callable[[list[str]], None]
) -> None:
    """The opening of ``python -m rlpipe.<command>``: ``-h``/``--help`` prints ``doc``, else
    ``body(args)`` runs with TorchRL's logger quiet; its user errors print one line, exit 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    if {"-h", "--help"} & set(args):
        print(doc.strip())
        return
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # the console is the command's output
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
        print(f"rlpipe: {err}", file=sys.stderr)
        sys.exit(err.exit_code)
    print(f"rlpipe: error: {format_error(err)}", file=sys.stderr)
    sys.exit(2)


def run_cli(hydra_main: Callable[[], Any]) -> None:
    """Call a ``@hydra.main`` function; user errors become one line on stderr and exit 2."""
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")  # let errors reach us instead of Hydra's print
    try:
        hydra_main()
    except USER_ERRORS as err:
        fail(err)
    except OSError as err:  # e.g. Hydra cannot create the run directory
        where = f" {err.filename}" if err.filename else ""
        fail(
            RlpipeError(
                f"cannot write{where}: {err.strerror or err}; pick a writable directory "
                "with hydra.run.dir=<dir> (hydra.sweep.dir=<dir> for -m)"
            )
        )
