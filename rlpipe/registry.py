"""The algorithm registry: ``algo`` option name -> config class, builder and config folder, each
imported when first asked for, plug-ins found when a name is missing. Imports no torch: the
command line lists and checks configs before any algorithm module (and torch) loads, and an
algorithm's module loads only once it is chosen.

Built-in entries name their classes as ``"module:attribute"`` strings; :func:`register` adds
an algorithm from outside the package, as classes or as such strings. Plug-ins register
themselves when imported: the modules named in ``RLPIPE_PLUGINS`` (comma-separated) and the
``rlpipe.algorithms`` entry points of installed packages (an entry point's name is the
algorithm's, its value the module that registers it), imported when a name is not registered
or when every name is listed.
"""

from __future__ import annotations

import importlib
import importlib.resources
import os
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rlpipe.errors import RlpipeError, check, check_choice

if TYPE_CHECKING:
    from importlib.resources.abc import Traversable

ENTRY_POINT_GROUP = "rlpipe.algorithms"
PLUGINS_VARIABLE = "RLPIPE_PLUGINS"


def how_to_register(name: str) -> str:
    """The three ways algorithm ``name`` from outside rlpipe becomes known to a process."""
    return (
        f"install the package that provides it (an {ENTRY_POINT_GROUP} entry point), name the "
        f"module that registers it in {PLUGINS_VARIABLE} (PYTHONPATH=<its folder> "
        f"{PLUGINS_VARIABLE}=<module>), or call rlpipe.register({name!r}, ...) first"
    )


@dataclass
class _Entry:
    config: type | str  # the config dataclass, or "module:attribute" naming it
    builder: Callable[..., Any] | str  # builder(env_factory, cfg, device=..., network=...)
    conf: str | None  # a folder of Hydra config files, as a search path entry (pkg:// or file://)


def _resolve(target: Any) -> Any:
    if not isinstance(target, str):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def _search_path_entry(conf: str | os.PathLike[str]) -> str:
    """``conf`` as Hydra's search path names it: ``pkg://<package>`` as given, a folder as
    ``file://<absolute path>`` (which must exist)."""
    if isinstance(conf, str) and conf.startswith(("pkg://", "file://")):
        return conf
    folder = Path(conf).absolute()
    check(folder.is_dir(), f"conf= must be a folder of config files or pkg://<package>, got {conf}")
    return f"file://{folder}"


def _folder(entry: str) -> Traversable:
    """The folder a search path entry names (a ``pkg://`` one: its package's files)."""
    if entry.startswith("pkg://"):
        return importlib.resources.files(entry[len("pkg://") :].replace("/", "."))
    return Path(entry[len("file://") :])


class Registry(Mapping):
    """``name -> (config class, builder)``, as a read-only mapping whose values import the
    builder's module on access; :meth:`config` imports only the config's. A name it does not
    hold makes it import the plug-ins first (``RLPIPE_PLUGINS``, then the entry point of that
    name); listing it imports every plug-in."""

    def __init__(self) -> None:
        self._entries: dict[str, _Entry] = {}
        self._variable_read = False  # RLPIPE_PLUGINS imported
        self._entry_points_read: set[str] | None = set()  # the names loaded; None: all of them

    def register(
        self,
        name: str,
        config: type | str,
        builder: Callable[..., Any] | str,
        *,
        conf: str | os.PathLike[str] | None = None,
    ) -> None:
        """Add (or replace) algorithm ``name`` in the registry.

        ``config``: its config dataclass (an ``AlgoConfig`` subclass whose ``name`` defaults to
        ``name``); ``builder``: what builds it, ``builder(env_factory, cfg, device=...,
        network=...)``; each an object or a ``"module:attribute"`` string imported on first use.
        ``algo=<name>`` works on the command line without a config file; ``conf``: a folder of
        config files the command line searches too (its ``tuned/<name>_<env>.yaml``,
        ``experiment/`` presets, ``algo/<name>.yaml``), a path or ``"pkg://<package>"``.
        """
        check(name.isidentifier(), f"an algorithm name must be an identifier, got {name!r}")
        where = None if conf is None else _search_path_entry(conf)
        self._entries[name] = _Entry(config, builder, where)

    def config(self, name: str) -> type:
        """The config dataclass of algorithm ``name``."""
        entry = self._entry(name)
        entry.config = _resolve(entry.config)
        return entry.config

    def builder(self, name: str) -> Callable[..., Any]:
        """The builder (usually the class) of algorithm ``name``: imports its module."""
        entry = self._entry(name)
        entry.builder = _resolve(entry.builder)
        return entry.builder

    def search_path(self) -> list[str]:
        """The config folders of every algorithm (plug-ins imported), as Hydra search path
        entries, each once."""
        self._import_plugins(None)
        return list(dict.fromkeys(e.conf for e in self._entries.values() if e.conf))

    def conf_folders(self) -> list[Traversable]:
        """rlpipe's config folder (``rlpipe.conf``), then the plug-ins' (:meth:`search_path`)."""
        return [importlib.resources.files("rlpipe.conf"), *map(_folder, self.search_path())]

    def conf_file(self, group: str, option: str) -> Traversable | None:
        """The first ``<group>/<option>.yaml`` of :meth:`conf_folders` (rlpipe's first), or None."""
        paths = (folder / group / f"{option}.yaml" for folder in self.conf_folders())
        return next((path for path in paths if path.is_file()), None)

    def conf_options(self, group: str) -> list[str]:
        """The options that the YAML files of :meth:`conf_folders` give config ``group``."""
        folders = [folder / group for folder in self.conf_folders()]
        return sorted(
            {
                path.name[: -len(".yaml")]
                for folder in folders
                if folder.is_dir()
                for path in folder.iterdir()
                if path.name.endswith(".yaml")
            }
        )

    def _entry(self, name: str) -> _Entry:
        if name not in self:
            check_choice(name, "algo.name", self)
        return self._entries[name]

    def _import_plugins(self, name: str | None) -> None:
        """Import the ``RLPIPE_PLUGINS`` modules (once), then the entry points named ``name``
        (None: all) that no registration has claimed yet."""
        if not self._variable_read:
            self._variable_read = True
            for module in filter(None, os.environ.get(PLUGINS_VARIABLE, "").split(",")):
                _import_module(module.strip())
        if self._entry_points_read is None:
            return
        from importlib.metadata import entry_points  # not at import: the front door stays quick

        for point in entry_points(group=ENTRY_POINT_GROUP):
            if name in (None, point.name) and point.name not in self._entry_points_read:
                self._entry_points_read.add(point.name)
                if point.name not in self._entries:  # a call or RLPIPE_PLUGINS comes first
                    _load_entry_point(point, self._entries)
        if name is None:
            self._entry_points_read = None

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        if name not in self._entries:
            self._import_plugins(name)
        return name in self._entries

    def __getitem__(self, name: str) -> tuple[type, Callable[..., Any]]:
        if name not in self:
            raise KeyError(name)
        return self.config(name), self.builder(name)

    def __iter__(self) -> Iterator[str]:
        self._import_plugins(None)
        return iter(list(self._entries))

    def __len__(self) -> int:
        self._import_plugins(None)
        return len(self._entries)


class PluginError(RlpipeError):
    """A plug-in that does not load, or an algorithm no plug-in provides."""


class UnknownAlgorithm(PluginError):
    """A run's config names an algorithm that is not registered in this process."""

    def __init__(self, name: str) -> None:
        super().__init__(
            f"algorithm {name!r} is not registered in this process; to make it importable, "
            f"{how_to_register(name)}"
        )


def _import_module(module: str) -> None:
    """Import a module named in ``RLPIPE_PLUGINS``; one line if it is not found."""
    try:
        importlib.import_module(module)
    except ImportError as err:
        raise PluginError(
            f"{PLUGINS_VARIABLE} names module {module!r}, which does not import ({err}); put "
            f"its folder on PYTHONPATH, or correct {PLUGINS_VARIABLE}"
        ) from err


def _load_entry_point(point: Any, entries: Mapping[str, _Entry]) -> None:
    """Load an ``rlpipe.algorithms`` entry point, which must register the algorithm it is
    named after; one line if its module is not found or does not."""
    package = point.dist.name if point.dist else "its package"
    where = f"the {ENTRY_POINT_GROUP} entry point {point.name} = {point.value!r} of {package}"
    try:
        point.load()
    except ImportError as err:
        raise PluginError(
            f"{where} does not import ({err}); reinstall {package}, or uninstall it"
        ) from err
    if point.name not in entries:
        raise PluginError(
            f"{where} registers no algorithm {point.name!r}: its module must call "
            f"rlpipe.register({point.name!r}, ...)"
        )


ALGORITHMS = Registry()
for _name, _config, _builder in (
    ("dqn", "DQNConfig", "rlpipe.algos.dqn:DQN"),
    ("reinforce", "ReinforceConfig", "rlpipe.algos.reinforce:Reinforce"),
    ("ars", "ARSConfig", "rlpipe.algos.ars.algorithm:ARS"),
    ("mbrl", "MBRLConfig", "rlpipe.algos.mbrl.algorithm:MBRL"),
    ("ppo", "PPOConfig", "rlpipe.algos.ppo:PPO"),
    ("sac", "SACConfig", "rlpipe.algos.sac:SAC"),
):
    ALGORITHMS.register(_name, f"rlpipe.algos.configs:{_config}", _builder)
register = ALGORITHMS.register


def config_class(name: Any) -> type | None:
    """The config class of a registered algorithm ``name``, or None (not a registered name)."""
    return ALGORITHMS.config(name) if name in ALGORITHMS else None
