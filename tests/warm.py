"""``python -m rlpipe`` for tests, forked from a server that has imported torch and the rest.

A fresh interpreter spends ~7 s importing torch, tensordict, TorchRL and Hydra before a tiny run
starts (2 slow cores); a process forked from a server that imported them once starts in ~0.2 s.
The forked run is a process of its own: its own argv, cwd, environment, stdout and stderr
(files), its own session (so that every process of the run can be found and killed), and it
imports rlpipe itself, so module-level state (``RLPIPE_FAULT``, the registry) is read afresh.
Tests of the entry point itself (``python -m`` startup, ``--help`` speed, import-time settings)
run a fresh interpreter (``run_module(..., fresh=True)``).
"""

from __future__ import annotations

import atexit
import functools
import multiprocessing
import os
import runpy
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
from pathlib import Path
from unittest import mock

# what the server imports once; rlpipe itself is imported by each run
PRELOAD = [
    "numpy",
    "torch",
    "tensordict",
    "torchrl.collectors",
    "torchrl.data",
    "torchrl.envs",
    "torchrl.modules",
    "torchrl.objectives",
    "hydra",
    "gymnasium",
    "matplotlib.pyplot",
]
TAG_VAR = "RLPIPE_TEST_TAG"  # the tests' tag of a run's processes (tests/fault_harness.py)
SESSIONS: dict[str | None, list[int]] = {}  # TAG_VAR's value -> the sessions of its runs


@functools.cache
def _context() -> multiprocessing.context.ForkServerContext:
    """The fork server, started on first use from an environment without the tests' variables
    (its environment is every forked run's ``/proc/<pid>/environ``)."""
    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(PRELOAD)
    import rlpipe  # noqa: F401  its import sets TorchRL's log level, read as TorchRL loads

    clean = {k: v for k, v in os.environ.items() if not k.startswith("RLPIPE_")}
    with mock.patch.dict(os.environ, clean, clear=True):
        from multiprocessing import forkserver

        forkserver.ensure_running()
    return context


def run(
    module: str, args: list[str], *, cwd: Path, env: dict[str, str], timeout: float
) -> subprocess.CompletedProcess:
    """``python -m module args...`` in ``cwd`` with ``env`` as its whole environment, forked from
    the server; its output as text, like ``subprocess.run(..., capture_output=True, text=True)``
    (on timeout, every process of its session is killed and ``TimeoutExpired`` raised)."""
    command = [sys.executable, "-m", module, *args]
    with tempfile.TemporaryDirectory(prefix="rlpipe-warm-") as folder:
        out, err = Path(folder) / "stdout", Path(folder) / "stderr"
        proc = _context().Process(target=_main, args=(module, args, str(cwd), env, out, err))
        proc.start()
        SESSIONS.setdefault(env.get(TAG_VAR), []).append(proc.pid)
        proc.join(timeout)
        if proc.exitcode is None:
            _kill_session(proc.pid)
            proc.join()
            raise subprocess.TimeoutExpired(command, timeout, out.read_text(), err.read_text())
        return subprocess.CompletedProcess(command, proc.exitcode, out.read_text(), err.read_text())


def _kill_session(sid: int) -> None:
    """SIGKILL every process of session ``sid`` (a forked run and whatever it started)."""
    try:
        os.killpg(sid, signal.SIGKILL)
    except ProcessLookupError:
        pass


def _main(
    module: str, args: list[str], cwd: str, env: dict[str, str], out: Path, err: Path
) -> None:
    """The forked process: becomes ``python -m module args...`` and exits as it would."""
    os.setsid()
    for fd, path in ((1, out), (2, err)):
        opened = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.dup2(opened, fd)
        os.close(opened)
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    sys.path[0:0] = [cwd]  # ``-m``'s first import folder
    # a main process, as `python -m` is, that starts and waits on children of its own
    current = multiprocessing.current_process()
    current._identity, current._name, current._parent_pid = (), "MainProcess", None
    multiprocessing.process._parent_process = None
    code: int = 0
    try:
        sys.argv = [module, *args]
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exit_:
        if exit_.code is None or isinstance(exit_.code, int):
            code = exit_.code or 0
        else:
            print(exit_.code, file=sys.stderr)
            code = 1
    except BaseException:
        traceback.print_exc()
        code = 1
    threading._shutdown()  # as the interpreter does on exit: threads, then atexit handlers
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
