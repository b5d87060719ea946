"""The one training loop every algorithm shares (:class:`Runner`), the hooks on it
(:class:`Callback`), and the narrow interface through which it writes its run dir
(:class:`RunStore`, which :class:`rlpipe.rundir.RunDir` implements)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

from torchrl.envs import EnvBase
from torchrl.record.loggers import Logger

from rlpipe import faults
from rlpipe.algos.base import EPISODE_FRAMES, EPISODE_RETURN, Algorithm, Metrics
from rlpipe.budget import check_budget, ended_short, no_evaluation_inside, spent
from rlpipe.cadence import Cadence, Window
from rlpipe.config import Config, config_to_dict
from rlpipe.console import say, warn
from rlpipe.episodes import EVALUATION, EvalResult, EvalStopped, episodes_seed, evaluate
from rlpipe.errors import RlpipeError, check
from rlpipe.outcomes import Diverged, Interrupted, RunResult, not_finite
from rlpipe.progress import ProgressBar
from rlpipe.runtime import rng_state, set_rng_state, set_threads
from rlpipe.signals import StopSignals


class RunStore(Protocol):
    """What the runner needs of its run directory (:class:`rlpipe.rundir.RunDir`)."""

    path: Path

    def session(
        self, config: Config | None, frames: int, keep: int
    ) -> AbstractContextManager[None]: ...

    def save_checkpoint(self, state: dict[str, Any], frames: int) -> Path: ...

    def save_best(self, state: dict[str, Any], frames: int) -> Path: ...

    def latest_checkpoint(self) -> Path | None: ...

    def read_summary(self) -> RunResult | None: ...

    def write_summary(self, result: RunResult) -> None: ...


class Callback:
    """Hooks into a :class:`Runner`: subclass and override the ones you need.

    Every hook does nothing by default; pass instances as ``Runner(..., callbacks=[...])``.
    """

    def on_eval(self, runner: Runner, result: EvalResult) -> None:
        """After each greedy evaluation (``runner.algo.frames`` frames in)."""

    def on_end(self, runner: Runner, result: RunResult) -> None:
        """After the final evaluation and checkpoint, before ``run`` returns."""

    def state_dict(self) -> dict[str, Any]:
        """What checkpoints keep of this callback (plain data), so that a resumed run goes on
        as the uninterrupted one would (nothing by default)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Take back what :meth:`state_dict` returned."""


class Runner:
    """The training loop: drives an :class:`~rlpipe.algos.Algorithm` until the run's end.

    The end: ``total_frames`` frames or the algorithm's own ``budget`` of iterations, whichever
    comes first. Shows a progress bar, evaluates the greedy policy every ``eval_every`` frames
    and at the end (``eval_env`` seeded before each from ``eval_seed`` and the frames, by
    :func:`~rlpipe.episodes.episodes_seed`: fresh starts at every evaluation, the same ones in a
    resumed run), logs ``train/``, ``eval/`` and ``time/`` metrics through a TorchRL logger,
    and checkpoints every ``checkpoint_every`` frames, at the end (newest ``keep_checkpoints``
    kept) and at every best evaluation, through ``run_dir`` (a :class:`RunStore`:
    ``rlpipe.RunDir(path)``), held for the whole run.
    ``callbacks`` (:class:`Callback`) see every evaluation and the end.

    ``config`` (a :class:`~rlpipe.config.Config`; left out: the algorithm's own record,
    :meth:`~rlpipe.algos.base.Algorithm.run_config`) goes to ``config.yaml`` and every
    checkpoint, so ``load_run``, ``rlpipe.evaluate``, ``rlpipe.plot`` and resumes work on the
    run. Its ``threads`` (``"auto"`` without one) set torch's intra-op threads when the runner
    is built: a hand-built run trains as fast as ``train`` runs it.
    """

    def __init__(
        self,
        algo: Algorithm,
        eval_env: EnvBase,
        run_dir: RunStore,
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
        config: Config | None = None,
        eval_seed: int | None = None,
    ) -> None:
        check(
            isinstance(algo, Algorithm),
            f"the Runner drives subclasses of rlpipe.Algorithm; {type(algo).__name__} is not one",
        )
        check(
            not isinstance(run_dir, (str, Path)),
            f"the Runner writes through a run dir object: Runner(algo, eval_env, "
            f"rlpipe.RunDir({str(run_dir)!r}), ...)",
        )
        check_budget(algo, total_frames)
        run_keys = dict(
            total_frames=total_frames,
            eval_every=eval_every,
            eval_episodes=eval_episodes,
            checkpoint_every=checkpoint_every,
        )
        # what config.yaml records: given, or the algorithm's own record of its config
        self.config = config or algo.run_config(
            **run_keys, keep_checkpoints=keep_checkpoints, progress=progress
        )
        set_threads("auto" if self.config is None else self.config.threads, algo.device)
        self.algo = algo
        self.eval_env = eval_env
        self.store = run_dir
        self.run_dir = run_dir.path
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
        self.eval_seed = eval_seed
        self.last_eval: EvalResult | None = None
        self._start = time.perf_counter()
        self._elapsed_before = 0.0  # wall seconds of the run before a resume
        self._eval_seconds = 0.0
        self._elapsed_at = -1  # frames of the last time/elapsed row (one row per frames)
        self._best = -math.inf  # the best evaluation's mean so far (checkpoints/best_*.pt)
        self._signals = StopSignals(on_stop=algo.request_stop)  # a long iteration may end early
        self._pending_eval = False  # an evaluation a signal cut short, to run first on resume
        self._last_return = math.nan  # of the latest finished training episode
        self._window = Window()  # scalars since the last log flush
        self._window_start, self._window_frames = self._start, 0

    def run(self) -> RunResult:
        """Train until the budget is spent; return the final evaluation and timings.

        SIGINT/SIGTERM end the current iteration (or evaluation), write a checkpoint and raise
        :class:`Interrupted` (a second signal stops at once); a non-finite loss or parameter
        raises :class:`Diverged` without writing a checkpoint. A run resumed after its final
        checkpoint trains, evaluates and logs nothing: it reports the result it had.
        """
        with self.store.session(self.config, self.algo.frames, self.keep_checkpoints):
            if self.finished and not self._pending_eval:
                stored = self._stored_summary()
                if stored is not None or self.last_eval is not None:
                    return self._finished_before(stored)
            warn(no_evaluation_inside(self.algo, self.total_frames, self.eval_every))
            return self._loop()

    def _loop(self) -> RunResult:
        """Train, evaluate and checkpoint to the end of the budget; the summary and callbacks."""
        self.algo.request_stop(False)
        self.algo.limit_frames(self.total_frames)  # it can end its last batch at the budget
        start = self._start = time.perf_counter() - self._elapsed_before
        frames = self.algo.frames
        log, evaluation, checkpoint = (
            Cadence(every, frames)
            for every in (self.log_every, self.eval_every, self.checkpoint_every)
        )
        self._window_start, self._window_frames = time.perf_counter(), frames
        bar = ProgressBar(self.algo, self.total_frames, enabled=self.progress)
        with bar, self._signals as signals:
            if self._pending_eval and not self.finished:  # the one a signal cut short
                self._evaluate()
            while not self.finished:
                metrics = self.algo.train_step()
                bar.advance()
                faults.point("train_step")
                self._check_finite(metrics)
                self._record(metrics)
                frames = self.algo.frames
                if log.due(frames):
                    self._flush()
                    bar.show(self._last_return, self.last_eval)
                if not self.finished and evaluation.due(frames):
                    self._evaluate()
                due = not self.finished and checkpoint.due(frames)
                if signals.received is not None and not self.finished:  # (at the end: below)
                    raise Interrupted(signals.received, frames, self.save(interrupted=not due))
                if due:
                    self.save()
                    self.algo.restart_episodes()  # as a run resumed from this checkpoint does
            warn(ended_short(self.algo, self.total_frames))
            self._evaluate()
            bar.show(self._last_return, self.last_eval)  # the bar ends on the final evaluation
            if signals.received is not None:
                raise Interrupted(signals.received, self.algo.frames, self.save())
            self.save()
            faults.point("final_checkpoint")
        return self._finish(time.perf_counter() - start)

    def _finished_before(self, stored: RunResult | None) -> RunResult:
        """The result of a run resumed at (or past) its budget: its ``summary.json``, or, when
        a kill came between the final checkpoint and the summary, the final evaluation the
        checkpoint holds (then the summary is written and the callbacks run)."""
        say(
            f"rlpipe: {self.run_dir} already finished at {self.algo.frames:,} frames; "
            "raise total_frames to train it further"
        )
        if stored is not None:
            return stored
        return self._finish(self._elapsed_before)

    def _finish(self, wall_time: float) -> RunResult:
        """The run's result from its last evaluation: ``summary.json``, then the callbacks."""
        result = RunResult(
            eval_mean=self.last_eval.mean,
            eval_std=self.last_eval.std,
            eval_episodes=len(self.last_eval.returns),
            frames=self.algo.frames,
            wall_time=wall_time,
            run_dir=str(self.run_dir),
        )
        self.store.write_summary(result)
        for callback in self.callbacks:
            callback.on_end(self, result)
        return result

    def _stored_summary(self) -> RunResult | None:
        """``summary.json`` when it reports the frames the algorithm is at."""
        result = self.store.read_summary()
        return result if result is not None and result.frames == self.algo.frames else None

    @property
    def finished(self) -> bool:
        """Whether the frame budget or the algorithm's own budget is spent."""
        return spent(self.algo, self.total_frames)

    def save(self, *, interrupted: bool = False) -> Path:
        """Write a checkpoint now: the algorithm's state, the global RNGs, the run's clocks, the
        last evaluation, the callbacks' state and ``extra_state``. Metrics not yet logged are
        logged first, so the CSVs hold every row up to the checkpoint's frames; ``interrupted``
        (a signal's checkpoint where no checkpoint was due): they are kept in the checkpoint
        instead, so that the resumed run logs the rows an uninterrupted one does."""
        self._check_finite()  # no checkpoint of a diverged policy
        if self._window.sums and not interrupted:
            self._flush()
        return self.store.save_checkpoint(self._state(), self.algo.frames)

    def _state(self) -> dict[str, Any]:
        """What a checkpoint holds (see :meth:`save`)."""
        return {
            **self.extra_state,
            **({} if self.config is None else {"config": config_to_dict(self.config)}),
            "algo": self.algo.state_dict(),
            "frames": self.algo.frames,
            "rng": rng_state(),
            "runner": {
                "elapsed": time.perf_counter() - self._start,
                "eval_seconds": self._eval_seconds,
                "last_eval": None if self.last_eval is None else asdict(self.last_eval),
                "pending_eval": self._pending_eval,
                "elapsed_at": self._elapsed_at,
                "best_eval": self._best,
                "window": self._window.state(),
                "callbacks": {type(c).__name__: c.state_dict() for c in self.callbacks},
            },
        }

    def _keep_best(self) -> None:
        """After an evaluation better than every earlier one: its checkpoint as
        ``checkpoints/best_<frames>.pt`` (``checkpoint=best``), the previous best removed."""
        if self.last_eval is None or not self.last_eval.mean > self._best:
            return
        self._best = self.last_eval.mean
        self.store.save_best(self._state(), self.algo.frames)

    def restore(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint :meth:`save` wrote (algorithm, RNGs, clocks, last
        evaluation)."""
        if not (type(state["frames"]) is int and state["frames"] >= 0):
            raise ValueError(f"frames must be a whole number >= 0, got {state['frames']!r}")
        self.algo.load_state_dict(state["algo"])
        if self.algo.frames != state["frames"]:
            raise ValueError("the algorithm's frames disagree with the checkpoint's")
        set_rng_state(state["rng"])
        runner = state["runner"]
        self._elapsed_before = float(runner["elapsed"])
        self._eval_seconds = float(runner["eval_seconds"])
        last = runner.get("last_eval")
        self.last_eval = None if last is None else EvalResult(**last)
        self._pending_eval = bool(runner.get("pending_eval", False))
        self._elapsed_at = int(runner.get("elapsed_at", -1))
        self._best = float(runner.get("best_eval", -math.inf))
        self._window.load(runner.get("window", {}))
        states = runner.get("callbacks", {})
        for callback in self.callbacks:
            callback.load_state_dict(states.get(type(callback).__name__, {}))
        self.algo.restart_episodes()  # fresh episodes, as the run did at this checkpoint

    def _stop_requested(self) -> bool:
        return self._signals.received is not None

    def _flush(self) -> None:
        """Log the window's means with the frame rate and elapsed time."""
        now, frames = time.perf_counter(), self.algo.frames
        scalars = self._window.pop()
        scalars["time/fps"] = (frames - self._window_frames) / max(now - self._window_start, 1e-9)
        self._log({**scalars, **self._elapsed(now)})
        self._window_start, self._window_frames = now, frames

    def _check_finite(self, metrics: Metrics | None = None) -> None:
        """Raise :class:`Diverged` on a non-finite metric of the iteration or, with ``metrics``
        None (before checkpoints and evaluations), a non-finite policy parameter."""
        bad = not_finite(metrics, self.algo.finite_keys, self.algo.policy.parameters())
        if bad is not None:
            raise Diverged(
                f"training diverged at {self.algo.frames:,} frames: {bad} is not finite; "
                f"stopped without a new checkpoint (last good: "
                f"{self.store.latest_checkpoint() or 'none'}); {self.algo.divergence_hint}"
            )

    def _record(self, metrics: Metrics) -> None:
        """Log per-event lists row by row (episodes at the frame they ended, where the algorithm
        says it); add scalars to the logging window."""
        ended = metrics.get(EPISODE_FRAMES)
        for key, value in metrics.items():
            if key == EPISODE_FRAMES:
                continue
            if isinstance(value, list):
                steps = ended if ended is not None and len(ended) == len(value) else None
                for i, item in enumerate(value):
                    self._log({key: item}, None if steps is None else steps[i])
                if key == EPISODE_RETURN and value:
                    self._last_return = value[-1]
            else:
                self._window.add(key, value)

    def _evaluate(self) -> None:
        """Evaluate and log; a signal aborts it (it then runs first when the run resumes)."""
        self._check_finite()
        start = time.perf_counter()
        if self.eval_seed is not None:
            self.eval_env.set_seed(episodes_seed(self.eval_seed, EVALUATION, self.algo.frames))
        try:
            result = evaluate(
                self.algo.policy, self.eval_env, self.eval_episodes, self._stop_requested
            )
        except EvalStopped:
            self._pending_eval = True
            self._eval_seconds += time.perf_counter() - start
            return
        self.last_eval, self._pending_eval = result, False
        scalars = self.last_eval.metrics()
        scalars["time/eval_seconds"] = time.perf_counter() - start
        # wall time spent training so far, evaluations excluded
        scalars["time/train_seconds"] = start - self._start - self._eval_seconds
        self._eval_seconds += scalars["time/eval_seconds"]
        self._log({**scalars, **self._elapsed(start)})
        self._keep_best()
        for callback in self.callbacks:
            callback.on_eval(self, self.last_eval)

    def _elapsed(self, now: float) -> dict[str, float]:
        """``time/elapsed`` (wall seconds of the run at ``now``) unless these frames have it:
        every log flush and every evaluation row carry one, each frame count once."""
        if self.algo.frames == self._elapsed_at:
            return {}
        self._elapsed_at = self.algo.frames
        return {"time/elapsed": now - self._start}

    def _log(self, scalars: dict[str, float], step: int | None = None) -> None:
        """Log ``scalars`` at ``step`` frames (default: the frames so far)."""
        if self.logger is None:
            return
        step = self.algo.frames if step is None else step
        try:
            for key, value in scalars.items():
                self.logger.log_scalar(key, value, step=step)
        except OSError as err:
            raise RlpipeError(
                f"cannot write metrics in {self.run_dir}: {err.strerror or err}; free some disk "
                "space or pick a writable hydra.run.dir, then resume"
            ) from err
