"""Files written so that a crash never leaves them half-written, and the writability probe the
commands run before long work."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path

from rlpipe import faults
from rlpipe.errors import RlpipeError

TEMP_SUFFIX = ".tmp"  # <dir>/.<name>.tmp: a new content being written


def temp_path(path: Path) -> Path:
    """Where :func:`write_atomic` writes ``path``'s new content before renaming it."""
    return path.with_name(f".{path.name}{TEMP_SUFFIX}")


def write_atomic(path: str | Path, data: bytes, *, fault: str | None = None) -> None:
    """Replace ``path``'s content with ``data`` (a temporary copy, fsynced, renamed over it, the
    directory fsynced): a crash leaves the old file or the new one, and the file keeps its
    permissions. ``fault`` names the :mod:`rlpipe.faults` point between the copy and the rename.
    A failed write removes the copy and raises the ``OSError``.
    """
    path = Path(path)
    temp = temp_path(path)
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        if path.exists():
            os.fchmod(fd, stat.S_IMODE(path.stat().st_mode))
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
