"""``python -m rlpipe.evaluate``: a trained run, baselines, videos and bad input."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
from conftest import assert_one_error_line, run_module

from rlpipe import Config, DQNConfig, train
from rlpipe.evaluate import main

NEEDS_VIDEO = pytest.mark.skipif(
    importlib.util.find_spec("imageio") is None,
    reason='needs the video extra: pip install torch==2.13.0 -e ".[video]"',
)
FIELDS = {
    "policy",
    "env",
    "run_dir",
    "checkpoint",
    "episodes",
    "copies",
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


def test_evaluate_trained_run(
    run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command line (one subprocess), then ``checkpoint=200`` in-process."""
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
    main([f"run_dir={run_dir}", "checkpoint=200", "episodes=1"])
    assert "trained (ckpt_000000000200)" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("policy", "env", "env_id"),
    [
        ("random", "cartpole", "CartPole-v1"),
        ("naive", "bipedal", "BipedalWalker-v3"),
        ("heuristic", "bipedal", "BipedalWalker-v3"),
    ],
)
def test_evaluate_baselines(
    tmp_path: Path, policy: str, env: str, env_id: str, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / f"{policy}.json"
    main([f"policy={policy}", f"env={env}", "episodes=2", f"out={out}"])
    assert capsys.readouterr().out.startswith(f"rlpipe: {policy} on {env_id}: return")
    summary = json.loads(out.read_text())
    assert summary["policy"] == policy and summary["checkpoint"] is None
    assert len(summary["returns"]) == 2


@pytest.mark.parametrize(
    ("copies", "on"), [(None, "on 4 env copies"), (1, "on one env"), (2, "on 2 env copies")]
)
def test_evaluate_copies(
    run_dir: Path, tmp_path: Path, copies: int | None, on: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``copies`` sets the env copies the episodes share (null: one per episode, up to 32)."""
    out = tmp_path / "summary.json"
    main([f"run_dir={run_dir}", "episodes=4", f"copies={copies or 'null'}", f"out={out}"])
    assert f"over 4 episodes {on} (" in capsys.readouterr().out
    summary = json.loads(out.read_text())
    assert summary["copies"] == (copies or 4) and len(summary["returns"]) == 4


@NEEDS_VIDEO
def test_evaluate_video(run_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "greedy.json"
    main([f"run_dir={run_dir}", "episodes=1", "video=true", f"out={out}"])
    video = tmp_path / "greedy.mp4"
    assert video.is_file() and video.stat().st_size > 1000
    assert json.loads(out.read_text())["video"] == str(video)
    assert "video" in capsys.readouterr().out


def test_latest_is_the_newest_run_dir_not_its_hydra_record(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run started last, no checkpoint yet: ``latest`` is it, and the error names it (not its
    ``.hydra`` folder, whose config.yaml Hydra writes after the run's own)."""
    from omegaconf import OmegaConf

    from rlpipe.runs import latest_run

    config = OmegaConf.to_yaml(OmegaConf.structured(Config()))
    old, new = tmp_path / "outputs" / "day" / "old", tmp_path / "outputs" / "day" / "new"
    (old / "checkpoints").mkdir(parents=True)
    (old / "config.yaml").write_text(config)
    (old / "checkpoints" / "ckpt_000000000100.pt").write_bytes(b"")
    (new / ".hydra").mkdir(parents=True)
    for i, path in enumerate([new / "config.yaml", new / ".hydra" / "config.yaml"]):
        path.write_text(config)
        os.utime(path, (2e9 + i, 2e9 + i))  # the .hydra record newest of all
    assert latest_run(tmp_path / "outputs") == new
    monkeypatch.chdir(tmp_path)
    assert_one_error_line(main, ["run_dir=latest"], "outputs/day/new has no checkpoint", capsys)


@NEEDS_VIDEO
def test_latest_run_best_checkpoint_live_window_and_a_longer_video(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Enjoy: run_dir=latest (the newest run under outputs/), checkpoint=best, render=human (a
    window; SDL's dummy driver here, in a subprocess) and video_episodes=N (N episodes in one
    mp4, in-process)."""
    for seed in (1, 2):  # the second run is the latest
        train(
            Config(seed=seed, total_frames=300, eval_every=100, eval_episodes=2, progress=False),
            tmp_path / "outputs" / "day" / f"run{seed}",
        )
    latest = tmp_path / "outputs" / "day" / "run2"
    args = ["run_dir=latest", "checkpoint=best", "episodes=2"]
    proc = run_module("rlpipe.evaluate", *args, "render=human", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    (summary,) = [json.loads(p.read_text()) for p in (latest / "evaluation").glob("*.json")]
    assert summary["run_dir"] == "outputs/day/run2" and summary["checkpoint"].startswith("best_")
    monkeypatch.chdir(tmp_path)
    main([*args, "video=true", "video_episodes=3"])
    summary = json.loads(next((latest / "evaluation").glob("*.json")).read_text())
    assert len(summary["video_frames"]) == 3 and Path(tmp_path / summary["video"]).is_file()
    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "SDL_VIDEODRIVER")}
    done = subprocess.run(
        [sys.executable, "-m", "rlpipe.evaluate", "run_dir=latest", "render=human"],
        cwd=tmp_path,
        env={**headless, "WAYLAND_DISPLAY": ""},
        capture_output=True,
        text=True,
    )
    assert done.returncode == 2 and "render=human needs a window" in done.stderr


@pytest.mark.parametrize(
    "args, message",
    [
        (["run_dir=MISSING"], "no-such-run does not exist"),
        (["run_dir=RUN", "render=tv"], "render must be human"),
        (["run_dir=RUN", "video_episodes=0"], "video_episodes must be >= 1"),
        (["run_dir=RUN", "colour=red"], "colour"),
        (["run_dir=RUN", "+colour=red"], "unknown key 'colour'"),
        (["run_dir=RUN", "episodes=0"], "episodes must be >= 1"),
        (["run_dir=RUN", "episodes=3", "copies=4"], "copies must be between 1 and episodes (3)"),
        (["run_dir=RUN", "copies=0"], "copies must be between 1 and episodes (10)"),
        (["run_dir=RUN", "copies=2", "render=human"], "render=human runs one env copy"),
        (["run_dir=RUN", "device=gpu"], "device must be auto, cpu, cuda or cuda:N, got gpu"),
        (
            ["run_dir=RUN", "checkpoint=150"],
            "has no checkpoint at 150 frames (checkpoints/ckpt_000000000150.pt); it has 200",
        ),
        (["policy=best", "env=cartpole"], "policy must be one of"),
        (["episodes=3"], "policy=trained needs run_dir"),
        (["policy=random"], "pass run_dir="),
        (["policy=heuristic", "env=cartpole"], "policy=heuristic is a hand-written BipedalWalker"),
        (["policy=naive", "env=cartpole"], "policy=naive is a hand-written BipedalWalker"),
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
    assert not (tmp_path / "evaluation").exists() and not (tmp_path / "outputs").exists()


def test_evaluate_bad_input_cli(tmp_path: Path) -> None:
    """The command line: one line on stderr, exit 2."""
    proc = run_module("rlpipe.evaluate", f"run_dir={tmp_path / 'nothing'}", cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error:") and "does not exist" in lines[0]


def test_baseline_default_out_is_under_outputs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Without a run dir the summary goes to outputs/evaluation/, not ./evaluation/."""
    monkeypatch.chdir(tmp_path)
    main(["policy=random", "env=cartpole", "episodes=2"])
    out = Path("outputs") / "evaluation" / "CartPole-v1-random.json"
    assert f"summary {out}" in capsys.readouterr().out
    assert json.loads((tmp_path / out).read_text())["policy"] == "random"
    assert not (tmp_path / "evaluation").exists()


def copy_run(run_dir: Path, dest: Path) -> Path:
    """A copy of the fixture run without the evaluations other tests wrote into it."""
    shutil.copytree(run_dir, dest, ignore=shutil.ignore_patterns("evaluation"))
    return dest


def no_episodes(*args: object, **kwargs: object) -> None:
    raise AssertionError("episodes ran before the output location was checked")


@pytest.fixture
def no_eval(monkeypatch: pytest.MonkeyPatch) -> None:
    """Running an episode fails the test."""
    monkeypatch.setattr(sys.modules["rlpipe.evaluate"], "evaluate", no_episodes)


def test_read_only_run_dir_fails_before_episodes(
    run_dir: Path,
    tmp_path: Path,
    no_eval: None,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A run dir that takes no new file (simulated: root writes through chmod 0o555)."""
    copy = copy_run(run_dir, tmp_path / "run")
    real = tempfile.TemporaryFile

    def read_only(*args: object, dir: str | Path | None = None, **kwargs: object):  # noqa: A002
        if dir is not None and Path(dir).is_relative_to(copy):
            raise PermissionError(30, "Read-only file system")
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    message = f"cannot write {copy / 'evaluation' / 'trained-ckpt_000000000200.json'}"
    assert_one_error_line(main, [f"run_dir={copy}", "episodes=2"], message, capsys)
    assert not (copy / "evaluation").exists()  # the probe's directory is removed again


@pytest.mark.skipif(
    os.geteuid() == 0,
    reason="root writes into a chmod 0o555 dir: run pytest as another user for this one; the "
    "read-only case runs for root too (test_read_only_run_dir_fails_before_episodes, simulated)",
)
def test_chmod_read_only_run_dir(
    run_dir: Path, tmp_path: Path, no_eval: None, capsys: pytest.CaptureFixture[str]
) -> None:
    copy = copy_run(run_dir, tmp_path / "run")
    copy.chmod(0o555)
    try:
        assert_one_error_line(main, [f"run_dir={copy}", "policy=random"], "out=<file", capsys)
    finally:
        copy.chmod(0o755)
    assert not (copy / "evaluation").exists()


def test_out_under_a_file_fails_before_episodes(tmp_path: Path) -> None:
    """out=<file>/x.json cannot be written, not even by root: one line, exit 2, and no episode
    ran (the eval fault point would have killed the process)."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory\n")
    env = {**os.environ, "RLPIPE_FAULT": "eval"}
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "rlpipe.evaluate",
            "policy=random",
            "env=cartpole",
            "video=true",
            f"out={blocker / 'sub' / 'x.json'}",
        ],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode != -signal.SIGKILL, "an episode ran before the check"
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0] == (
        f"rlpipe: error: cannot write {blocker / 'sub' / 'x.json'}: {blocker} is not a "
        "directory; pick a writable place for the summary with out=<file.json>"
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a-file"]


def write_probe_module(directory: Path) -> Path:
    """A module that leaves a marker when imported and registers a CartPole under its id."""
    marker = directory / "imported.txt"
    (directory / "rlpipe_probe_env.py").write_text(
        "import pathlib\n"
        "import gymnasium as gym\n"
        f"pathlib.Path({str(marker)!r}).write_text('imported')\n"
        "gym.register('ProbeCartPole-v0', entry_point='gymnasium.envs.classic_control:CartPoleEnv',"
        " max_episode_steps=50)\n"
    )
    return marker


@pytest.mark.parametrize("policy", ["trained", "random"])
def test_run_dir_env_import_refused(
    run_dir: Path,
    tmp_path: Path,
    policy: str,
    no_eval: None,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A run dir is data: env.id=module:Id in its config.yaml imports nothing by default."""
    copy = copy_run(run_dir, tmp_path / "run")
    config = copy / "config.yaml"
    config.write_text(
        config.read_text().replace("id: CartPole-v1", "id: rlpipe_probe_env:ProbeCartPole-v0")
    )
    marker = write_probe_module(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    argv = [f"run_dir={copy}", f"policy={policy}"]
    assert_one_error_line(main, argv, "allow_env_import=true", capsys)
    assert not marker.exists()
    assert not (copy / "evaluation").exists()


def test_run_dir_env_import_allowed(
    run_dir: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    copy = copy_run(run_dir, tmp_path / "run")
    config = copy / "config.yaml"
    text = config.read_text().replace("backend: envpool", "backend: gymnasium")  # its own id
    config.write_text(text.replace("id: CartPole-v1", "id: rlpipe_probe_env:ProbeCartPole-v0"))
    marker = write_probe_module(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    main([f"run_dir={copy}", "policy=random", "episodes=2", "allow_env_import=true"])
    assert marker.exists()
    assert "random on rlpipe_probe_env:ProbeCartPole-v0" in capsys.readouterr().out
    assert (copy / "evaluation" / "random.json").is_file()
    sys.modules.pop("rlpipe_probe_env", None)
