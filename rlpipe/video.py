"""Headless videos of greedy episodes: ``rgb_array`` frames -> mp4 (imageio), plus the logger."""

from __future__ import annotations

import os
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase, ExplorationType, set_exploration_type

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env, sub_envs
from rlpipe.errors import RlpipeError, check
from rlpipe.files import temp_path

MAX_STEPS = 10_000  # for envs without a time limit


def make_render_env(cfg: EnvConfig, seed: int | None = None) -> EnvBase:
    """One copy of ``cfg`` that renders ``rgb_array`` frames; a clear error if it cannot."""
    if not os.environ.get("XDG_RUNTIME_DIR"):  # else SDL prints an error line about it
        os.environ["XDG_RUNTIME_DIR"] = tempfile.mkdtemp(prefix="rlpipe-runtime-")
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


def check_display(what: str) -> None:
    """Fail with one line when there is no display to open ``what``'s window on."""
    has_display = any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "SDL_VIDEODRIVER"))
    check(
        has_display or not sys.platform.startswith("linux"),
        f"no display available (DISPLAY is not set): {what} needs a window; run it on a "
        "desktop session or under xvfb-run (SDL_VIDEODRIVER=dummy runs it without a visible "
        "window)",
    )


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
    """Encode ``(T, H, W, 3)`` uint8 frames as an H.264 mp4 at ``path`` (encoded aside, then
    renamed into place: never written through a link)."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temp = temp_path(path).with_suffix(".mp4")  # encoded aside, renamed over a link or file
    if os.path.lexists(temp):
        os.unlink(temp)
    # macro_block_size=2: keep the frame size (H.264 only needs even sides)
    imageio.mimwrite(temp, list(frames), fps=fps, codec="libx264", macro_block_size=2)
    os.replace(temp, path)
    return path
