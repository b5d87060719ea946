"""Where an ARS iteration's rollouts run: this process, worker processes, or Ray actors.

Every backend rolls out the population's members (flat parameter vectors and episode seeds) on
:class:`Rollouts` units and returns their results; with several workers the population is cut
into chunks that the workers pull as they free up (episode lengths vary a lot), each rolling
out its chunk as one batch to the end and sending back only returns and observation statistics.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing as mp
import os
import signal
import sys
import time
import weakref
from multiprocessing.connection import Connection, wait
from typing import Any, Protocol

import cloudpickle
import torch
from tensordict.nn import TensorDictModuleBase

from rlpipe.algos.ars.pool import RAY_INSTALL, Pool, Shares, Units
from rlpipe.algos.ars.rollout import RolloutResult, Rollouts
from rlpipe.algos.configs import ARS_BACKENDS
from rlpipe.envs import EnvFactory
from rlpipe.errors import RlpipeError

__all__ = ["BACKENDS", "RAY_INSTALL", "Backend", "Shares", "WorkerDied", "start_backend"]

BACKENDS = ARS_BACKENDS
# iterations the workers finish faster than this are short enough for round trips to matter:
# one in this process alone is timed too, and the faster per env step wins; the slower is timed
# again once an iteration's env steps have grown or shrunk RETIME_FACTOR-fold since its timing
SHORT_SECONDS = 0.1
RETIME_FACTOR = 2.0


class Backend(Protocol):
    def roll_out(
        self, flat: torch.Tensor, seeds: torch.Tensor, reward_clip: float | None = None
    ) -> Shares:
        """Roll out member ``i`` with parameters ``flat[i]`` from episode seed ``seeds[i]``,
        training rewards clipped to ``[-reward_clip, reward_clip]`` (None: not clipped)."""
        ...

    def close(self) -> None: ...


def start_backend(
    policy: TensorDictModuleBase,
    env_factory: EnvFactory,
    population: int,
    *,
    backend: str,
    workers: int,
    seed: int,
    options: dict[str, Any],
    ray_address: str | None = None,
    ray_num_cpus: int | None = None,
) -> Backend:
    """Build the env copies (and start the workers) that roll out ``population`` members.

    ``"local"``: ``workers`` processes on this machine (1: this process, as one batch; 0: one
    per core); ``"ray"``: ``workers`` Ray actors (0: one per CPU of the cluster). Worker ``w``
    builds its envs with ``seed + w``; ``options`` are :func:`rollout`'s keyword arguments
    that stay for the whole search (``reward_clip`` comes with each ``roll_out``).
    """
    units = Units(policy, env_factory, seed, options)
    if backend == "ray":
        from rlpipe.algos.ars.ray_actors import RayActors  # Ray is an extra: imported on use

        return RayActors(units, population, workers, address=ray_address, num_cpus=ray_num_cpus)
    workers = min(workers or os.cpu_count() or 1, population)
    if workers == 1:
        return _InProcess(Rollouts(*units.args(0, population)), population)
    return _Processes(units, population, workers)


class _InProcess:
    """The rollout backend that steps the whole population as one batch in this process."""

    def __init__(self, rollouts: Rollouts, population: int) -> None:
        self.rollouts, self.members = rollouts, torch.arange(population)

    def roll_out(
        self, flat: torch.Tensor, seeds: torch.Tensor, reward_clip: float | None = None
    ) -> Shares:
        return [(self.members, self.rollouts.run(None, flat, seeds.tolist(), reward_clip))]

    def close(self) -> None:
        self.rollouts.close()


class WorkerDied(RlpipeError):
    """A rollout worker process died (killed, out of memory, crashed) during an ARS iteration."""

    def __init__(self, pid: int | None, how: str) -> None:
        super().__init__(
            f"an ARS rollout worker (pid {pid}) died: {how}; the last checkpoint is intact, "
            "resume the run with resume=<run dir>"
        )
        self.pid, self.how = pid, how


# the parent ends of the pipes of every live worker pool of this process: a forked worker
# inherits them all and closes them, so that a worker sees EOF (and exits) once its parent is
# gone, and the parent sees EOF once a worker is gone
_PARENT_ENDS: weakref.WeakSet[Connection] = weakref.WeakSet()
PR_SET_PDEATHSIG = 1  # prctl(2): the signal a process gets when its parent dies
CLOSE_SECONDS = 10.0  # how long close() lets the workers finish before it terminates them


class _Processes(Pool):
    """Worker processes on this machine, one pipe each.

    Workers never outlive this process, whatever ends it (SIGKILL included): each holds only
    its own end of its pipe, so it sees EOF once the parent is gone, and on Linux the kernel
    also kills it when the parent dies (``PR_SET_PDEATHSIG``; strictly, when the *thread* that
    started the pool ends, so start and use a pool in a thread that outlives it). A worker that
    dies raises :class:`WorkerDied` in the parent, which never waits on a dead worker; the other
    workers are stopped at once and the pool cannot be used again.

    When the workers finish an iteration in under :data:`SHORT_SECONDS` (short episodes, e.g.
    early CartPole), an iteration in this process alone, on env copies of its own, is timed too,
    and the way with the fewer seconds per env step rolls out the following ones: so workers are
    not slower than one process by their round trips. The round trips cost the same whatever the
    work, so the slower way is timed again once an iteration's env steps have changed
    :data:`RETIME_FACTOR`-fold since it was timed (episodes grow as the policy learns). Either
    way gives the same rollouts (episode seeds come with the members).
    """

    def __init__(self, units: Units, population: int, workers: int) -> None:
        super().__init__(units, population, workers)
        self._here: _InProcess | None = None  # this process's own env copies
        # "pool"/"here" -> (wall seconds, env steps) of its latest iteration
        self._timed: dict[str, tuple[float, int]] = {}
        self._steps = 0  # env steps of the latest iteration
        method = _start_method()
        ctx = mp.get_context(method)
        self._procs: dict[Connection, Any] = {}  # parent end -> its worker process
        self._failure: WorkerDied | None = None
        try:
            for w in range(workers):
                parent, child = ctx.Pipe()
                _PARENT_ENDS.add(parent)
                # a forked worker inherits every parent end (its own too) and closes them; a
                # spawned one gets only its child end (and any connection in its arguments)
                inherited = list(_PARENT_ENDS) if method == "fork" else []
                payload = cloudpickle.dumps(units.args(w, self.chunk_size))
                proc = ctx.Process(
                    target=_worker, args=(child, payload, os.getpid(), inherited), daemon=True
                )
                self.workers.append(parent)
                try:
                    proc.start()
                finally:
                    child.close()
                self._procs[parent] = proc
            # this process's own copies, built (as part of start-up) while the workers build theirs
            args = units.args(workers, population)
            self._here = _InProcess(Rollouts(*args), population)
            waiting = list(self.workers)
            while waiting:  # until every worker has built its envs
                for conn in self._wait(waiting):
                    self._collect(conn)
                    waiting.remove(conn)
        except BaseException:
            self._stop(grace=0.0)
            raise

    def roll_out(
        self, flat: torch.Tensor, seeds: torch.Tensor, reward_clip: float | None = None
    ) -> Shares:
        if self._failure is not None:
            raise self._failure
        way = self._way()
        start = time.perf_counter()
        if way == "here":
            for proc in self._procs.values():  # a dead worker stops training here too
                if not proc.is_alive():
                    raise self._died(proc)
            shares = self._here.roll_out(flat, seeds, reward_clip)
        else:
            shares = super().roll_out(flat, seeds, reward_clip)
        seconds = time.perf_counter() - start
        self._steps = max(int(sum(result.lengths.sum() for _, result in shares)), 1)
        self._timed[way] = seconds, self._steps
        return shares

    def _way(self) -> str:
        """Where the next iteration rolls out: the workers ("pool") or this process ("here")."""
        if "pool" not in self._timed:
            return "pool"
        if "here" not in self._timed:
            return "here" if self._timed["pool"][0] < SHORT_SECONDS else "pool"
        rate = {way: seconds / steps for way, (seconds, steps) in self._timed.items()}
        faster, slower = sorted(rate, key=rate.get)
        if rate[faster] * self._steps >= SHORT_SECONDS:  # long iterations: round trips don't matter
            return "pool"
        change = self._steps / self._timed[slower][1]
        return slower if max(change, 1 / change) >= RETIME_FACTOR else faster

    def _submit(self, worker: Any, *message: Any) -> Any:
        try:
            worker.send(message)
        except OSError as err:  # BrokenPipeError, ConnectionResetError: the worker is gone
            raise self._died(self._procs[worker]) from err
        return worker

    def _wait(self, handles: list[Any]) -> list[Any]:
        # a dead worker's pipe is ready (at EOF), unless something else still holds its end:
        # its process's sentinel is ready in any case
        sentinels = {proc.sentinel: proc for proc in self._procs.values()}
        ready = wait([*handles, *sentinels])
        for handle in ready:
            if handle in sentinels:
                raise self._died(sentinels[handle])
        return ready

    def _collect(self, handle: Any) -> RolloutResult:
        try:
            return handle.recv()
        except (EOFError, OSError) as err:  # the worker died (maybe mid-message)
            raise self._died(self._procs[handle]) from err

    def _died(self, proc: Any) -> WorkerDied:
        """The error for ``proc``'s death; the other workers are stopped at once."""
        proc.join(timeout=1)  # its exit code is set once it is reaped
        code = proc.exitcode
        if code is None:
            how = "its pipe broke (it was still running; it is stopped now)"
        elif code < 0:
            how = f"killed by {_signal_name(-code)}"
        else:
            how = f"exited with code {code}"
        self._failure = WorkerDied(proc.pid, how)
        self._stop(grace=0.0)
        return self._failure

    def close(self) -> None:
        if self._here is not None:
            self._here.close()
        self._stop(grace=CLOSE_SECONDS)

    def _stop(self, grace: float) -> None:
        """Ask the workers to stop (``grace`` > 0) and wait up to ``grace`` seconds for them
        all, then terminate (and at last kill) those still running. Never raises or hangs."""
        for conn in self.workers:
            if grace > 0:
                with contextlib.suppress(OSError):  # a dead worker's pipe is broken
                    conn.send(None)
            conn.close()
            _PARENT_ENDS.discard(conn)
        procs = list(self._procs.values())
        self.workers, self._procs = [], {}
        deadline = time.monotonic() + grace
        for proc in procs:
            proc.join(timeout=max(deadline - time.monotonic(), 0))
        for stop in ("terminate", "kill"):
            running = [proc for proc in procs if proc.is_alive()]
            for proc in running:
                getattr(proc, stop)()
            for proc in running:
                proc.join(timeout=1)


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def _worker(conn: Any, payload: bytes, parent_pid: int, inherited: list[Connection]) -> None:
    # Ctrl-C reaches the whole process group: the parent checkpoints and stops the workers
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for end in inherited:  # the parent's ends: only the parent may hold them
        end.close()
    if not _die_with_parent(parent_pid):
        return
    torch.set_num_threads(1)
    rollouts = Rollouts(*cloudpickle.loads(payload))
    try:
        conn.send(None)  # ready
        while (message := conn.recv()) is not None:
            conn.send(rollouts.run(*message))
    except (EOFError, BrokenPipeError, ConnectionResetError):  # the parent died without close()
        pass
    finally:
        rollouts.close()


def _die_with_parent(parent_pid: int) -> bool:
    """Have the kernel SIGKILL this process when its parent dies (Linux; elsewhere nothing);
    False if the parent (``parent_pid``) is already gone."""
    if sys.platform.startswith("linux"):
        try:
            prctl = ctypes.CDLL(None, use_errno=True).prctl
            prctl(PR_SET_PDEATHSIG, ctypes.c_ulong(signal.SIGKILL), *[ctypes.c_ulong(0)] * 3)
        except (AttributeError, OSError):  # no prctl in this libc
            pass
    return os.getppid() == parent_pid  # it may have died before the kernel watched it


def _start_method() -> str:
    """``fork`` where it is safe (a worker is up at once), else ``spawn``.

    ``spawn`` re-imports torch and TorchRL in every worker; ``fork`` cannot be used once CUDA
    is initialised in this process.
    """
    if "fork" in mp.get_all_start_methods() and not torch.cuda.is_initialized():
        return "fork"
    return "spawn"
