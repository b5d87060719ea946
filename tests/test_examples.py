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
from rlpipe.evaluate import main as evaluate_main

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
TINY = ["progress=false", "eval_episodes=2"]


@pytest.fixture
def examples(monkeypatch):
    """Import an example module by name (``examples/`` on sys.path, as PYTHONPATH would put it)."""
    monkeypatch.syspath_prepend(str(EXAMPLES))
    return importlib.import_module


def evaluated(run_dir: Path, *extra: str, env: dict[str, str] | None = None) -> str:
    """``python -m rlpipe.evaluate run_dir=...`` with ``examples/`` importable (``env``: more
    environment variables); its last line."""
    done = run_module(
        "rlpipe.evaluate",
        f"run_dir={run_dir}",
        "episodes=2",
        *extra,
        cwd=run_dir.parent,
        pythonpath=EXAMPLES,
        env=env,
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


def trained(run_dir: Path, *overrides: str, env: dict[str, str] | None = None) -> dict:
    """``python -m rlpipe <overrides>`` into ``run_dir`` with ``examples/`` importable (``env``:
    more environment variables); the ``config.yaml`` it wrote."""
    done = run_module(
        "rlpipe",
        *overrides,
        *TINY,
        f"hydra.run.dir={run_dir}",
        cwd=run_dir.parent,
        pythonpath=EXAMPLES,
        env=env,
    )
    assert done.returncode == 0, done.stderr
    return yaml.safe_load((run_dir / "config.yaml").read_text())


def test_dueling_network_from_the_command_line(tmp_path, capsys):
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
    with pytest.raises(SystemExit) as refused:  # in-process: examples/ is not importable here
        evaluate_main([f"run_dir={run_dir}"])
    assert refused.value.code == 2
    stderr = capsys.readouterr().err
    assert "algo.network._target_='dueling_dqn.DuelingQNet'" in stderr
    assert "allow_env_import=true" in stderr
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


# TD3 with a tiny budget: short episodes, small networks, learning from the 32nd frame on
TD3_TINY = [
    "algo=td3",
    "env=pendulum",
    "~tuned",
    "env.max_episode_steps=20",
    "algo.learning_starts=32",
    "algo.batch_size=16",
    "algo.hidden_sizes=[16,16]",
    "eval_every=50",
    "checkpoint_every=50",
]
PLUGIN = {"RLPIPE_PLUGINS": "td3"}  # the command line imports examples/td3.py


def test_td3_plugin_trains_from_python_and_loads_back(examples, registry, tmp_path):
    td3 = examples("td3")
    result = td3.main(*TD3_TINY[2:], *TINY, "total_frames=64", run_dir=str(tmp_path / "run"))
    assert result.frames == 64
    run = load_run(tmp_path / "run")
    assert isinstance(run.algo, td3.TD3) and run.algo.updates == 64 - 32 + 1
    env = make_env(run.cfg.env, num_envs=2, seed=1)
    assert len(evaluate(run.algo.policy, env, 2).returns) == 2
    env.close()
    run.algo.close()


def test_td3_plugin_trains_resumes_and_evaluates_from_the_cli(tmp_path, registry, capsys):
    run_dir = tmp_path / "run"
    stored = trained(run_dir, *TD3_TINY, "total_frames=100", env=PLUGIN)
    assert stored["algo"]["name"] == "td3" and stored["algo"]["policy_delay"] == 2
    # without the plug-in: which algorithm is missing, and how to make it importable
    with pytest.raises(SystemExit) as missing:  # in-process, where no plug-in was imported
        evaluate_main([f"run_dir={run_dir}"])
    stderr = capsys.readouterr().err
    assert missing.value.code == 2 and len(stderr.strip().splitlines()) == 1
    assert "algorithm 'td3' is not registered in this process" in stderr
    assert "RLPIPE_PLUGINS=<module>" in stderr
    resumed = run_module(
        "rlpipe",
        f"resume={run_dir}",
        *TD3_TINY,
        *TINY,
        "total_frames=150",
        cwd=tmp_path,
        pythonpath=EXAMPLES,
        env=PLUGIN,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming" in resumed.stdout and "| 150 frames |" in resumed.stdout
    assert "on Pendulum-v1: return" in evaluated(run_dir, env=PLUGIN)


def test_td3_on_discrete_actions_is_one_line(tmp_path):
    done = run_module(
        "rlpipe", "algo=td3", "env=cartpole", *TINY, cwd=tmp_path, pythonpath=EXAMPLES, env=PLUGIN
    )
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "TD3 acts in a bounded flat box of continuous actions" in lines[0]


def test_every_example_is_listed_in_the_docs():
    listed = (EXAMPLES.parent / "docs" / "api.md").read_text()
    files = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert files == ["ars_layernorm.py", "custom_env.py", "dueling_dqn.py", "td3.py"]
    assert all(f"(../examples/{name})" in listed for name in files)
