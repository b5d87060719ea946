"""rlpipe's own lines (resume notices, warnings, the summary line): printed on the console, which
may close under a command without ending it, and recorded in the run's log file,
``<run dir>/rlpipe.log``, whose handler writes the file itself, never through a link."""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from rlpipe.files import NotOwnFile, open_append, set_aside, strange

# the command line's Hydra logging config sends this logger to the run's log file only
RUN_LOG = logging.getLogger("rlpipe.run")
RUN_LOG.addHandler(logging.NullHandler())  # from Python: printed, not logged again
RUN_LOG.propagate = False


def say(line: str, *, err: bool = False) -> None:
    """Print ``line`` (on stderr with ``err``; a progress bar stays whole) and record it in the
    run's log file when the command line has one."""
    from tqdm.auto import tqdm  # here: the command line's front door stays light

    tqdm.write(line, file=sys.stderr if err else sys.stdout)
    RUN_LOG.log(logging.WARNING if err else logging.INFO, line)


def warn(message: str | None) -> None:
    """``rlpipe: warning: <message>`` on stderr and in the run's log (None: nothing)."""
    if message is not None:
        say(f"rlpipe: warning: {message}", err=True)


class RunLogHandler(logging.FileHandler):
    """Hydra's ``file`` handler for ``rlpipe.log`` (``conf/config.yaml``): opens the file itself
    (a link, special file or hard link in its place is set aside first, with a warning), and,
    with ``delay: true``, only at the first line, so a run that fails before it logs anything
    leaves no log file."""

    def _open(self) -> IO[str]:
        path = Path(self.baseFilename)
        try:
            return open_append(path, "a", encoding=self.encoding or "utf-8", errors=self.errors)
        except NotOwnFile:
            what = strange(path) or "a file with another name too (a hard link)"
            aside = set_aside(path)
            print(
                f"rlpipe: warning: {path} was {what}, not this run's log: moved it to {aside}",
                file=sys.stderr,
            )
            return open_append(path, "a", encoding=self.encoding or "utf-8", errors=self.errors)


class _Console:
    """``sys.stdout`` or ``sys.stderr`` whose reader may leave (``| head``, a pager quit): from
    then on what is written goes to the null device, not to a ``BrokenPipeError``."""

    def __init__(self, stream: IO[str]) -> None:
        self.stream = stream

    def write(self, text: str) -> int:
        try:
            return self.stream.write(text)
        except BrokenPipeError:
            self._reader_gone()
            return len(text)

    def flush(self) -> None:
        try:
            self.stream.flush()
        except BrokenPipeError:
            self._reader_gone()

    def _reader_gone(self) -> None:
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, self.stream.fileno())
        os.close(null)

    def __getattr__(self, name: str) -> Any:  # isatty, fileno, encoding, ...: the stream's
        return getattr(self.stream, name)


@contextmanager
def console_may_close() -> Iterator[None]:
    """Within: a console that closes ends nothing: a run trains on (its lines still reach
    rlpipe.log), a command finishes its work; outside, the streams are as they were."""
    saved = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = (None if s is None else _Console(s) for s in saved)
    try:
        yield
    finally:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
        sys.stdout, sys.stderr = saved
