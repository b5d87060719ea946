"""What a run records besides its metrics, as :class:`~rlpipe.runner.Callback` hooks on the
:class:`~rlpipe.runner.Runner`: videos of greedy episodes, ``curve.png``, and closing the logger."""

from __future__ import annotations

from pathlib import Path

import torch

from rlpipe.config import Config, EnvConfig
from rlpipe.episodes import EvalResult
from rlpipe.figures import plot_run
from rlpipe.loggers import log_artifacts, require_extra, takes_video
from rlpipe.outcomes import RunResult
from rlpipe.rundir import RunDir
from rlpipe.runner import Callback, Runner
from rlpipe.video import frame_rate, make_render_env, record_episode, write_mp4

__all__ = ["Callback", "CloseLogger", "CurveCallback", "VideoCallback", "make_callbacks"]


class VideoCallback(Callback):
    """Records one greedy episode to ``<run dir>/videos/eval_<frames>.mp4`` at evaluations.

    At the first evaluation past each multiple of ``every`` frames (1: every evaluation), and
    always after the final one; every episode starts from ``seed`` (None: the env's own
    episodes). TensorBoard and W&B loggers get the video too.
    """

    def __init__(self, env_cfg: EnvConfig, every: int, seed: int | None = None) -> None:
        require_extra("video", "video=true")
        self.env = make_render_env(env_cfg, seed=seed)
        self.seed = seed
        self.every = every
        self.next_due = every
        self.last_frames = -1

    def state_dict(self) -> dict[str, int]:
        return {"next_due": self.next_due, "last_frames": self.last_frames}

    def load_state_dict(self, state: dict[str, int]) -> None:
        self.next_due = int(state.get("next_due", self.every))
        self.last_frames = int(state.get("last_frames", -1))

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
        if self.seed is not None:
            self.env.set_seed(self.seed)
        frames = record_episode(runner.algo.policy, self.env)
        self.last_frames = runner.algo.frames
        name = f"eval_{runner.algo.frames:012d}.mp4"
        path = write_mp4(frames, runner.run_dir / RunDir.VIDEOS / name, frame_rate(self.env))
        if takes_video(runner.logger):
            video = torch.from_numpy(frames).permute(0, 3, 1, 2).unsqueeze(0)  # N T C H W
            runner.logger.log_video(
                "eval/video", video, step=runner.algo.frames, fps=frame_rate(self.env)
            )
        return path


class CurveCallback(Callback):
    """Draws ``curve.png`` into the run dir when the run ends, and gives it and the run's videos
    to the tracker (W&B, MLflow: artifacts; TensorBoard: an image)."""

    def on_end(self, runner: Runner, result: RunResult) -> None:
        curve = plot_run(runner.run_dir)
        log_artifacts(
            runner.logger, [curve, *sorted((runner.run_dir / RunDir.VIDEOS).glob("*.mp4"))]
        )


class CloseLogger(Callback):
    """Flushes and closes the runner's logger when the run ends (W&B/MLflow runs finish)."""

    def on_end(self, runner: Runner, result: RunResult) -> None:
        if runner.logger is not None:
            runner.logger.shutdown()


def make_callbacks(cfg: Config) -> list[Callback]:
    """What ``train`` records besides metrics: videos (``cfg.video``), ``curve.png``."""
    callbacks: list[Callback] = []
    if cfg.video:
        callbacks.append(VideoCallback(cfg.env, int(cfg.video), seed=cfg.seed + 20_000))
    if cfg.logger.backend != "none":
        callbacks.append(CurveCallback())
    return [*callbacks, CloseLogger()]
