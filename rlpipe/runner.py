"""The one training loop every algorithm shares."""

from __future__ import annotations

import json
import math
import random
import signal
import time
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger
from tqdm.auto import tqdm

from rlpipe.algos.base import Algorithm, Metrics
from rlpipe.checkpoint import checkpoint_path, list_checkpoints, save_checkpoint
from rlpipe.errors import RlpipeError, check
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


class Interrupted(RlpipeError):
    """SIGINT or SIGTERM stopped the run after a final checkpoint (``exit_code``: 128 + signal)."""

    def __init__(self, signum: int, frames: int, checkpoint: Path) -> None:
        name = signal.Signals(signum).name
        super().__init__(
            f"{name} received: stopped at {frames:,} frames, checkpoint {checkpoint}; "
            f"resume with the same command plus resume={checkpoint.parent.parent}"
        )
        self.exit_code = 128 + signum


class Diverged(RlpipeError):
    """A loss or a parameter became NaN or infinite; no checkpoint is written after it."""


def rng_state() -> dict[str, Any]:
    """Python's, NumPy's and torch's global generator states, as checkpoint-safe containers."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {
        "python": random.getstate(),
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached],
        "torch": torch.get_rng_state(),
    }


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured."""
    random.setstate(state["python"])
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])


class Callback:
    """Hooks into a :class:`Runner`: override the ones you need (all do nothing by default)."""

    def on_eval(self, runner: Runner, result: EvalResult) -> None:
        """After each greedy evaluation (``runner.algo.frames`` frames in)."""

    def on_end(self, runner: Runner, result: RunResult) -> None:
        """After the final evaluation and checkpoint, before ``run`` returns."""


def check_budget(algo: Algorithm, total_frames: int | None) -> None:
    """A run needs ``total_frames`` unless the algorithm has a budget of its own."""
    check(
        total_frames is not None or algo.budget is not None,
        f"total_frames=null, but {type(algo).__name__} has no budget of its own "
        "(epochs, iterations): set total_frames=N",
    )


class Runner:
    """Drive an :class:`~rlpipe.algos.Algorithm` until ``total_frames`` frames or its own
    ``budget`` of iterations (REINFORCE epochs, ARS iterations), whichever comes first.

    Shows a progress bar (frames/s, latest training episode return, last eval), evaluates
    the greedy policy every ``eval_every`` frames and at the end, logs ``train/``, ``eval/``
    and ``time/`` metrics through a TorchRL logger, and writes atomic checkpoints every
    ``checkpoint_every`` frames and at the end into ``<run_dir>/checkpoints`` (newest
    ``keep_checkpoints`` kept). ``callbacks`` (:class:`Callback`) see every evaluation and the end.
    """

    def __init__(
        self,
        algo: Algorithm,
        eval_env: EnvBase,
        run_dir: str | Path,
        *,
        total_frames: int | None,
        eval_every: int = 10_000,
        eval_episodes: int = 10,
        checkpoint_every: int = 25_000,
        keep_checkpoints: int = 3,
        logger: Logger | None = None,
        progress: bool = True,
        log_every: int = 1_000,
        extra_state: dict[str, Any] | None = None,
        callbacks: Sequence[Callback] = (),
    ) -> None:
        check_budget(algo, total_frames)
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
        self.callbacks = list(callbacks)
        self.last_eval: EvalResult | None = None
        self._start = time.perf_counter()
        self._elapsed_before = 0.0  # wall seconds of the run before a resume
        self._eval_seconds = 0.0
        self._signal: int | None = None

    def run(self) -> RunResult:
        """Train until the budget is spent; return the final evaluation and timings.

        SIGINT/SIGTERM end the current iteration, write a checkpoint and raise
        :class:`Interrupted` (a second signal stops at once); a non-finite loss or parameter
        raises :class:`Diverged` without writing a checkpoint.
        """
        start = self._start = time.perf_counter() - self._elapsed_before
        handlers = self._catch_signals()
        window = _Window()
        next_log, next_eval, next_ckpt = (
            _next_multiple(self.algo.frames, every)
            for every in (self.log_every, self.eval_every, self.checkpoint_every)
        )
        last_return = math.nan
        window_start, window_frames = time.perf_counter(), self.algo.frames
        by_frames = self.total_frames is not None  # else the bar counts iterations
        bar = tqdm(
            total=self.total_frames if by_frames else self.algo.budget,
            initial=self.algo.frames if by_frames else self.algo.iterations,
            unit="frame" if by_frames else "it",
            unit_scale=True,
            disable=not self.progress,
            dynamic_ncols=True,
            mininterval=0.5,
        )
        try:
            while not self.finished:
                before = self.algo.frames if by_frames else self.algo.iterations
                metrics = self.algo.train_step()
                bar.update((self.algo.frames if by_frames else self.algo.iterations) - before)
                self._check_finite(metrics)
                last_return = self._record(metrics, window, last_return)
                frames = self.algo.frames
                if self._signal is not None:
                    raise Interrupted(self._signal, frames, self.save())
                if frames >= next_log:
                    now = time.perf_counter()
                    scalars = window.pop()
                    scalars["time/fps"] = (frames - window_frames) / max(now - window_start, 1e-9)
                    scalars["time/elapsed"] = now - start
                    self._log(scalars)
                    window_start, window_frames = now, frames
                    next_log = _next_multiple(frames, self.log_every)
                    bar.set_postfix(self._postfix(scalars["time/fps"], last_return), refresh=False)
                if self.eval_every and frames >= next_eval and not self.finished:
                    self._evaluate()
                    next_eval = _next_multiple(frames, self.eval_every)
                if self.checkpoint_every and frames >= next_ckpt and not self.finished:
                    self.save()
                    next_ckpt = _next_multiple(frames, self.checkpoint_every)
            self._evaluate()
            self.save()
        finally:
            bar.close()
            for signum, handler in handlers.items():
                signal.signal(signum, handler)
        result = RunResult(
            eval_mean=self.last_eval.mean,
            eval_std=self.last_eval.std,
            eval_episodes=len(self.last_eval.returns),
            frames=self.algo.frames,
            wall_time=time.perf_counter() - start,
            run_dir=str(self.run_dir),
        )
        (self.run_dir / "summary.json").write_text(json.dumps(asdict(result), indent=2) + "\n")
        for callback in self.callbacks:
            callback.on_end(self, result)
        return result

    @property
    def finished(self) -> bool:
        """Whether the frame budget or the algorithm's own budget is spent."""
        algo = self.algo
        return (self.total_frames is not None and algo.frames >= self.total_frames) or (
            algo.budget is not None and algo.iterations >= algo.budget
        )

    def save(self) -> Path:
        """Write a checkpoint now: the algorithm's state, the global RNGs, the run's clocks and
        ``extra_state``."""
        state = {
            **self.extra_state,
            "algo": self.algo.state_dict(),
            "frames": self.algo.frames,
            "rng": rng_state(),
            "runner": {
                "elapsed": time.perf_counter() - self._start,
                "eval_seconds": self._eval_seconds,
            },
        }
        path = checkpoint_path(self.run_dir / "checkpoints", self.algo.frames)
        return save_checkpoint(state, path, keep=self.keep_checkpoints)

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint :meth:`save` wrote (algorithm, RNGs, clocks)."""
        self.algo.load_state_dict(state["algo"])
        set_rng_state(state["rng"])
        self._elapsed_before = float(state["runner"]["elapsed"])
        self._eval_seconds = float(state["runner"]["eval_seconds"])

    def _catch_signals(self) -> dict[int, Any]:
        """Route SIGINT/SIGTERM to a flag checked after each iteration (main thread only)."""

        def handle(signum: int, frame: Any) -> None:
            if self._signal is not None:  # a second signal: stop now
                signal.signal(signum, signal.SIG_DFL)
                signal.raise_signal(signum)
            self._signal = signum
            tqdm.write(f"rlpipe: {signal.Signals(signum).name}: checkpointing after this iteration")

        previous = {}
        try:
            for signum in (signal.SIGINT, signal.SIGTERM):
                previous[signum] = signal.signal(signum, handle)
        except ValueError:  # not the main thread: leave signals alone
            pass
        return previous

    def _check_finite(self, metrics: Metrics) -> None:
        bad = [k for k, v in metrics.items() if "loss" in k and not _all_finite(v)]
        if not bad and not all(bool(p.isfinite().all()) for p in self.algo.policy.parameters()):
            bad = ["policy parameters"]
        if bad:
            kept = list_checkpoints(self.run_dir / "checkpoints")
            raise Diverged(
                f"training diverged at {self.algo.frames:,} frames: {bad[0]} is not finite; "
                f"stopped without a new checkpoint (last good: "
                f"{kept[-1] if kept else 'none'}); try a smaller algo.lr"
            )

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
        for callback in self.callbacks:
            callback.on_eval(self, self.last_eval)

    def _log(self, scalars: dict[str, float]) -> None:
        if self.logger is None:
            return
        try:
            for key, value in scalars.items():
                self.logger.log_scalar(key, value, step=self.algo.frames)
        except OSError as err:
            raise RlpipeError(
                f"cannot write metrics in {self.run_dir}: {err.strerror or err}; free some disk "
                "space or pick a writable hydra.run.dir, then resume"
            ) from err

    def _postfix(self, fps: float, last_return: float) -> dict[str, str]:
        postfix = {"fps": f"{fps:,.0f}", "ep_return": f"{last_return:.1f}"}
        if self.last_eval is not None:
            postfix["eval"] = f"{self.last_eval.mean:.1f}±{self.last_eval.std:.1f}"
        return postfix


def _all_finite(value: float | list[float]) -> bool:
    return all(math.isfinite(v) for v in (value if isinstance(value, list) else [value]))


def _next_multiple(frames: int, every: int) -> float:
    """The first multiple of ``every`` strictly above ``frames`` (``every == 0``: never)."""
    if every <= 0:
        return math.inf
    return (frames // every + 1) * every
