"""Resume after a crash, interrupts, damaged or hostile checkpoints, divergence, reproducible
metrics and disk errors (issue 5)."""

from __future__ import annotations

import math
import os
import random
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import assert_one_error_line, run_module, start_module
from tensordict.nn import TensorDictModule
from torch import nn

from rlpipe.algos import Algorithm, ARSConfig, DQNConfig, ReinforceConfig
from rlpipe.checkpoint import load_checkpoint
from rlpipe.config import Config, EnvConfig, LoggerConfig
from rlpipe.envs import make_env
from rlpipe.pipeline import load_run, train
from rlpipe.rundir import RunDir
from rlpipe.runner import Diverged, Runner

# DQN on CartPole with its own defaults (not the tuned preset's 32 updates of 256 per batch): 2
# envs, 20 frames per iteration, a checkpoint every 200 frames
DQN_ARGS = [
    "~tuned",
    "progress=false",
    "env.num_envs=2",
    "algo.frames_per_batch=20",
    "algo.learning_starts=100",
    "eval_every=500",
    "eval_episodes=2",
    "checkpoint_every=200",
]


def _steps(run_dir: Path, name: str) -> list[int]:
    path = run_dir / "metrics" / "scalars" / f"{name}.csv"
    return [int(float(line.split(",")[0])) for line in path.read_text().split()]


def _popen(tmp_path: Path, *args: str) -> subprocess.Popen:
    return start_module("rlpipe", *args, cwd=tmp_path, stdout=subprocess.DEVNULL)


def _wait_for_checkpoint(proc: subprocess.Popen, run_dir: Path, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while not RunDir(run_dir).checkpoints():
        assert proc.poll() is None, f"the run ended early: {proc.stderr.read()}"
        assert time.monotonic() < deadline, "no checkpoint appeared"
        time.sleep(0.05)


def test_sigkill_at_a_random_moment_then_resume_reaches_the_budget(tmp_path):
    run_dir = tmp_path / "run"
    args = [*DQN_ARGS, "total_frames=6000", f"hydra.run.dir={run_dir}"]
    proc = _popen(tmp_path, *args)
    _wait_for_checkpoint(proc, run_dir)
    time.sleep(random.uniform(0.0, 1.5))
    proc.kill()
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run finished before it could be killed"
    killed_at = load_checkpoint(RunDir(run_dir).checkpoints()[-1])["frames"]
    assert 0 < killed_at < 6000

    result = run_module("rlpipe", *args, f"resume={run_dir}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    loaded = load_run(run_dir)  # the final checkpoint loads and rebuilds the run
    loaded.algo.close()
    assert loaded.algo.frames == 6000 and loaded.checkpoint.name == "ckpt_000000006000.pt"
    # one row per evaluation and per log flush: nothing duplicated, nothing missing
    assert _steps(run_dir, "eval/return_mean") == list(range(500, 6001, 500))
    fps_steps = _steps(run_dir, "time/fps")
    assert fps_steps == sorted(set(fps_steps)) and fps_steps[-1] == 6000


def test_sigint_writes_a_checkpoint_and_says_how_to_resume(tmp_path):
    run_dir = tmp_path / "run"
    proc = _popen(tmp_path, *DQN_ARGS, "total_frames=1000000", f"hydra.run.dir={run_dir}")
    _wait_for_checkpoint(proc, run_dir)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGINT, stderr
    last = stderr.strip().splitlines()[-1]
    assert "SIGINT" in last and f"resume={run_dir}" in last, stderr
    assert "Traceback" not in stderr
    stopped_at = load_checkpoint(RunDir(run_dir).checkpoints()[-1])["frames"]
    assert str(RunDir(run_dir).checkpoints()[-1]) in last
    budget = stopped_at + 100
    result = run_module(
        "rlpipe", *DQN_ARGS, f"total_frames={budget}", f"resume={run_dir}", cwd=tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert load_checkpoint(RunDir(run_dir).checkpoints()[-1])["frames"] >= budget


def _tiny_dqn(run_dir: Path, total_frames: int, **overrides) -> Config:
    cfg = Config(
        env=EnvConfig(id="CartPole-v1", num_envs=2),
        algo=DQNConfig(frames_per_batch=20, learning_starts=40, batch_size=16),
        total_frames=total_frames,
        eval_every=0,
        eval_episodes=2,
        checkpoint_every=100,
        keep_checkpoints=3,
        progress=False,
        **overrides,
    )
    train(cfg, run_dir)
    return cfg


def test_damaged_newest_checkpoint_is_skipped_with_a_warning(tmp_path, capsys):
    run_dir = tmp_path / "run"
    _tiny_dqn(run_dir, 400)
    newest = RunDir(run_dir).checkpoints()[-1]
    newest.write_bytes(newest.read_bytes()[:100])  # truncated, as by a crash mid-copy
    _tiny_dqn(run_dir, 500, resume=str(run_dir))
    assert f"checkpoint {newest} is damaged" in capsys.readouterr().err
    assert load_checkpoint(RunDir(run_dir).checkpoints()[-1])["frames"] == 500
    # resumed from 300: the rows logged after it were dropped, then written again
    assert _steps(run_dir, "eval/return_mean") == [500]
    episodes = _steps(run_dir, "train/episode_return")
    assert episodes == sorted(episodes) and episodes[-1] > 300


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("finished") / "run"
    _tiny_dqn(run_dir, 200)
    return run_dir


def _copy_run(src: Path, dst: Path) -> Path:
    subprocess.run(["cp", "-r", str(src), str(dst)], check=True)
    return dst


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("missing", "run directory {tmp}/nowhere does not exist"),
        ("other_algo", "belongs to another run: it differs in algo.name ('reinforce' here"),
        ("other_env", "it differs in env.id ('MountainCar-v0' here, 'CartPole-v1' there)"),
        ("hostile", "refusing checkpoint {tmp}/run/checkpoints/ckpt_000000000300.pt"),
        ("no_checkpoint", "{tmp}/run has no checkpoint to resume from"),
        ("not_a_run", "{tmp} is not an rlpipe run directory"),
    ],
)
def test_bad_resume_is_one_line_and_touches_nothing(tmp_path, finished_run, case, message):
    run_dir = _copy_run(finished_run, tmp_path / "run")
    # the finished run's own settings (a run dir refuses another run before anything else)
    same_run = ["~tuned", "env.num_envs=2", "algo.frames_per_batch=20", "algo.learning_starts=40"]
    overrides = [*same_run, "algo.batch_size=16", "progress=false", "total_frames=300"]
    overrides.append(f"resume={run_dir}")
    if case == "missing":
        overrides[-1] = f"resume={tmp_path / 'nowhere'}"
    elif case == "other_algo":
        overrides = [o for o in overrides if not o.startswith("algo.")] + ["algo=reinforce"]
    elif case == "other_env":
        overrides.append("env=mountaincar")
    elif case == "hostile":
        torch.save({"algo": _Evil()}, run_dir / "checkpoints" / f"ckpt_{300:012d}.pt")
    elif case == "no_checkpoint":
        for path in RunDir(run_dir).checkpoints():
            path.unlink()
    elif case == "not_a_run":
        overrides[-1] = f"resume={tmp_path}"
    # Hydra's job log (rlpipe.log) may be created empty, the lock file holds the last PID
    before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file() and p.name != ".lock"}
    result = run_module("rlpipe", *overrides, cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: "), result.stderr
    assert message.format(tmp=tmp_path) in lines[0]
    assert "pwned" not in result.stdout
    after = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file()}
    assert {p: v for p, v in after.items() if p.name not in ("rlpipe.log", ".lock")} == before


def test_evaluate_on_a_run_without_checkpoint_is_one_line(tmp_path, finished_run, capsys):
    from rlpipe.evaluate import main

    run_dir = _copy_run(finished_run, tmp_path / "run")
    for path in RunDir(run_dir).checkpoints():
        path.unlink()
    message = f"{run_dir} has no checkpoint yet"
    assert_one_error_line(main, [f"run_dir={run_dir}", "episodes=2"], message, capsys)


class _Drifting(Algorithm):
    """A stand-in algorithm whose loss turns NaN at its third iteration."""

    finite_keys = ("train/loss",)  # what the runner checks for divergence

    def __init__(self) -> None:
        super().__init__()
        self.policy = TensorDictModule(nn.Linear(4, 2), ["observation"], ["action"])

    def train_step(self) -> dict[str, float]:
        self.frames += 100
        self.iterations += 1
        return {"train/loss": math.nan if self.iterations == 3 else 1.0}

    def state_dict(self) -> dict:
        return {"policy": self.policy.state_dict(), "frames": self.frames}

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state["policy"])

    def close(self) -> None:
        pass


def test_nan_loss_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path):
    runner = Runner(
        _Drifting(),
        make_env(EnvConfig(), seed=0),
        RunDir(tmp_path),
        total_frames=1000,
        eval_every=0,
        checkpoint_every=100,
        progress=False,
    )
    with pytest.raises(Diverged, match="diverged at 300 frames: train/loss is not finite"):
        runner.run()
    assert [p.name for p in RunDir(tmp_path).checkpoints()] == [
        "ckpt_000000000100.pt",
        "ckpt_000000000200.pt",
    ]


@pytest.mark.parametrize(
    ("env_cfg", "algo_cfg", "total_frames"),
    [
        (EnvConfig(num_envs=2), DQNConfig(frames_per_batch=20, learning_starts=40), 400),
        (
            EnvConfig(id="rlpipe/CartPoleContinuous-v0", num_envs=8, max_episode_steps=50),
            ReinforceConfig(epochs=2, episodes_per_epoch=8, updates_per_epoch=4),
            None,
        ),
        (EnvConfig(), ARSConfig(iterations=2, num_directions=4, num_best=2, workers=2), None),
    ],
    ids=["dqn", "reinforce", "ars"],
)
def test_same_config_and_seed_give_identical_metrics(tmp_path, env_cfg, algo_cfg, total_frames):
    runs = []
    for name in ("a", "b"):
        cfg = Config(
            env=env_cfg,
            algo=algo_cfg,
            logger=LoggerConfig("csv"),
            seed=3,
            total_frames=total_frames,
            eval_every=0,
            eval_episodes=2,
            progress=False,
        )
        train(cfg, tmp_path / name)
        scalars = tmp_path / name / "metrics" / "scalars"
        runs.append(
            {
                str(p.relative_to(scalars)): p.read_text()
                for p in scalars.rglob("*.csv")
                # clocks differ between runs (time/*), nothing else
                if p.parent.name != "time"
            }
        )
    assert runs[0] and "eval/return_mean.csv" in runs[0]
    assert runs[0] == runs[1]


def _limit_file_size() -> None:
    resource.setrlimit(resource.RLIMIT_FSIZE, (50_000, 50_000))
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG


def test_a_failing_checkpoint_write_is_one_line(tmp_path):
    run_dir = tmp_path / "run"
    result = subprocess.run(
        [sys.executable, "-m", "rlpipe", *DQN_ARGS, "total_frames=600", f"hydra.run.dir={run_dir}"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=_limit_file_size,  # the 0.5 MB replay buffer cannot be written
    )
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith(f"rlpipe: error: cannot write checkpoint {run_dir}/checkpoints/")
    assert "File too large" in lines[0]
    assert not list((run_dir / "checkpoints").glob(".*"))  # no half-written temp file


def test_an_unwritable_run_dir_fails_at_start(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("a file where a directory should be")
    result = run_module("rlpipe", "progress=false", f"hydra.run.dir={blocker}/run", cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: "), result.stderr
    assert f"{blocker}/run" in lines[0]
    assert blocker.read_text() == "a file where a directory should be"
