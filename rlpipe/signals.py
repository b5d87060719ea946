"""SIGINT and SIGTERM while a run trains: the first asks it to stop after the current
iteration (it checkpoints), a second stops the process at once."""

from __future__ import annotations

import signal
from collections.abc import Callable
from types import TracebackType
from typing import Any

from tqdm.auto import tqdm


class StopSignals:
    """Within ``with``: SIGINT/SIGTERM set :attr:`received` (and call ``on_stop``) instead of
    ending the process; a second one ends it as the signal would. The previous handlers come back
    at exit. Outside the main thread signals are left alone."""

    def __init__(self, on_stop: Callable[[], None]) -> None:
        self.on_stop = on_stop
        self.received: int | None = None  # the first signal's number
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopSignals:
        try:
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)
        except ValueError:  # not the main thread: leave signals alone
            pass
        return self

    def __exit__(self, *exc: type[BaseException] | BaseException | TracebackType | None) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous = {}

    def _handle(self, signum: int, frame: Any) -> None:
        if self.received is not None:  # a second signal: stop now
            signal.signal(signum, signal.SIG_DFL)
            signal.raise_signal(signum)
        self.received = signum
        self.on_stop()
        tqdm.write(f"rlpipe: {signal.Signals(signum).name}: checkpointing after this iteration")
