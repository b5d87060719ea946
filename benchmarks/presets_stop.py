"""Stopping benchmarks/presets.py (Ctrl-C, SIGTERM): its runs stop where they are, saved.

Each run's process starts in a session of its own, so a terminal's Ctrl-C reaches the benchmark
alone, and the benchmark sends every run exactly one SIGINT: an rlpipe run checkpoints after its
iteration and exits (a second signal would end it at once, unsaved), an SB3 run stops where it
is (its saves survive a stop at any point). The benchmark waits for them, then ends with one line
and 128 + the signal; the same command continues from what they saved. Another signal while it
waits kills the runs.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import subprocess
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Stop(BaseException):
    """SIGINT or SIGTERM reached the benchmark (raised in its main thread)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


class Stopped(Exception):
    """A run stopped, or did not start, because the benchmark is stopping."""


class Runs:
    """The processes of the benchmark's runs: started unless it is stopping, and stopped."""

    def __init__(self) -> None:
        self.lock = threading.RLock()  # re-entrant: a signal handler may kill while we stop
        self.pids: set[int] = set()
        self.stopping = False

    @contextmanager
    def starting(self) -> Iterator[None]:
        """Hold off a stop while a run's process starts; raise :class:`Stopped` if one began."""
        with self.lock:
            if self.stopping:
                raise Stopped("the benchmark is stopping")
            yield

    def call(self, command: list[str], **popen: Any) -> int:
        """``subprocess.call`` in a session of its own, asked to stop with the benchmark."""
        with self.starting():
            proc = subprocess.Popen(command, start_new_session=True, **popen)
            self.pids.add(proc.pid)
        try:
            return proc.wait()
        finally:
            with self.lock:
                self.pids.discard(proc.pid)

    def signal(self, signum: int) -> int:
        """Send ``signum`` to every running run (the spawned SB3 processes too); from now on no
        run starts. Returns how many were sent it."""
        with self.lock:
            self.stopping = True
            pids = self.pids | {p.pid for p in multiprocessing.active_children()}
            for pid in pids:
                try:
                    os.kill(pid, signum)
                except ProcessLookupError:  # it ended meanwhile
                    pass
            return len(pids)


RUNS = Runs()


def own_session() -> None:
    """In a spawned run's process: a session of its own, and SIGINT raising KeyboardInterrupt even
    where the benchmark started with it ignored (``nohup ... &``)."""
    if hasattr(os, "setsid"):  # POSIX
        os.setsid()
    signal.signal(signal.SIGINT, signal.default_int_handler)


def _raise_stop(signum: int, frame: object) -> None:
    for each in SIGNALS:  # first: a second signal, however soon, kills the runs
        if signal.getsignal(each) is _raise_stop:
            signal.signal(each, _kill_runs)
    raise Stop(signum)


def _kill_runs(signum: int, frame: object) -> None:
    RUNS.signal(signal.SIGKILL)


@contextmanager
def stop_signals() -> Iterator[None]:
    """Within: SIGINT and SIGTERM raise :class:`Stop` in the main thread, once; after that they
    kill the runs (a SIGINT ignored from the start, as under ``nohup ... &``, stays ignored)."""
    previous = {signum: signal.getsignal(signum) for signum in SIGNALS}
    for signum, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(signum, _raise_stop)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def stop_runs() -> int:
    """Ask every run to stop (SIGINT; a further SIGINT or SIGTERM, from the moment :class:`Stop`
    was raised, kills them). How many were asked."""
    return RUNS.signal(signal.SIGINT)
