"""A run dir's lock: one training process per run dir at a time, its PID in the lock file (an
``fcntl`` lock, which the OS drops with the process however it dies). The lock file is only ever
a regular file of the run dir's own: a link, special file or hard link found in its place is set
aside, never written through."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rlpipe.console import warn
from rlpipe.errors import RunDirConflict
from rlpipe.files import NotOwnFile, open_regular, set_aside, strange


@contextmanager
def locked(directory: Path, name: str) -> Iterator[None]:
    """Hold ``directory/name`` locked (the directory is made if missing): a second process gets
    :class:`RunDirConflict` naming the holder's PID; an ``OSError`` means it cannot be written."""
    directory.mkdir(parents=True, exist_ok=True)
    fd = _open(directory / name)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            raise RunDirConflict(
                f"{directory} is in use by another rlpipe process (pid {holder}); wait for it "
                "to end or pick another run dir (hydra.run.dir=<dir>)"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def _open(path: Path) -> int:
    """The lock file's descriptor, read-write; what is not a lock file of the dir's own (a link,
    a FIFO, a directory, a file with a second name) is set aside first, with a warning."""
    try:
        fd = open_regular(path, os.O_RDWR | os.O_CREAT)
    except NotOwnFile:
        what = strange(path)
    else:
        if os.fstat(fd).st_nlink == 1:
            return fd
        os.close(fd)
        what = "a file with another name too (a hard link)"
    aside = set_aside(path)
    warn(
        f"{path} was {what}, not a lock file of this run dir: moved it to {aside} (nothing "
        "was written through it)"
    )
    try:
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    except FileExistsError:  # another process made it in the meantime: it is a lock file
        return open_regular(path, os.O_RDWR)
