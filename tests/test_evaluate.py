"""``python -m rlpipe.evaluate``: a trained run, baselines, videos and bad input."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest
from conftest import assert_one_error_line, run_module

from rlpipe import Config, DQNConfig, train
from rlpipe.evaluate import main

FIELDS = {
    "policy",
    "env",
    "run_dir",
    "checkpoint",
    "episodes",
    "seed",
    "return_mean",
    "return_std",
    "return_min",
    "return_max",
    "length_mean",
    "returns",
    "lengths",
    "video",
}


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One tiny DQN run on CartPole-v1."""
    run_dir = tmp_path_factory.mktemp("evaluate") / "run"
    cfg = Config(
        algo=DQNConfig(),
        device="cpu",
        total_frames=200,
        eval_every=100,
        eval_episodes=2,
        progress=False,
    )
    train(cfg, run_dir)
    return run_dir


def test_evaluate_trained_run(run_dir: Path, tmp_path: Path) -> None:
    proc = run_module("rlpipe.evaluate", f"run_dir={run_dir}", "episodes=3", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "±" in proc.stdout and "over 3 episodes" in proc.stdout
    summary = json.loads((run_dir / "evaluation" / "trained-ckpt_000000000200.json").read_text())
    assert FIELDS <= set(summary)
    assert summary["policy"] == "trained" and summary["env"] == "CartPole-v1"
    assert summary["checkpoint"] == "ckpt_000000000200"
    assert len(summary["returns"]) == len(summary["lengths"]) == 3
    assert summary["return_min"] <= summary["return_mean"] <= summary["return_max"]
    assert all(r >= 1 for r in summary["returns"])
    assert summary["video"] is None


def test_evaluate_random_baseline(tmp_path: Path) -> None:
    out = tmp_path / "random.json"
    proc = run_module(
        "rlpipe.evaluate", "policy=random", "env=cartpole", "episodes=3", f"out={out}", cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("rlpipe: random on CartPole-v1: return")
    summary = json.loads(out.read_text())
    assert summary["policy"] == "random" and summary["checkpoint"] is None
    assert len(summary["returns"]) == 3


@pytest.mark.skipif(importlib.util.find_spec("imageio") is None, reason="needs rlpipe[video]")
def test_evaluate_video(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "greedy.json"
    proc = run_module(
        "rlpipe.evaluate",
        f"run_dir={run_dir}",
        "episodes=1",
        "video=true",
        f"out={out}",
        cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    video = tmp_path / "greedy.mp4"
    assert video.is_file() and video.stat().st_size > 1000
    assert json.loads(out.read_text())["video"] == str(video)
    assert "video" in proc.stdout


@pytest.mark.parametrize(
    "args, message",
    [
        (["run_dir=MISSING"], "no-such-run does not exist"),
        (["run_dir=RUN", "colour=red"], "colour"),
        (["run_dir=RUN", "+colour=red"], "unknown key 'colour'"),
        (["run_dir=RUN", "episodes=0"], "episodes must be >= 1"),
        (["policy=best", "env=cartpole"], "policy must be one of"),
        (["episodes=3"], "policy=trained needs run_dir"),
        (["policy=random"], "pass run_dir="),
        (["policy=heuristic", "env=cartpole"], "BipedalWalker controller"),
    ],
)
def test_evaluate_bad_input(
    run_dir: Path,
    tmp_path: Path,
    args: list[str],
    message: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """In-process (fast): ``main`` prints one ``rlpipe: error:`` line and exits with 2."""
    monkeypatch.chdir(tmp_path)
    missing = tmp_path / "no-such-run"
    argv = [a.replace("MISSING", str(missing)).replace("RUN", str(run_dir)) for a in args]
    assert_one_error_line(main, argv, message, capsys)
    assert not (tmp_path / "evaluation").exists()


def test_evaluate_bad_input_cli(tmp_path: Path) -> None:
    """The command line: one line on stderr, exit 2."""
    proc = run_module("rlpipe.evaluate", f"run_dir={tmp_path / 'nothing'}", cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error:") and "does not exist" in lines[0]
