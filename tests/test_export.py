"""``python -m rlpipe.export``: every algorithm's greedy policy as a file that takes the run's
actions, and its returns in a plain gymnasium loop without rlpipe; the formats; bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from functools import partial
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from conftest import assert_one_error_line, needs_extra, run_module
from tensordict.nn import TensorDictModuleBase
from test_mbrl import SMALL as SMALL_MBRL
from torch import nn
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe import (
    ARSConfig,
    Config,
    DQNConfig,
    EnvConfig,
    MBRLConfig,
    PPOConfig,
    ReinforceConfig,
    RlpipeError,
    SACConfig,
    evaluate,
    export_policy,
    greedy_policy,
    load_run,
    make_env,
    train,
)
from rlpipe.algos.mbrl import MBRL
from rlpipe.export import main
from rlpipe.greedy import FixedNoisePlanner, policy_actions

# algorithm -> env id and config of a tiny run; between them every action head: argmax of
# Q-values (DQN), most probable action (REINFORCE), normaliser + clamped Gaussian mean (PPO),
# tanh Gaussian (SAC), normaliser + argmax (ARS), the planner (MBRL)
RUNS = {
    "dqn": ("CartPole-v1", DQNConfig(learning_starts=64, batch_size=32, frames_per_batch=20)),
    "reinforce": (
        "CartPole-v1",
        ReinforceConfig(episodes_per_epoch=2, updates_per_epoch=2, batch_size=32),
    ),
    "ppo": (
        "Pendulum-v1",
        PPOConfig(frames_per_batch=100, minibatch_size=50, epochs=1, normalize_observations=True),
    ),
    "sac": (
        "Pendulum-v1",
        SACConfig(learning_starts=64, batch_size=32, frames_per_batch=20, hidden_sizes=[32, 32]),
    ),
    "ars": ("CartPole-v1", ARSConfig(num_directions=2, num_best=2, episode_length=50, workers=1)),
    "mbrl": ("Pendulum-v1", MBRLConfig(**SMALL_MBRL)),
}
SEEDS = [11, 12, 13]  # the episodes both loops run
ONNX = ("dqn", "sac")  # a discrete and a continuous policy through ONNX Runtime

# the plain loop: gymnasium and the exported file, no rlpipe (it checks that it imported none)
PLAIN_LOOP = """
import json, sys
import gymnasium as gym
import numpy as np
import torch


def load(path):
    if path.endswith(".onnx"):
        import onnxruntime

        session = onnxruntime.InferenceSession(path)
        return lambda obs: session.run(None, {"observation": obs})[0]
    policy = torch.jit.load(path)
    return lambda obs: policy(torch.from_numpy(obs)).numpy()


def episodes(path, env_id, seeds):
    policy, returns = load(path), []
    for seed in seeds:
        env = gym.make(env_id)
        env.reset(seed=seed)  # as rlpipe's envs are seeded (TorchRL resets once with the seed)
        obs, _ = env.reset()
        total, done = 0.0, False
        while not done:
            action = policy(np.asarray(obs, dtype=np.float32)[None])[0]
            obs, reward, terminated, truncated, _ = env.step(action if action.ndim else int(action))
            total, done = total + float(reward), terminated or truncated
        returns.append(total)
    return returns


jobs = json.loads(sys.argv[1])
returns = {name: episodes(**job) for name, job in jobs.items()}
assert "rlpipe" not in sys.modules
print(json.dumps(returns))
"""


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """One tiny run of every algorithm (200 frames)."""
    root = tmp_path_factory.mktemp("export")
    for name, (env_id, algo) in RUNS.items():
        cfg = Config(
            env=EnvConfig(id=env_id),
            algo=algo,
            total_frames=200,
            eval_every=200,
            eval_episodes=2,
            progress=False,
        )
        train(cfg, root / name)
    return {name: root / name for name in RUNS}


@pytest.fixture(scope="module")
def exported(runs: dict[str, Path]) -> dict[str, Path]:
    """Every run's greedy policy as TorchScript (into the run dir's export/)."""
    return {name: export_policy(run).path for name, run in runs.items()}


def plain_loop(jobs: dict[str, dict]) -> dict[str, list[float]]:
    """Returns of the episodes ``jobs`` asks for, from :data:`PLAIN_LOOP` in a subprocess."""
    proc = subprocess.run(
        [sys.executable, "-c", PLAIN_LOOP, json.dumps(jobs)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.fixture(scope="module")
def plain_returns(runs: dict[str, Path], exported: dict[str, Path]) -> dict[str, list[float]]:
    """The plain loop's returns of every exported file, one subprocess for all."""
    jobs = {
        name: {"path": str(path), "env_id": RUNS[name][0], "seeds": SEEDS}
        for name, path in exported.items()
    }
    return plain_loop(jobs)


def rlpipe_returns(run_dir: Path) -> list[float]:
    """``rlpipe.evaluate`` of the run's policy: one episode per seed of :data:`SEEDS`, each on
    one gymnasium env copy (MBRL's greedy planner draws its noise per batch)."""
    run = load_run(run_dir)
    env_cfg = replace(run.cfg.env, backend="gymnasium")
    returns = []
    for seed in SEEDS:
        env = make_env(env_cfg, num_envs=1, seed=seed, vectorization="sync")
        returns += evaluate(run.algo.policy, env, 1).returns
        env.close()
    run.algo.close()
    return returns


def observations(env_id: str, n: int = 1000) -> torch.Tensor:
    """``n`` observations from the env's observation space (another seed than the export's)."""
    space = gym.make(env_id).observation_space
    space.seed(123)
    return torch.as_tensor(np.stack([space.sample() for _ in range(n)]), dtype=torch.float32)


@pytest.mark.parametrize("name", list(RUNS))
def test_the_file_takes_the_runs_actions(name: str, runs, exported) -> None:
    path = exported[name]
    newest = sorted((runs[name] / "checkpoints").glob("ckpt_*.pt"))[-1]
    assert path == runs[name] / "export" / f"policy-{newest.stem}.pt"
    policy = torch.jit.load(str(path))
    run = load_run(runs[name])
    obs = observations(RUNS[name][0])
    is_planner = name == "mbrl"
    expected = policy_actions(run.algo.policy, obs, rows_alone=is_planner)
    run.algo.close()
    with torch.no_grad():
        actual = policy(obs)
    assert actual.dtype == expected.dtype and actual.shape == expected.shape
    if expected.dtype.is_floating_point:
        torch.testing.assert_close(actual, expected, rtol=1e-5, atol=1e-5)
        assert expected.std() > 0  # the policy does depend on the observation
    else:
        assert torch.equal(actual, expected)
        assert len(expected.unique()) > 1


@pytest.mark.parametrize("name", list(RUNS))
def test_plain_gymnasium_loop_returns_rlpipes_returns(name: str, runs, plain_returns) -> None:
    ours, theirs = plain_returns[name], rlpipe_returns(runs[name])
    assert ours == pytest.approx(theirs, rel=1e-4)
    assert np.mean(ours) == pytest.approx(np.mean(theirs), rel=1e-4)


def test_onnx_files_take_the_runs_actions_and_returns(runs) -> None:
    needs_extra("onnxruntime", "onnx")
    import onnxruntime

    jobs = {}
    for name in ONNX:
        result = export_policy(runs[name], format="onnx")
        assert result.path.name == "policy-ckpt_000000000200.onnx" and result.checked == 1000
        session = onnxruntime.InferenceSession(str(result.path))
        spec = json.loads(session.get_modelmeta().custom_metadata_map["rlpipe"])
        assert spec["algo"] == name and spec["env"]["id"] == RUNS[name][0]
        obs = observations(RUNS[name][0])
        run = load_run(runs[name])
        expected = policy_actions(run.algo.policy, obs).numpy()
        run.algo.close()
        actual = session.run(None, {"observation": obs.numpy()})[0]
        np.testing.assert_allclose(actual, expected, rtol=1e-5, atol=1e-5)
        jobs[name] = {"path": str(result.path), "env_id": RUNS[name][0], "seeds": SEEDS}
    for name, returns in plain_loop(jobs).items():
        assert returns == pytest.approx(rlpipe_returns(runs[name]), rel=1e-4)


def test_state_dict_file_rebuilds_the_policy(runs, tmp_path: Path) -> None:
    out = tmp_path / "ppo.pt"
    result = export_policy(runs["ppo"], format="state_dict", out=out, checkpoint="best")
    assert result.path == out and result.spec["checkpoint"].startswith("best_")
    saved = torch.load(out, weights_only=True)
    spec = saved["spec"]
    assert spec["action"] == {
        "kind": "box",
        "shape": [1],
        "low": [-2.0],
        "high": [2.0],
        "dtype": "float32",
    }
    assert spec["observation"] == {"shape": [3], "dtype": "float32"}
    assert "Normalizer" in spec["module"]  # PPO's observation normaliser is part of it
    run = load_run(runs["ppo"], "best")
    rebuilt = greedy_policy(run.algo)
    for tensor in rebuilt.state_dict().values():
        tensor.zero_()
    rebuilt.load_state_dict(saved["state_dict"])
    obs = observations("Pendulum-v1", 100)
    torch.testing.assert_close(rebuilt(obs), policy_actions(run.algo.policy, obs))
    run.algo.close()


def test_greedy_policy_is_plain_torch_and_a_snapshot(runs) -> None:
    run = load_run(runs["dqn"])
    policy = greedy_policy(run.algo)
    assert not policy.training
    assert not any(isinstance(m, TensorDictModuleBase) for m in policy.modules())
    obs = observations("CartPole-v1", 50)
    before = policy(obs)
    with torch.no_grad():
        for parameter in run.algo.policy.parameters():
            parameter.neg_()  # later training does not reach the exported module
    assert torch.equal(policy(obs), before)
    assert not torch.equal(policy_actions(run.algo.policy, obs), before)
    run.algo.close()


@pytest.mark.parametrize(
    ("env_id", "planner"),
    [(env, planner) for env in ("Pendulum-v1", "CartPole-v1") for planner in ("cem", "random")],
)
def test_fixed_noise_planner_plans_each_row_as_mbrl_alone(env_id: str, planner: str) -> None:
    """Every planner path: each row of a batch gets the action MBRL's greedy policy takes for
    that observation alone (an untrained world model: any weights will do)."""
    torch.manual_seed(0)
    cfg = MBRLConfig(**{**SMALL_MBRL, "planner": planner})
    algo = MBRL(partial(make_env, EnvConfig(id=env_id), seed=0), cfg)
    module = greedy_policy(algo)
    assert isinstance(module, FixedNoisePlanner)
    obs = observations(env_id, 40)
    expected = policy_actions(algo.policy, obs, rows_alone=True)
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):  # greedy all the same
        torch.testing.assert_close(module(obs), expected)
    assert len(expected.unique()) > 1
    algo.close()


def test_command_line_writes_and_loads(runs, tmp_path: Path) -> None:
    """The entry point in a subprocess: run_dir=latest (the newest run under outputs/),
    checkpoint=best, out=, and the summary line."""
    shutil.copytree(runs["dqn"], tmp_path / "outputs" / "day" / "time")
    proc = run_module(
        "rlpipe.export", "run_dir=latest", "checkpoint=best", "out=dqn.pt", cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    line = proc.stdout.strip()
    assert line.startswith("rlpipe: exported dqn's greedy policy (best_") and "dqn.pt" in line
    assert "float32 [batch, 4] observations -> int64 [batch] actions" in line
    extra = {"rlpipe.json": ""}
    policy = torch.jit.load(str(tmp_path / "dqn.pt"), _extra_files=extra)
    assert json.loads(extra["rlpipe.json"])["checkpoint"].startswith("best_")
    assert policy(torch.zeros(3, 4)).shape == (3,)


class BatchSizeNet(nn.Module):
    """A Q-network whose Python control flow depends on its input's batch size: a trace keeps
    the branch of its example batch."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.linear = nn.Linear(in_features, out_features)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if observation.shape[0] > 8:
            return -self.linear(observation)
        return self.linear(observation)


def test_a_policy_the_file_cannot_follow_is_refused(tmp_path: Path) -> None:
    cfg = Config(
        algo=DQNConfig(learning_starts=16, batch_size=8, frames_per_batch=16),
        total_frames=32,
        eval_episodes=1,
        progress=False,
    )
    train(cfg, tmp_path / "run", network=BatchSizeNet(4, 2))
    out = tmp_path / "batch_size.pt"
    with pytest.raises(RlpipeError, match=r"takes other actions on \d+ of 1000 observations"):
        export_policy(tmp_path / "run", out=out, network=BatchSizeNet(4, 2))
    assert not out.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["format=tflite"], "format must be one of torchscript, onnx, state_dict; got 'tflite'"),
        (["checkpoint=ckpt_000000000999.pt"], "ckpt_000000000999.pt does not exist"),
        (["observations=0"], "observations must be >= 1"),
        (["nope=1"], "Could not override 'nope'"),
    ],
)
def test_bad_input_is_one_line(args: list[str], message: str, runs, capsys) -> None:
    assert_one_error_line(main, [f"run_dir={runs['dqn']}", *args], message, capsys)


def test_a_dir_that_is_not_a_run_is_one_line(tmp_path: Path, capsys) -> None:
    assert_one_error_line(main, [f"run_dir={tmp_path}"], "is not an rlpipe run directory", capsys)
    assert_one_error_line(main, [], "pass run_dir=", capsys)
    assert list(tmp_path.iterdir()) == []


def test_an_existing_file_is_not_overwritten(runs, tmp_path: Path, capsys) -> None:
    out = tmp_path / "mine.pt"
    out.write_text("the user's")
    args = [f"run_dir={runs['dqn']}", f"out={out}"]
    assert_one_error_line(main, args, "exists; pass overwrite=true", capsys)
    assert out.read_text() == "the user's"
    main([*args, "overwrite=true"])
    assert torch.jit.load(str(out))(torch.zeros(1, 4)).shape == (1,)


def test_onnx_without_the_extra_says_how_to_install_it(
    runs, tmp_path: Path, capsys, monkeypatch
) -> None:
    monkeypatch.setitem(sys.modules, "onnxscript", None)  # import onnxscript fails
    out = tmp_path / "dqn.onnx"
    args = [f"run_dir={runs['dqn']}", "format=onnx", f"out={out}"]
    assert_one_error_line(main, args, 'pip install "rlpipe[onnx]"', capsys)
    assert not out.exists()


def test_help_lists_the_keys(capsys) -> None:
    main(["--help"])
    text = capsys.readouterr().out
    assert text.startswith("``python -m rlpipe.export run_dir=")
    assert "keys (conf/export.yaml): run_dir, checkpoint, format, out, overwrite" in text


def test_an_export_dir_that_is_a_link_is_refused(runs, tmp_path: Path, capsys) -> None:
    """Nothing is written through a link in the run dir: its export/ pointing elsewhere."""
    run = Path(
        shutil.copytree(runs["dqn"], tmp_path / "run", ignore=shutil.ignore_patterns("export"))
    )
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (run / "export").symlink_to(elsewhere)
    assert_one_error_line(main, [f"run_dir={run}"], "export is a symbolic link", capsys)
    assert list(elsewhere.iterdir()) == []
