"""The run's ``threads`` (torch's intra-op threads, process-wide) wherever a run is built: by
``train``, by a hand-built ``Runner``, by ``load_run`` and by ``make_algorithm``."""

from __future__ import annotations

import contextlib
import importlib
import os
import sys
from dataclasses import replace
from functools import partial
from pathlib import Path

import pytest
import torch

from rlpipe.algos import DQN, DQNConfig, make_algorithm
from rlpipe.cli import compose_run
from rlpipe.config import Config, EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.pipeline import load_run, train
from rlpipe.rundir import RunDir
from rlpipe.runner import Runner
from rlpipe.runtime import TORCH_THREADS

pytestmark = pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="threads=2 needs two cores")
ENV = EnvConfig(id="CartPole-v1", backend="gymnasium")
ALGO = DQNConfig(frames_per_batch=16, learning_starts=16, batch_size=16)


@pytest.fixture(autouse=True)
def threads_restored():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def two_thread_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("threads") / "run"
    cfg = Config(env=ENV, algo=ALGO, total_frames=16, eval_episodes=1, threads=2, progress=False)
    train(cfg, run_dir)
    return run_dir


def test_a_hand_built_runner_applies_the_runs_threads(tmp_path):
    algo = DQN(partial(make_env, ENV, seed=0), ALGO)
    eval_env = make_env(ENV, seed=1)
    try:
        torch.set_num_threads(2)  # what torch's default is on two cores
        Runner(algo, eval_env, RunDir(tmp_path / "a"), total_frames=16, progress=False)
        assert torch.get_num_threads() == 1  # the algorithm's record: threads=auto, 1 on CPU
        cfg = algo.run_config(total_frames=16, eval_every=0, eval_episodes=1, checkpoint_every=0)
        Runner(
            algo, eval_env, RunDir(tmp_path / "b"), total_frames=16, config=replace(cfg, threads=2)
        )
        assert torch.get_num_threads() == 2  # the config's, which config.yaml records
        Runner(
            algo, eval_env, RunDir(tmp_path / "c"), total_frames=16, config=replace(cfg, threads=0)
        )
        assert torch.get_num_threads() == TORCH_THREADS  # 0: torch's default
    finally:
        algo.close()
        eval_env.close()


def test_load_run_applies_the_runs_threads(two_thread_run):
    torch.set_num_threads(1)
    loaded = load_run(two_thread_run)
    loaded.algo.close()
    assert torch.get_num_threads() == 2
    assert loaded.cfg.threads == 2


def test_make_algorithm_applies_threads_and_checks_them():
    torch.set_num_threads(2)
    make_algorithm(partial(make_env, ENV, seed=0), ALGO).close()
    assert torch.get_num_threads() == 1  # auto
    make_algorithm(partial(make_env, ENV, seed=0), ALGO, threads=2).close()
    assert torch.get_num_threads() == 2
    with pytest.raises(RlpipeError, match="threads must be auto or a number >= 0"):
        make_algorithm(partial(make_env, ENV, seed=0), ALGO, threads="many")


@pytest.fixture
def handbuilt(monkeypatch):
    """benchmarks/handbuilt.py, imported."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "benchmarks"))
    return importlib.import_module("handbuilt")


def test_the_handbuilt_benchmark_times_each_way_of_building(handbuilt, tmp_path):
    """Each hand-built variant trains the preset (load_run's: on from a finished run) with the
    threads it stands for."""
    parent = tmp_path / "parent"
    train(compose_run(handbuilt.PRESET, "total_frames=32", *handbuilt.QUIET), parent)
    for variant, threads in (("handbuilt", 1), ("load_run", 1), ("before", TORCH_THREADS)):
        assert handbuilt.measure(variant, 32, parent) > 0
        assert torch.get_num_threads() == threads


def test_the_handbuilt_benchmark_table(handbuilt, tmp_path, monkeypatch):
    """One row per condition and variant: the median seconds and the median of the rounds'
    ratios to the command line doing the same work."""
    seconds = {
        "cli": [2.0, 4.0],
        "handbuilt": [2.2, 4.0],
        "resume": [3.0, 5.0],
        "load_run": [3.0, 6.0],
        "before": [8, 8],
    }
    rounds = {variant: iter(values) for variant, values in seconds.items()}
    monkeypatch.setattr(handbuilt, "command_line", lambda frames, run_dir: 0.0)
    monkeypatch.setattr(handbuilt, "busy", lambda on: contextlib.nullcontext())
    monkeypatch.setattr(handbuilt, "run_variant", lambda variant, *_: next(rounds[variant]))
    out = tmp_path / "BENCH.md"
    argv = ["handbuilt.py", "--rounds", "2", "--conditions", "alone", "--append", str(out)]
    monkeypatch.setattr(sys, "argv", [*argv, "--frames", "64"])
    handbuilt.main()
    rows = [line for line in out.read_text().splitlines() if line.startswith("| alone |")]
    assert rows == [
        "| alone | command line | 3.0 | 2.0, 4.0 | 1.00 |",
        "| alone | hand-built Runner | 3.1 | 2.2, 4.0 | 1.05 |",
        "| alone | command line, resume= (64 frames more) | 4.0 | 3.0, 5.0 | 1.00 |",
        "| alone | load_run + Runner (64 frames more) | 4.5 | 3.0, 6.0 | 1.10 |",
        "| alone | hand-built Runner, torch's default threads (as before) | 8.0 | 8.0, 8.0 "
        "| 3.00 |",
    ]
