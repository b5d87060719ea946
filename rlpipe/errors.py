"""User-facing errors: one clear line, a non-zero exit, no traceback wall."""

from __future__ import annotations


class RlpipeError(ValueError):
    """A problem the user can fix (bad config value, unknown env, unsupported action space).

    The command-line entry points print ``rlpipe: error: <message>`` and exit with code 2.
    """


def check(condition: bool, message: str) -> None:
    """Raise :class:`RlpipeError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise RlpipeError(message)
