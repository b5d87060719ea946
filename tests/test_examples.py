"""The shipped examples (``examples/``) run: each from Python with a tiny budget, and the
command lines their docstrings give, then ``rlpipe.evaluate`` on what they trained."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
import torch
import yaml
from conftest import run_module

from rlpipe import RlpipeError, evaluate, load_run, make_env

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = ["progress=false", "eval_episodes=2"]


@pytest.fixture
def examples(monkeypatch):
    """Import an example module by name (``examples/`` on sys.path, as PYTHONPATH would put it)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    return importlib.import_module


def evaluated(run_dir: Path, *extra: str) -> str:
    """``python -m rlpipe.evaluate run_dir=...`` with ``examples/`` importable; its last line."""
    done = run_module(
        "rlpipe.evaluate",
        f"run_dir={run_dir}",
        "episodes=2",
        *extra,
        cwd=run_dir.parent,
        pythonpath=EXAMPLES,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


def test_dueling_network_from_python_trains_and_loads_back(examples, tmp_path):
    dueling = examples("dueling_dqn")
    net = dueling.DuelingQNet(4, 2, hidden=16)
    q = net(torch.randn(5, 4))
    advantage = net.advantage(net.trunk(torch.zeros(1, 4)))
    assert q.shape == (5, 2) and torch.isfinite(advantage).all()
    result = dueling.main(total_frames=2048, run_dir=str(tmp_path / "run"))
    assert result.frames == 2048
    with pytest.raises(RlpipeError, match=r"network was a Python object \(dueling_dqn.Duel"):
        load_run(tmp_path / "run")  # config.yaml records the class, not the object
    run = load_run(tmp_path / "run", network=dueling.DuelingQNet(4, 2))  # an object: passed again
    env = make_env(run.cfg.env, num_envs=2, seed=1)
    assert len(evaluate(run.algo.policy, env, 2).returns) == 2
    env.close()
    run.algo.close()


def trained(run_dir: Path, *overrides: str) -> dict:
    """``python -m rlpipe <overrides>`` into ``run_dir`` with ``examples/`` importable; the
    ``config.yaml`` it wrote."""
    done = run_module(
        "rlpipe",
        *overrides,
        *TINY,
        f"hydra.run.dir={run_dir}",
        cwd=run_dir.parent,
        pythonpath=EXAMPLES,
    )
    assert done.returncode == 0, done.stderr
    return yaml.safe_load((run_dir / "config.yaml").read_text())


def test_dueling_network_from_the_command_line(tmp_path):
    run_dir = tmp_path / "run"
    stored = trained(
        run_dir,
        "+experiment=dqn_cartpole",
        "total_frames=2048",
        "eval_every=1024",
        "algo.network._target_=dueling_dqn.DuelingQNet",
        "algo.network.hidden=16",
    )
    assert stored["algo"]["network"] == {"_target_": "dueling_dqn.DuelingQNet", "hidden": 16}
    # the spec imports code: refused until trusted, then rebuilt from config.yaml
    refused = run_module("rlpipe.evaluate", f"run_dir={run_dir}", cwd=tmp_path)
    assert refused.returncode == 2
    assert "algo.network._target_='dueling_dqn.DuelingQNet'" in refused.stderr
    assert "allow_env_import=true" in refused.stderr
    assert "return" in evaluated(run_dir, "allow_env_import=true")


def test_layernorm_ars_policy_trains_and_evaluates_from_the_cli(examples, tmp_path):
    layernorm = examples("ars_layernorm")
    run_dir = tmp_path / "run"
    result = layernorm.main(total_frames=3000, run_dir=str(run_dir))
    assert result.frames >= 3000
    stored = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert stored["algo"]["network"]["_target_"] == "ars_layernorm.LayerNormMLP"
    run = load_run(run_dir, allow_env_import=True)
    assert any(isinstance(m, torch.nn.LayerNorm) for m in run.algo.policy.modules())
    run.algo.close()
    assert "on CartPole-v1: return" in evaluated(run_dir, "allow_env_import=true")


def test_custom_env_module_trains_from_the_cli(tmp_path):
    run_dir = tmp_path / "run"
    stored = trained(
        run_dir,
        "env=gym",
        "env.id=custom_env:GoalLine-v0",
        "env.kwargs.goal=0.5",
        "total_frames=400",
        "eval_every=200",
    )
    assert stored["env"]["id"] == "custom_env:GoalLine-v0"
    assert stored["env"]["kwargs"] == {"goal": 0.5}
    assert "GoalLine-v0: return" in evaluated(run_dir, "allow_env_import=true")


def test_custom_env_module_missing_is_one_line(tmp_path):
    done = run_module(
        "rlpipe",
        "env=gym",
        "env.id=custom_env:GoalLine-v0",
        *TINY,
        f"hydra.run.dir={tmp_path / 'run'}",
        cwd=tmp_path,  # examples/ not on PYTHONPATH
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "'custom_env'" in lines[0] and "PYTHONPATH" in lines[0]


def test_every_example_is_listed_in_the_docs():
    listed = (EXAMPLES.parent / "docs" / "api.md").read_text()
    files = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert files == ["ars_layernorm.py", "custom_env.py", "dueling_dqn.py"]
    assert all(f"(../examples/{name})" in listed for name in files)
