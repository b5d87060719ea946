"""ARS's rollout workers: the same search in worker processes as in one, when this process
rolls out instead, workers started only to train, and no worker outliving a killed run."""

from __future__ import annotations

import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from functools import partial
from types import SimpleNamespace

import pytest
import torch
from test_ars import CARTPOLE, PENDULUM
from test_ars_search import small_search

from rlpipe.algos import ARS, ARSConfig
from rlpipe.algos.ars import backends
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError


@pytest.mark.parametrize("workers", [1, 2])
def test_each_iteration_clips_rewards_at_the_bound_it_is_given(workers):
    """The clip bound travels with every roll_out (ARS anneals it between iterations), to this
    process's envs and to the workers alike: CartPole's +1 a step clipped at 0.5 counts 0.5."""
    search = small_search(seed=5, workers=workers)
    try:
        search.start()
        population = 2 * search.num_directions
        flat, seeds = search.theta.expand(population, -1).clone(), torch.arange(population)
        for bound, per_step in ((None, 1.0), (0.5, 0.5), (None, 1.0)):
            results = [r for _, r in search._backend.roll_out(flat, seeds, bound)]
            lengths = torch.cat([r.lengths for r in results]).double()
            assert torch.equal(torch.cat([r.raw_returns for r in results]), lengths)
            assert torch.equal(torch.cat([r.returns for r in results]), per_step * lengths)
    finally:
        search.close()


@pytest.mark.parametrize(
    ("short", "here"),
    [(0.0, False), (math.inf, True)],
    ids=["workers-every-iteration", "this-process-timed-too"],
)
def test_worker_processes_give_the_same_search_as_one_process(monkeypatch, short, here):
    """Each member's episode seed comes from the search, whichever process rolls it out: the
    workers, or this process (timed against the workers when iterations are short)."""
    monkeypatch.setattr(backends, "SHORT_SECONDS", short)
    thetas, counts = [], []
    for workers in (1, 2):
        search = small_search(seed=5, workers=workers)
        try:
            before = search.theta
            # several iterations: a worker gets the policy state with its first chunk of each
            steps = [search.step()["env_steps"] for _ in range(3)]
            if workers == 2:  # the first iteration in the workers, the second as the case says
                assert ("here" in search._backend._timed) is here
        finally:
            search.close()
        assert not torch.equal(before, search.theta)
        assert search.normalizer.count == sum(steps) > 18
        thetas.append(search.theta)
        counts.append(steps)
    assert torch.allclose(thetas[0], thetas[1]) and counts[0] == counts[1]


def test_workers_or_this_process_by_seconds_per_env_step():
    """The faster way per env step rolls out; the slower is timed again once the work has
    changed RETIME_FACTOR-fold; long iterations always go to the workers."""
    short = backends.SHORT_SECONDS

    def way(steps: int, **timed: tuple[float, int]) -> str:
        pool = SimpleNamespace(_timed=timed, _steps=steps)
        return backends._Processes._way(pool)

    assert way(0) == "pool"  # nothing timed yet
    assert way(100, pool=(short / 2, 100)) == "here"  # short: this process is timed too
    assert way(100, pool=(short * 2, 100)) == "pool"
    # this process is faster per step, though its iteration (more steps) took longer
    fast_here = {"pool": (short / 5, 100), "here": (short / 4, 150)}
    assert way(150, **fast_here) == "here"
    assert way(int(100 * backends.RETIME_FACTOR) - 1, **fast_here) == "here"
    assert way(int(100 * backends.RETIME_FACTOR), **fast_here) == "pool"  # the work has doubled
    assert way(2_000, **fast_here) == "pool"  # 2,000 steps here would take over SHORT_SECONDS
    fast_pool = {"pool": (short / 4, 200), "here": (short / 3, 200)}
    assert way(200, **fast_pool) == "pool"
    assert way(90, **fast_pool) == "here"  # the work has halved since this process was timed


def test_building_ars_starts_no_workers_until_it_trains():
    """``load_run`` builds a run's algorithm only to hold its policy: that spawns nothing."""
    before = set(multiprocessing.active_children())
    algo = ARS(partial(make_env, CARTPOLE), ARSConfig(workers=2))
    assert set(multiprocessing.active_children()) == before
    algo.close()  # nothing started, nothing to stop
    assert set(multiprocessing.active_children()) == before
    algo = ARS(partial(make_env, CARTPOLE), ARSConfig(workers=2))
    try:
        metrics = algo.train_step()
        assert len(set(multiprocessing.active_children()) - before) == 2
    finally:
        algo.close()
    assert metrics["train/env_steps"] == algo.frames > 0 and algo.iterations == 1
    assert set(multiprocessing.active_children()) == before


def _train_until_killed(conn, variant: str) -> None:
    """The main process of a run, forked from the test process (which has imported everything):
    ARS with two workers, whose pids it sends once they are up, trains until killed."""
    if variant == "spawn":
        backends._start_method = lambda: "spawn"
    elif variant == "fork-pipes-only":  # no PR_SET_PDEATHSIG: only EOF on the pipes
        backends._die_with_parent = lambda parent_pid: True
    elif variant == "fork-prctl-only":  # workers keep the inherited pipe ends: only the kernel
        backends._PARENT_ENDS = _Forgetful()
    cfg = ARSConfig(num_directions=4, num_best=4, episode_length=200, workers=2)
    algo = ARS(partial(make_env, PENDULUM, seed=0), cfg)
    algo.search.start()
    conn.send([proc.pid for proc in multiprocessing.active_children()])
    while True:
        algo.train_step()


class _Forgetful(set):
    """A set that keeps nothing."""

    def add(self, item: object) -> None:
        pass


def _start_time(pid: int) -> str | None:
    """``pid``'s start time (with the pid, a process's identity); None once it is gone (a
    zombie counts as gone: it holds no memory, and init reaps it)."""
    try:
        with open(f"/proc/{pid}/stat") as file:
            stat = file.read().rpartition(")")[2].split()
    except OSError:
        return None
    return None if stat[0] in ("Z", "X") else stat[19]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="forks, reads /proc")
@pytest.mark.parametrize(
    # spawned workers import torch & co. afresh: slow, in the fault-injection suite
    "variant",
    [
        "fork",
        "fork-pipes-only",
        "fork-prctl-only",
        pytest.param("spawn", marks=pytest.mark.faults),
    ],
)
def test_workers_exit_when_the_main_process_is_killed(variant):
    """SIGKILL of the main process leaves no worker behind: each worker sees EOF on its pipe
    (it holds no other end of any pipe) and the kernel kills it with its parent (prctl)."""
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    main = ctx.Process(target=_train_until_killed, args=(send, variant))
    main.start()
    send.close()
    try:
        assert receive.poll(120), "the workers did not start"
        workers = {pid: _start_time(pid) for pid in receive.recv()}
        assert len(workers) == 2 and None not in workers.values()
        time.sleep(0.5)  # mid-iteration
    finally:
        main.kill()
        main.join()
    deadline = time.monotonic() + 5
    while True:
        left = [pid for pid, start in workers.items() if _start_time(pid) == start]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    for pid in left:  # the same processes (pid and start time): do not leave them behind
        os.kill(pid, signal.SIGKILL)
    assert not left, f"workers {left} outlived the killed main process"


def test_a_killed_worker_stops_training_with_one_line(monkeypatch):
    """A worker killed mid-training (OOM killer, kill -9) raises one RlpipeError line in the
    main process within seconds; close() then neither raises nor hangs."""
    monkeypatch.setattr(backends, "SHORT_SECONDS", 0.0)  # every iteration in the workers
    before = set(multiprocessing.active_children())
    cfg = ARSConfig(num_directions=4, num_best=4, episode_length=200, workers=2)
    algo = ARS(partial(make_env, PENDULUM, seed=0), cfg)
    try:
        algo.train_step()
        workers = list(set(multiprocessing.active_children()) - before)
        assert len(workers) == 2
        victim, killed_at = workers[0], []

        def kill() -> None:
            killed_at.append(time.monotonic())
            os.kill(victim.pid, signal.SIGKILL)

        timer = threading.Timer(0.3, kill)
        timer.start()
        with pytest.raises(RlpipeError) as error:
            while not killed_at or time.monotonic() < killed_at[0] + 10:
                algo.train_step()
        raised_at = time.monotonic()
        timer.join()
        assert raised_at - killed_at[0] < 5
        message = str(error.value)
        assert f"ARS rollout worker (pid {victim.pid}) died: killed by SIGKILL" in message
        assert "resume=" in message and "\n" not in message
        with pytest.raises(RlpipeError, match="worker"):  # the pool is not used again
            algo.train_step()
    finally:
        start = time.monotonic()
        algo.close()
        assert time.monotonic() - start < 5
    assert set(multiprocessing.active_children()) == before  # the other worker is stopped too
