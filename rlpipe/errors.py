"""User-facing errors: one clear line, a non-zero exit, no traceback wall."""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable
from typing import Any


class RlpipeError(ValueError):
    """A problem the user can fix (bad config value, unknown env, unsupported action space).

    The command-line entry points print ``rlpipe: error: <message>`` and exit with code 2.
    """


class RunDirConflict(RlpipeError):
    """The run dir belongs to another run, or another process is writing it."""


def check(condition: bool, message: str) -> None:
    """Raise :class:`RlpipeError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise RlpipeError(message)


# rule name -> (test, what a value must be)
RULES: dict[str, tuple[Callable[[Any], bool], str]] = {
    "positive": (lambda v: math.isfinite(v) and v > 0, "must be a finite number > 0"),
    "at_least_one": (lambda v: v >= 1, "must be >= 1"),
    "non_negative": (lambda v: math.isfinite(v) and v >= 0, "must be a finite number >= 0"),
    "discount": (lambda v: 0 < v <= 1, "must be in (0, 1]"),
    "fraction": (lambda v: 0 <= v < 1, "must be in [0, 1)"),
    "sizes": (lambda v: all(h >= 1 for h in v), "must be positive"),
    "optional_at_least_one": (lambda v: v is None or v >= 1, "must be >= 1 or null"),
    "seed": (lambda v: 0 <= v <= 2**32 - 1, "must be in [0, 2**32 - 1]"),
    # checked with the config, before torch loads: a typo fails at once, not after the imports
    "device": (
        lambda v: isinstance(v, str) and re.fullmatch(r"auto|cpu|cuda(:\d+)?", v) is not None,
        "must be auto, cpu, cuda or cuda:N",
    ),
}


def check_fields(obj: object, prefix: str, **rules: Iterable[str]) -> None:
    """Check ``obj``'s fields named under each rule of :data:`RULES`, e.g.
    ``check_fields(cfg, "algo.", positive=("lr",), discount=("gamma",))``; the error names the
    key as ``<prefix><field>``."""
    for rule, names in rules.items():
        test, requirement = RULES[rule]
        for name in names:
            value = getattr(obj, name)
            check(test(value), f"{prefix}{name} {requirement}, got {value}")


def check_choice(value: Any, key: str, choices: Iterable[Any]) -> None:
    """``value`` must be one of ``choices``; the error names ``key`` and lists them."""
    choices = tuple(choices)
    check(value in choices, f"{key} must be one of {', '.join(map(str, choices))}; got {value!r}")
