"""Headless videos of greedy episodes: ``rgb_array`` frames -> mp4 (imageio), plus the logger."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env, sub_envs
from rlpipe.errors import RlpipeError
from rlpipe.evaluation import EvalResult
from rlpipe.loggers import require_extra, takes_video
from rlpipe.runner import Callback, Runner, RunResult

MAX_STEPS = 10_000  # for envs without a time limit
VIDEO_DIR = "videos"


def make_render_env(cfg: EnvConfig, seed: int | None = None) -> EnvBase:
    """One copy of ``cfg`` that renders ``rgb_array`` frames; a clear error if it cannot."""
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")  # pygame-drawn envs: no sound card noise
    with warnings.catch_warnings():  # gymnasium warns about unknown render modes; we say it once
        warnings.simplefilter("ignore")
        env = make_env(cfg, num_envs=1, seed=seed, render_mode="rgb_array")
    modes = sub_envs(env)[0].metadata.get("render_modes", [])
    if "rgb_array" not in modes:
        env.close()
        raise RlpipeError(
            f"env {cfg.id} cannot render rgb_array frames (render modes: {modes or 'none'}), "
            "so there is no video to record; drop video=true"
        )
    return env


def frame_rate(env: EnvBase) -> int:
    """The env's own ``render_fps`` (30 when it does not say)."""
    return int(sub_envs(env)[0].metadata.get("render_fps") or 30)


@torch.no_grad()
def record_episode(policy: TensorDictModuleBase, env: EnvBase) -> np.ndarray:
    """Frames ``(T, H, W, 3)`` of one greedy episode of ``policy`` on a :func:`make_render_env`."""
    inner = sub_envs(env)[0]
    frames = []
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        td = env.reset()
        frames.append(inner.render())
        env.rollout(
            (inner.spec.max_episode_steps if inner.spec else None) or MAX_STEPS,
            policy,
            tensordict=td,
            auto_reset=False,
            auto_cast_to_device=True,
            break_when_any_done=True,
            callback=lambda *_: frames.append(inner.render()),
        )
    return np.stack(frames)


def write_mp4(frames: np.ndarray, path: str | Path, fps: int) -> Path:
    """Encode ``(T, H, W, 3)`` uint8 frames as an H.264 mp4 at ``path``."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # macro_block_size=2: keep the frame size (H.264 only needs even sides)
    imageio.mimwrite(path, list(frames), fps=fps, codec="libx264", macro_block_size=2)
    return path


class VideoCallback(Callback):
    """Records one greedy episode to ``<run dir>/videos/eval_<frames>.mp4`` at evaluations.

    At the first evaluation past each multiple of ``every`` frames (1: every evaluation), and
    always after the final one. TensorBoard and W&B loggers get the video too.
    """

    def __init__(self, env_cfg: EnvConfig, every: int, seed: int | None = None) -> None:
        require_extra("video", "video=true")
        self.env = make_render_env(env_cfg, seed=seed)
        self.every = every
        self.next_due = every
        self.last_frames = -1

    def on_eval(self, runner: Runner, result: EvalResult) -> None:
        if runner.algo.frames >= self.next_due:
            self.record(runner)
            self.next_due = (runner.algo.frames // self.every + 1) * self.every

    def on_end(self, runner: Runner, result: RunResult) -> None:
        if self.last_frames != runner.algo.frames:
            self.record(runner)
        self.env.close()

    def record(self, runner: Runner) -> Path:
        """Record, write and log one episode of the runner's current greedy policy."""
        frames = record_episode(runner.algo.policy, self.env)
        self.last_frames = runner.algo.frames
        name = f"eval_{runner.algo.frames:012d}.mp4"
        path = write_mp4(frames, runner.run_dir / VIDEO_DIR / name, frame_rate(self.env))
        if takes_video(runner.logger):
            video = torch.from_numpy(frames).permute(0, 3, 1, 2).unsqueeze(0)  # N T C H W
            runner.logger.log_video(
                "eval/video", video, step=runner.algo.frames, fps=frame_rate(self.env)
            )
        return path
