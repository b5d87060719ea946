"""Files a run owns, handled so that no crash leaves one half-written and no link or special file
makes rlpipe read or write anything else: atomic writes, reads and appends that refuse symbolic
links and non-regular files, setting such entries aside, and the writability probe the commands
run before long work."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path
from typing import IO, Any

from rlpipe import faults
from rlpipe.errors import RlpipeError

TEMP_SUFFIX = ".tmp"  # <dir>/.<name>.tmp: a new content being written
REFUSED_SUFFIX = ".refused"  # <name>.refused: a link or special file set aside, never followed
# a read or an append opens only the named entry itself (no link), and never waits on a FIFO
_NO_LINK = os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)


class NotOwnFile(RlpipeError):
    """A path that should be a regular file is a link, a FIFO, a directory or another special
    file: rlpipe neither reads nor writes through it."""


def temp_path(path: Path) -> Path:
    """Where :func:`write_atomic` writes ``path``'s new content before renaming it."""
    return path.with_name(f".{path.name}{TEMP_SUFFIX}")


def strange(path: str | Path, *, directory: bool = False) -> str | None:
    """What ``path`` is, when it is neither missing nor a regular file (a real directory, with
    ``directory``): ``"a symbolic link (to X)"``, ``"a FIFO"``, ... ; None otherwise. The entry
    itself is looked at (``lstat``), never what a link points to."""
    try:
        mode = os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    if stat.S_ISLNK(mode):
        return f"a symbolic link (to {os.readlink(path)})"
    if stat.S_ISDIR(mode) if directory else stat.S_ISREG(mode):
        return None
    kinds = {
        stat.S_ISDIR: "a directory",
        stat.S_ISREG: "a file, not a directory",
        stat.S_ISFIFO: "a FIFO",
        stat.S_ISSOCK: "a socket",
        stat.S_ISCHR: "a device",
        stat.S_ISBLK: "a device",
    }
    return next((what for test, what in kinds.items() if test(mode)), "a special file")


def reached_directly(root: str | Path, path: str | Path) -> bool:
    """Whether ``path``, below ``root``, is reached from it through no symbolic link (``path``
    itself included; ``root``'s own parents may be links)."""
    real = Path(os.path.realpath(root)) / Path(path).relative_to(root)
    return Path(os.path.realpath(path)) == real


def open_regular(path: str | Path, flags: int = os.O_RDONLY, mode: int = 0o644) -> int:
    """A descriptor of ``path`` opened with ``flags``, only if it is a regular file itself: a
    symbolic link, FIFO, directory or device raises :class:`NotOwnFile` (nothing is opened
    through it, and a FIFO is never waited on)."""
    try:
        fd = os.open(path, flags | _NO_LINK, mode)
    except OSError as err:
        described = strange(path)
        if described is None:
            raise
        raise NotOwnFile(f"{path} is {described}, not a regular file") from err
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise NotOwnFile(f"{path} is {strange(path) or 'not a regular file'}, not a regular file")
    os.set_blocking(fd, True)
    return fd


def read_regular(path: str | Path) -> bytes:
    """``path``'s bytes, read only if it is a regular file itself (see :func:`open_regular`)."""
    with os.fdopen(open_regular(path), "rb") as file:
        return file.read()


def open_append(path: str | Path, mode: str = "ab", **options: Any) -> IO[Any]:
    """``path`` opened to append (created if missing; ``mode`` and ``options`` as for ``open``),
    only if it is a regular file with no other name (a hard link's other name would see the
    appended bytes): else :class:`NotOwnFile`."""
    fd = open_regular(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    if os.fstat(fd).st_nlink > 1:
        os.close(fd)
        raise NotOwnFile(f"{path} has another name (a hard link): rlpipe does not append to it")
    return os.fdopen(fd, mode, **options)


def set_aside(path: str | Path) -> Path:
    """Rename the entry ``path`` (a link is renamed, not followed) to ``<path>.refused`` (or
    ``.refused.<n>`` when that is taken) and return the new name."""
    path = Path(path)
    aside = path.with_name(path.name + REFUSED_SUFFIX)
    number = 1
    while os.path.lexists(aside):
        aside = path.with_name(f"{path.name}{REFUSED_SUFFIX}.{number}")
        number += 1
    os.rename(path, aside)
    return aside


def write_atomic(path: str | Path, data: bytes, *, fault: str | None = None) -> None:
    """Replace ``path``'s content with ``data`` (a temporary copy, fsynced, renamed over it, the
    directory fsynced): a crash leaves the old file or the new one, and the file keeps its
    permissions. The rename replaces the entry itself: a link at ``path`` is replaced, its
    target untouched, and a hard link's other name keeps the old content. ``fault`` names the
    :mod:`rlpipe.faults` point between the copy and the rename. A failed write removes the copy
    and raises the ``OSError``.
    """
    path = Path(path)
    temp = temp_path(path)
    if os.path.lexists(temp):  # a killed write's copy, or something planted there
        os.unlink(temp)
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
    try:
        old = os.lstat(path) if os.path.lexists(path) else None
        if old is not None and stat.S_ISREG(old.st_mode):
            os.fchmod(fd, stat.S_IMODE(old.st_mode))
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view) :]
        os.fsync(fd)
    except BaseException:
        os.close(fd)
        temp.unlink(missing_ok=True)
        raise
    os.close(fd)
    if fault:
        faults.point(fault)
    try:
        os.replace(temp, path)
    except BaseException:
        temp.unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)


def check_writable(path: str | Path, hint: str) -> None:
    """Fail with one line (naming ``path``, then ``hint``) unless a file can be written there.

    For commands that work long before they write: they check first. Probes by creating the
    missing directories and a temporary file in the last one; removes all it made, so a
    check writes nothing either way.
    """
    path = Path(path)
    directory = path.parent
    missing = [d for d in (directory, *directory.parents) if not d.exists()]  # deepest first
    existing = missing[-1].parent if missing else directory
    problem = None
    if path.is_dir():
        problem = "it is a directory"
    elif path.exists() and not os.access(path, os.W_OK):
        problem = "the file is read-only"
    elif not existing.is_dir():
        problem = f"{existing} is not a directory"
    else:
        try:
            directory.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=directory):
                pass
        except OSError as err:
            problem = err.strerror or str(err)
        finally:
            for made in missing:
                try:
                    made.rmdir()
                except OSError:  # not made, or someone else's files are in it now
                    pass
    if problem:
        raise RlpipeError(f"cannot write {path}: {problem}; {hint}")
