"""The ``compile`` key: torch.compile of the loss, the same state and resumes, and the lines a
machine without a compiler gets (``compile=true``: an error; ``auto``: a warning, eager)."""

from __future__ import annotations

import json
from functools import partial

import pytest
import torch
from conftest import BASE, run_module

from rlpipe.algos import DQNConfig, make_algorithm
from rlpipe.algos.compiling import compile_algorithm, compiler_problem
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.runtime import seed_everything

NO_CXX = {"CXX": "/nonexistent/c++"}  # $CXX names the compiler inductor would use: missing here


def _dqn(compile: bool | str = False):
    seed_everything(0)
    env = partial(make_env, EnvConfig(id="CartPole-v1", backend="gymnasium", num_envs=2), seed=0)
    # collection only in train_step (no update before 1,000 frames): the same buffer on both
    cfg = DQNConfig(frames_per_batch=64, learning_starts=1000, batch_size=32, hidden_sizes=[16])
    return make_algorithm(env, cfg, compile=compile)


def test_a_missing_compiler_is_named(monkeypatch):
    assert compiler_problem(torch.device("cpu")) is None  # g++ is here (the README's setup)
    monkeypatch.setenv("CXX", NO_CXX["CXX"])
    assert "needs a C++ compiler" in compiler_problem(torch.device("cpu"))
    with pytest.raises(RlpipeError, match="compile=true, but .* run with compile=false"):
        _dqn(compile=True)


def test_the_compiled_loss_is_the_same_loss_with_the_same_state():
    eager, compiled = _dqn(), _dqn(compile=True)
    assert "forward" in vars(compiled.loss) and "forward" not in vars(eager.loss)
    eager.train_step()
    compiled.train_step()  # the same seed, the same frames: the same buffer
    batch = eager.buffer.sample(32)
    for algo in (eager, compiled):
        algo.loss.zero_grad()
        algo.loss(batch.clone())["loss"].backward()
    for ours, theirs in zip(compiled.loss.parameters(), eager.loss.parameters(), strict=True):
        torch.testing.assert_close(ours.grad, theirs.grad)
    ours, theirs = compiled.state_dict(), eager.state_dict()
    assert ours["loss"].keys() == theirs["loss"].keys()
    compiled.load_state_dict(theirs)  # a checkpoint of either loads into the other
    for key, value in theirs["loss"].items():
        torch.testing.assert_close(compiled.loss.state_dict()[key], value)


def test_an_algorithm_without_a_loss_refuses_compile_true():
    class NoLoss:
        compiled = ()

    with pytest.raises(RlpipeError, match="has no gradient step to compile"):
        compile_algorithm(NoLoss(), strict=True)


def test_compile_true_on_ars_is_one_line(tmp_path):
    result = run_module(
        "rlpipe",
        "algo=ars",
        "compile=true",
        "total_frames=100",
        f"hydra.run.dir={tmp_path / 'r'}",
        cwd=tmp_path,
    )
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "rlpipe: error: compile=true, but ARS has no gradient step to compile: run with "
        "compile=false"
    ]


def test_compile_true_without_a_compiler_is_one_line(tmp_path):
    result = run_module(
        "rlpipe",
        *BASE,
        "compile=true",
        f"hydra.run.dir={tmp_path / 'run'}",
        cwd=tmp_path,
        env=NO_CXX,
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith("rlpipe: error: compile=true, but torch.compile on CPU needs")
    assert "compile=false" in lines[0]
    assert not (tmp_path / "run" / "checkpoints").exists()


def test_compile_auto_without_a_compiler_warns_once_and_trains(tmp_path):
    run_dir = tmp_path / "run"
    result = run_module(
        "rlpipe", *BASE, "compile=auto", f"hydra.run.dir={run_dir}", cwd=tmp_path, env=NO_CXX
    )
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]
    assert warnings == [
        "rlpipe: warning: compile=auto: torch.compile on CPU needs a C++ compiler and none was "
        "found (/nonexistent/c++); running without compiling (compile=false says so)"
    ]
    assert json.loads((run_dir / "summary.json").read_text())["frames"] == 200


@pytest.mark.parametrize(("value", "shown"), [("yes", "'yes'"), ("1", "1")])
def test_other_compile_values_are_refused(tmp_path, value, shown):
    result = run_module("rlpipe", f"compile={value}", cwd=tmp_path)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        f"rlpipe: error: compile must be true, false or auto, got {shown}"
    ]


def test_a_compiled_run_resumes_as_it_would_have_gone_on(tmp_path):
    """compile=true to 200 frames at once, and to 100 then resumed to 200: the same numbers."""
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    args = [*BASE, "compile=true", "algo.hidden_sizes=[16]"]
    assert run_module("rlpipe", *args, f"hydra.run.dir={whole}", cwd=tmp_path).returncode == 0
    first = run_module("rlpipe", *args, "total_frames=100", f"hydra.run.dir={cut}", cwd=tmp_path)
    assert first.returncode == 0, first.stderr
    again = run_module("rlpipe", *args, f"resume={cut}", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    for name in ("eval/return_mean", "train/loss"):
        rows = [(run / "metrics" / "scalars" / f"{name}.csv").read_text() for run in (whole, cut)]
        assert rows[0] == rows[1], name
