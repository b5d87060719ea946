"""Videos of greedy episodes: ``video=true`` / a cadence, the mp4s, TensorBoard, and bad input."""

from __future__ import annotations

from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest
from conftest import TINY, needs_extra
from PIL import Image

from rlpipe import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.heuristic import random_policy
from rlpipe.video import make_render_env, record_episode, write_mp4

EVAL_CSV = "metrics/scalars/eval/return_mean.csv"
NORENDER_MODULE = """
import gymnasium as gym
import numpy as np


class NoRender(gym.Env):
    metadata = {"render_modes": []}
    observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    action_space = gym.spaces.Discrete(2)

    def __init__(self, render_mode=None):
        self.render_mode = render_mode

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(2, np.float32), {}

    def step(self, action):
        return np.zeros(2, np.float32), 1.0, True, False, {}


gym.register("NoRender-v0", entry_point=NoRender)
"""


def write_norender_module(directory: Path) -> str:
    """A gymnasium env without rendering, importable from ``directory``; returns its env id."""
    (directory / "norender_env.py").write_text(NORENDER_MODULE)
    return "norender_env:NoRender-v0"


def read_video(path: Path) -> np.ndarray:
    """All frames of an mp4, ``(T, H, W, 3)``."""
    return np.stack(imageio.mimread(path, memtest=False))


def assert_cartpole_frames(frames: np.ndarray) -> None:
    assert frames.shape[1:] == (400, 600, 3)
    assert frames.shape[0] >= 10  # CartPole episodes last at least ~9 steps, plus the reset frame
    assert frames.std() > 10  # not a blank picture
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).sum() > 0  # the cart moved


def test_record_episode_has_one_frame_per_step_plus_the_first(tmp_path):
    env = make_render_env(EnvConfig(id="CartPole-v1"), seed=0)
    frames = record_episode(random_policy(env), env)
    env.close()
    steps = len(frames) - 1
    assert 8 <= steps <= 500 and frames.dtype == np.uint8
    path = write_mp4(frames, tmp_path / "v" / "episode.mp4", fps=50)
    decoded = read_video(path)
    assert decoded.shape == frames.shape  # full size, every frame
    assert np.abs(decoded.astype(int) - frames.astype(int)).mean() < 5  # lossy, but the same
    assert_cartpole_frames(decoded)


def test_env_without_rgb_array_is_refused(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    env_id = write_norender_module(tmp_path)
    make_env(EnvConfig(id=env_id)).close()  # the env itself works
    with pytest.raises(RlpipeError, match="cannot render rgb_array frames"):
        make_render_env(EnvConfig(id=env_id))


def test_video_true_records_every_evaluation_and_logs_to_tensorboard(rlpipe_cli, tmp_path):
    needs_extra("tensorboard", "tensorboard")
    proc = rlpipe_cli(*TINY, "video=true", "logger=tensorboard")
    assert proc.returncode == 0, proc.stderr
    run = tmp_path / "run"
    videos = sorted(p.name for p in (run / "videos").iterdir())
    assert videos == ["eval_000000000100.mp4", "eval_000000000200.mp4"]
    for name in videos:
        assert_cartpole_frames(read_video(run / "videos" / name))
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events_dir,) = (run / "tensorboard").iterdir()
    events = EventAccumulator(str(events_dir), size_guidance={"images": 0})
    events.Reload()
    assert "eval/return_mean" in events.Tags()["scalars"]
    assert [e.step for e in events.Images("eval/video")] == [100, 200]
    curve = Image.open(run / "curve.png")
    assert curve.size == (1200, 450)


def test_video_cadence_records_past_each_multiple_and_at_the_end(rlpipe_cli, tmp_path):
    proc = rlpipe_cli(*TINY, "eval_every=50", "video=150")
    assert proc.returncode == 0, proc.stderr
    run = tmp_path / "run"
    evals = [int(line.split(",")[0]) for line in (run / EVAL_CSV).read_text().splitlines()]
    assert len(evals) == 4 and evals[-1] == 200  # ~50, ~100, ~150, 200
    expected = [next(f for f in evals if f >= 150), 200]
    videos = sorted(p.name for p in (run / "videos").iterdir())
    assert videos == [f"eval_{f:012d}.mp4" for f in expected]


BAD_VIDEO = [
    (["video=abc"], "video must be true, false or a frame cadence N >= 1, got 'abc'"),
    (["video=-5"], "video must be true, false or a frame cadence N >= 1, got -5"),
]


@pytest.mark.parametrize("args, message", BAD_VIDEO, ids=[a[0] for a, _ in BAD_VIDEO])
def test_bad_video_value_is_one_line(rlpipe_cli, args, message):
    proc = rlpipe_cli("progress=false", *args)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"rlpipe: error: {message}"


def test_video_on_an_env_that_cannot_render_is_one_line(rlpipe_cli, tmp_path):
    env_id = write_norender_module(tmp_path)
    proc = rlpipe_cli(*TINY, "env=gym", f"env.id={env_id}", "video=true")
    assert proc.returncode == 2
    assert proc.stderr.strip() == (
        "rlpipe: error: env norender_env:NoRender-v0 cannot render rgb_array frames (render "
        "modes: none), so there is no video to record; drop video=true"
    )
    assert not (tmp_path / "run" / "metrics").exists()
    assert not (tmp_path / "run" / "checkpoints").exists()
