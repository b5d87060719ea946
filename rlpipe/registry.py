"""The algorithm registry: ``algo`` option name -> config class and builder, each imported when
first asked for. Imports no torch: the command line lists and checks configs before any
algorithm module (and torch) loads, and an algorithm's module loads only once it is chosen.

Built-in entries name their classes as ``"module:attribute"`` strings; :func:`register` adds
an algorithm from outside the package, as classes or as such strings.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

from rlpipe.errors import check, check_choice


@dataclass
class _Entry:
    config: type | str  # the config dataclass, or "module:attribute" naming it
    builder: Callable[..., Any] | str  # builder(env_factory, cfg, device=..., network=...)


def _resolve(target: Any) -> Any:
    if not isinstance(target, str):
        return target
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


class Registry(Mapping):
    """``name -> (config class, builder)``, as a read-only mapping whose values import the
    builder's module on access; :meth:`config` imports only the config's."""

    def __init__(self) -> None:
        self._entries: dict[str, _Entry] = {}

    def register(self, name: str, config: type | str, builder: Callable[..., Any] | str) -> None:
        """Add (or replace) algorithm ``name`` in the registry.

        ``config``: its config dataclass (an ``AlgoConfig`` subclass whose ``name`` defaults to
        ``name``); ``builder``: what builds it, ``builder(env_factory, cfg, device=...,
        network=...)``; each an object or a ``"module:attribute"`` string imported on first use.
        """
        check(name.isidentifier(), f"an algorithm name must be an identifier, got {name!r}")
        self._entries[name] = _Entry(config, builder)

    def config(self, name: str) -> type:
        """The config dataclass of algorithm ``name``."""
        check_choice(name, "algo.name", self._entries)
        entry = self._entries[name]
        entry.config = _resolve(entry.config)
        return entry.config

    def builder(self, name: str) -> Callable[..., Any]:
        """The builder (usually the class) of algorithm ``name``: imports its module."""
        check_choice(name, "algo.name", self._entries)
        entry = self._entries[name]
        entry.builder = _resolve(entry.builder)
        return entry.builder

    def __getitem__(self, name: str) -> tuple[type, Callable[..., Any]]:
        if name not in self._entries:
            raise KeyError(name)
        return self.config(name), self.builder(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self._entries)

    def __len__(self) -> int:
        return len(self._entries)


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
    return ALGORITHMS.config(name) if isinstance(name, str) and name in ALGORITHMS else None
