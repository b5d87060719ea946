"""The SB3 side of benchmarks/presets.py: SB3 (or sb3-contrib's ARS) with the RL Zoo's settings.

A spawned process with one torch thread trains ``Preset.sb3_algo`` on the preset's env, seed and
frame budget, with the preset's eval cadence and episodes (greedy, vectorised eval envs, eval
time off the training clock; observations through the Zoo's ``VecNormalize`` statistics where it
normalises them), then the same final greedy eval as ``rlpipe.evaluate``. Its results go to
``<out>/sb3.json`` with the machine and load it ran on; a later call reads them back. Hours-long
presets save at every eval (model, replay buffer, normaliser) under ``sb3-saves/`` and a call
with the same ``--out`` continues from the newest save, training clock included, its noise and
episodes seeded afresh (:func:`resume_seed`). ARS's saves hold no replay buffer (a policy and a
normaliser: tens of KB), so git keeps them beside the records (``.gitignore``) and a seed
continues on another machine; a run's saves go once its record is written.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from presets_runs import Run, record, recorded
from presets_stop import RUNS, Stopped, own_session
from presets_table import Preset

from rlpipe.cadence import Cadence
from rlpipe.config import Config
from rlpipe.episodes import EVALUATION, FINAL, episode_quotas, episodes_seed, eval_envs
from rlpipe.files import write_atomic


@dataclass(frozen=True)
class Sb3Job:
    """What the SB3 process trains: the preset's env, budget, eval cadence and Zoo settings."""

    env: str
    seed: int
    frames: int
    eval_every: int
    eval_episodes: int
    final_episodes: int
    kwargs: dict[str, Any]
    algo: str = "DQN"
    policy: str = "MlpPolicy"
    n_envs: int = 1
    normalize: bool = False
    save_dir: str | None = None  # resumable: the saves at every eval go here


def greedy_returns(
    model: Any, envs: Any, episodes: int, seed: int, normalize: Callable | None = None
) -> list[float]:
    """Returns of ``episodes`` greedy episodes on a gymnasium vector env (observations through
    ``normalize`` first, if given), counted as :func:`rlpipe.episodes.evaluate` counts them (a
    fixed quota per env copy)."""
    n = envs.num_envs
    quotas = episode_quotas(n, episodes).numpy()
    obs, _ = envs.reset(seed=seed)
    running, returns = np.zeros(n), []
    while (quotas > 0).any():
        action, _ = model.predict(obs if normalize is None else normalize(obs), deterministic=True)
        obs, reward, terminated, truncated, _ = envs.step(action)
        running += reward  # an autoreset step's reward is 0
        done = terminated | truncated
        counted = done & (quotas > 0)
        returns += running[counted].tolist()
        quotas -= counted
        running[done] = 0.0
    return returns


@dataclass
class Sb3Save:
    """One save of an SB3 run: its model, replay buffer (off-policy), observation normaliser
    (where the Zoo normalises) and its evals so far."""

    model: Path
    replay: Path
    normalizer: Path
    evals: list[Any]


class Sb3Saves:
    """An SB3 run's saves, one dir each (``<frames>/``); ``progress.json`` names the newest
    complete one, and is replaced only once that save is on disk, so a kill at any point
    leaves the previous save to resume from."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.progress = root / "progress.json"

    def newest(self) -> Sb3Save | None:
        if not self.progress.is_file():
            return None
        saved = json.loads(self.progress.read_text())
        where = self.root / saved["dir"]
        return Sb3Save(
            where / "model.zip", where / "replay.pkl", where / "normalizer.pkl", saved["evals"]
        )

    def save(self, model: Any, evals: list[Any]) -> None:
        frames = str(model.num_timesteps)
        where = self.root / frames
        where.mkdir(parents=True, exist_ok=True)
        model.save(where / "model.zip")
        if hasattr(model, "save_replay_buffer"):
            model.save_replay_buffer(where / "replay.pkl")
        normalizer = getattr(model, "get_vec_normalize_env", lambda: None)()
        if normalizer is not None:
            normalizer.save(where / "normalizer.pkl")
        write_atomic(self.progress, json.dumps({"dir": frames, "evals": evals}).encode())
        for old in self.root.iterdir():  # earlier saves: the newest is all a resume needs
            if old.is_dir() and old.name != frames:
                shutil.rmtree(old)


def resume_seed(seed: int, frames: int) -> int:
    """The seed of a run resumed at ``frames``. SB3's ``load`` seeds the noise and the env anew
    from the run's own seed, which would replay the run's first draws after every resume."""
    return int(np.random.SeedSequence(seed, spawn_key=(frames,)).generate_state(1)[0])


def end_with(parent: int, every: float = 1.0) -> None:
    """End this process once ``parent`` is gone (its benchmark killed, not stopped), so no SB3 run
    trains on unseen for hours; a kill is safe for its saves (:class:`Sb3Saves`)."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(every)
        os._exit(1)

    threading.Thread(target=watch, daemon=True).start()


def run_sb3(job: Sb3Job, parent: int | None = None) -> dict[str, Any]:
    """Train SB3's ``job.algo`` as ``job`` says (one torch thread), ending if ``parent`` (the
    benchmark's pid, if given) goes; evals and the final eval's mean."""
    import gymnasium as gym
    import sb3_contrib
    import stable_baselines3
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    if parent is not None:
        end_with(parent)
    torch.set_num_threads(1)

    class GreedyEval(BaseCallback):
        """A greedy eval at the preset's cadence, then a save if resumable; eval and save time
        are kept off the training clock, which continues from ``seconds`` on a resumed run."""

        def __init__(
            self, saves: Sb3Saves | None, evals: list[Any], seconds: float, frames: int
        ) -> None:
            super().__init__()
            self.envs = gym.make_vec(job.env, num_envs=eval_envs(job.eval_episodes))
            self.cadence = Cadence(job.eval_every, frames)
            self.saves, self.evals, self.seconds = saves, [tuple(e) for e in evals], seconds
            self.start, self.off_clock = time.perf_counter(), 0.0

        def _on_training_start(self) -> None:
            self.start = time.perf_counter()

        def _on_step(self) -> bool:
            if self.cadence.due(self.num_timesteps):
                self.evaluate()
            return True

        def evaluate(self) -> None:
            t0 = time.perf_counter()
            seed = episodes_seed(job.seed, EVALUATION, self.num_timesteps)  # as rlpipe's runner
            returns = greedy_returns(self.model, self.envs, job.eval_episodes, seed, normalized)
            trained = self.seconds + t0 - self.start - self.off_clock
            self.evals.append((self.num_timesteps, float(np.mean(returns)), trained))
            if self.saves is not None:  # an hours-long run: a line at each save
                self.saves.save(self.model, self.evals)
                print(
                    f"presets: SB3 saved at {self.num_timesteps:,} of {job.frames:,} frames "
                    f"(eval {self.evals[-1][1]:.1f}, {trained:,.0f} s of training) in "
                    f"{self.saves.root}",
                    file=sys.stderr,
                    flush=True,
                )
            self.off_clock += time.perf_counter() - t0

    def normalized(obs: np.ndarray) -> np.ndarray:
        """Observations as the policy sees them in training (the Zoo's VecNormalize, if any)."""
        return obs if not job.normalize else model.get_vec_normalize_env().normalize_obs(obs)

    env = make_vec_env(job.env, n_envs=job.n_envs, seed=job.seed)
    algo = getattr(sb3_contrib if job.algo == "ARS" else stable_baselines3, job.algo)
    saves = Sb3Saves(Path(job.save_dir)) if job.save_dir else None
    progress = saves.newest() if saves else None
    if progress is None:
        if job.normalize:
            env = VecNormalize(env, norm_obs=True, norm_reward=False)
        model = algo(job.policy, env, seed=job.seed, device="cpu", **job.kwargs)
        callback = GreedyEval(saves, [], 0.0, 0)
    else:
        if job.normalize:
            env = VecNormalize.load(str(progress.normalizer), env)
        model = algo.load(progress.model, env=env, device="cpu")
        model.set_random_seed(resume_seed(job.seed, model.num_timesteps))
        if progress.replay.is_file():
            model.load_replay_buffer(progress.replay)
        callback = GreedyEval(saves, progress.evals, progress.evals[-1][2], model.num_timesteps)
    left = max(job.frames - model.num_timesteps, 0)
    model.learn(left, callback=callback, reset_num_timesteps=False)
    if not callback.evals or callback.evals[-1][0] != model.num_timesteps:
        callback.evaluate()  # like rlpipe's runner: always an eval at the end
    callback.envs.close()
    final_envs = gym.make_vec(job.env, num_envs=eval_envs(job.final_episodes))
    seed = episodes_seed(job.seed, FINAL)  # the starts of rlpipe's final eval
    final = greedy_returns(model, final_envs, job.final_episodes, seed, normalized)
    final_envs.close()
    return {"evals": callback.evals, "final": float(np.mean(final))}


def sb3_finished(out: Path) -> bool:
    """Whether ``out`` (a job's dir in ``--out``) holds a finished SB3 run."""
    return (out / "sb3.json").is_file()


def sb3_job(preset: Preset, cfg: Config, seed: int, episodes: int, out: Path) -> Run:
    """Run SB3 in a spawned process; its results also go to ``<out>/sb3.json``."""
    assert preset.sb3 is not None and cfg.total_frames is not None
    job = Sb3Job(
        preset.env,
        seed,
        cfg.total_frames,
        cfg.eval_every,
        cfg.eval_episodes,
        episodes,
        preset.sb3,
        preset.sb3_algo,
        preset.sb3_policy,
        preset.sb3_envs,
        preset.sb3_normalize,
        str(out / "sb3-saves") if preset.resumable else None,
    )
    saved = out / "sb3.json"
    reused = sb3_finished(out)  # a finished run of an earlier call with this --out
    if reused:
        result = json.loads(saved.read_text())
    else:
        start = os.getloadavg()[0]
        spawn = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(1, mp_context=spawn, initializer=own_session) as pool:
            with RUNS.starting():  # its process starts here: a stop under way sends it SIGINT
                future = pool.submit(run_sb3, job, os.getpid())
            try:
                result = record(saved, start, **future.result())
            except KeyboardInterrupt as e:  # the stop's SIGINT, in the SB3 process
                raise Stopped("stopped") from e
        if job.save_dir is not None:  # never read again: the record is what a call reads back
            shutil.rmtree(job.save_dir, ignore_errors=True)
    evals = [(int(f), float(m), float(s)) for f, m, s in result["evals"]]
    return Run(
        preset.experiment, seed, "SB3", evals, result["final"], reused=reused, **recorded(result)
    )
