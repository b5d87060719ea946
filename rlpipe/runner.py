"""The one training loop every algorithm shares."""

from __future__ import annotations

import json
import math
import time
from collections import defaultdict
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from rlpipe.algos.base import Algorithm, Metrics
from rlpipe.checkpoint import checkpoint_path, save_checkpoint
from rlpipe.evaluation import EvalResult, evaluate


@dataclass
class RunResult:
    """What a finished run reports (also written to ``summary.json`` in the run dir)."""

    eval_mean: float
    eval_std: float
    eval_episodes: int
    frames: int
    wall_time: float
    run_dir: str

    def summary_line(self) -> str:
        return (
            f"final eval {self.eval_mean:.2f} ± {self.eval_std:.2f} over {self.eval_episodes} "
            f"episodes | {self.frames:,} frames | {self.wall_time:.1f} s | run dir {self.run_dir}"
        )


class _Window:
    """Averages scalar metrics between two log flushes."""

    def __init__(self) -> None:
        self.sums: dict[str, float] = defaultdict(float)
        self.counts: dict[str, int] = defaultdict(int)

    def add(self, key: str, value: float) -> None:
        self.sums[key] += value
        self.counts[key] += 1

    def pop(self) -> dict[str, float]:
        means = {k: self.sums[k] / self.counts[k] for k in self.sums}
        self.sums.clear()
        self.counts.clear()
        return means


class Runner:
    """Drive an :class:`~rlpipe.algos.Algorithm` to a frame budget.

    Shows a progress bar (frames/s, latest training episode return, last eval), evaluates
    the greedy policy every ``eval_every`` frames and at the end, logs ``train/``, ``eval/``
    and ``time/`` metrics through a TorchRL logger, and writes atomic checkpoints every
    ``checkpoint_every`` frames and at the end into ``<run_dir>/checkpoints`` (newest
    ``keep_checkpoints`` kept).
    """

    def __init__(
        self,
        algo: Algorithm,
        eval_env: EnvBase,
        run_dir: str | Path,
        *,
        total_frames: int,
        eval_every: int = 10_000,
        eval_episodes: int = 10,
        checkpoint_every: int = 25_000,
        keep_checkpoints: int = 3,
        logger: Logger | None = None,
        progress: bool = True,
        log_every: int = 1_000,
        extra_state: dict[str, Any] | None = None,
    ) -> None:
        self.algo = algo
        self.eval_env = eval_env
        self.run_dir = Path(run_dir)
        self.total_frames = total_frames
        self.eval_every = eval_every
        self.eval_episodes = eval_episodes
        self.checkpoint_every = checkpoint_every
        self.keep_checkpoints = keep_checkpoints
        self.logger = logger
        self.progress = progress
        self.log_every = log_every
        self.extra_state = extra_state or {}
        self.last_eval: EvalResult | None = None
        self._start = time.perf_counter()
        self._eval_seconds = 0.0

    def run(self) -> RunResult:
        """Train until ``total_frames``; return the final evaluation and timings."""
        start = self._start = time.perf_counter()
        window = _Window()
        next_log, next_eval, next_ckpt = (
            _next_multiple(self.algo.frames, every)
            for every in (self.log_every, self.eval_every, self.checkpoint_every)
        )
        last_return = math.nan
        window_start, window_frames = time.perf_counter(), self.algo.frames
        bar = tqdm(
            total=self.total_frames,
            initial=self.algo.frames,
            unit="frame",
            unit_scale=True,
            disable=not self.progress,
            dynamic_ncols=True,
            mininterval=0.5,
        )
        try:
            while self.algo.frames < self.total_frames:
                before = self.algo.frames
                metrics = self.algo.train_step()
                bar.update(self.algo.frames - before)
                last_return = self._record(metrics, window, last_return)
                frames = self.algo.frames
                if frames >= next_log:
                    now = time.perf_counter()
                    scalars = window.pop()
                    scalars["time/fps"] = (frames - window_frames) / max(now - window_start, 1e-9)
                    scalars["time/elapsed"] = now - start
                    self._log(scalars)
                    window_start, window_frames = now, frames
                    next_log = _next_multiple(frames, self.log_every)
                    bar.set_postfix(self._postfix(scalars["time/fps"], last_return), refresh=False)
                if self.eval_every and frames >= next_eval and frames < self.total_frames:
                    self._evaluate()
                    next_eval = _next_multiple(frames, self.eval_every)
                if self.checkpoint_every and frames >= next_ckpt and frames < self.total_frames:
                    self.save()
                    next_ckpt = _next_multiple(frames, self.checkpoint_every)
            self._evaluate()
            self.save()
        finally:
            bar.close()
        result = RunResult(
            eval_mean=self.last_eval.mean,
            eval_std=self.last_eval.std,
            eval_episodes=len(self.last_eval.returns),
            frames=self.algo.frames,
            wall_time=time.perf_counter() - start,
            run_dir=str(self.run_dir),
        )
        (self.run_dir / "summary.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
        return result

    def save(self) -> Path:
        """Write a checkpoint of the algorithm's state (plus ``extra_state``) now."""
        state = {"algo": self.algo.state_dict(), "frames": self.algo.frames, **self.extra_state}
        path = checkpoint_path(self.run_dir / "checkpoints", self.algo.frames)
        return save_checkpoint(state, path, keep=self.keep_checkpoints)

    def _record(self, metrics: Metrics, window: _Window, last_return: float) -> float:
        for key, value in metrics.items():
            if isinstance(value, list):
                for item in value:
                    self._log({key: item})
                if key == "train/episode_return" and value:
                    last_return = value[-1]
            else:
                window.add(key, value)
        return last_return

    def _evaluate(self) -> None:
        start = time.perf_counter()
        self.last_eval = evaluate(self.algo.policy, self.eval_env, self.eval_episodes)
        scalars = self.last_eval.metrics()
        scalars["time/eval_seconds"] = time.perf_counter() - start
        # wall time spent training so far, evaluations excluded
        scalars["time/train_seconds"] = start - self._start - self._eval_seconds
        self._eval_seconds += scalars["time/eval_seconds"]
        self._log(scalars)

    def _log(self, scalars: dict[str, float]) -> None:
        if self.logger is not None:
            for key, value in scalars.items():
                self.logger.log_scalar(key, value, step=self.algo.frames)

    def _postfix(self, fps: float, last_return: float) -> dict[str, str]:
        postfix = {"fps": f"{fps:,.0f}", "ep_return": f"{last_return:.1f}"}
        if self.last_eval is not None:
            postfix["eval"] = f"{self.last_eval.mean:.1f}±{self.last_eval.std:.1f}"
        return postfix


def _next_multiple(frames: int, every: int) -> float:
    """The first multiple of ``every`` strictly above ``frames`` (``every == 0``: never)."""
    if every <= 0:
        return math.inf
    return (frames // every + 1) * every
