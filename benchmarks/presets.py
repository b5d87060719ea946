"""Every tuned preset over seeds: one Markdown table (and, with ``--sb3``, SB3 + RL Zoo beside it).

Each rlpipe run is exactly what a user runs, in a subprocess (``SDL_VIDEODRIVER=dummy``):

    python -m rlpipe +experiment=<preset> seed=<s> progress=false checkpoint_every=0 \
        hydra.run.dir=<dir> [total_frames=<--frames>]
    python -m rlpipe.evaluate run_dir=<dir> episodes=<final episodes>

then its ``metrics/scalars/eval/return_mean.csv`` and ``time/train_seconds.csv`` give the
frames and training seconds (evaluation excluded) at the first eval reaching the target, the mean
of the last three evals and the final frames; ``evaluation/trained-*.json`` the final greedy
eval. With ``--sb3``, presets that have RL Zoo hyper-parameters also train Stable-Baselines3's
DQN, PPO or SAC (a spawned process, one torch thread) on the same seed with the preset's eval
cadence and episodes (greedy, vectorised eval envs, eval time off the clock), then the same final
eval.
``--jobs`` runs go at once; rlpipe seed s and SB3 seed s start side by side. Runs that an earlier
call finished in ``--out`` are read instead of run again, so an interrupted benchmark continues
and a table can be made again from its runs. The hours-long presets (``sac_bipedal``) also save
at every eval on both sides (rlpipe's checkpoints; SB3's model and replay buffer under
``sb3-saves/``), so a call with the same ``--out`` continues an interrupted run from its last
eval, training clocks included.

    pip install -e ".[dev,bench]"
    python benchmarks/presets.py --sb3 --append BENCHMARKS.md             # everything (long)
    python benchmarks/presets.py --presets dqn_cartpole --sb3             # the tuned CartPole DQN
    python benchmarks/presets.py --presets dqn_cartpole --seeds 0 --frames 2000 \
        --final-episodes 5 --sb3                                          # smoke test
"""

from __future__ import annotations

import importlib.resources
import importlib.util
import json
import multiprocessing
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from common import compose_run, machine, parser, publish, read_scalar, table

from rlpipe.cadence import Cadence
from rlpipe.config import Config
from rlpipe.episodes import episode_quotas, eval_envs

PACKAGES = ["torch", "torchrl", "tensordict", "gymnasium", "stable_baselines3"]
NET_256 = dict(net_arch=[256, 256])


@dataclass(frozen=True)
class Preset:
    """One tuned preset (``+experiment=<experiment>``) and the bar it is measured against."""

    experiment: str
    env: str
    target: float  # "frames to target": the first eval >= target
    final_episodes: int  # episodes of the final greedy eval
    zoo: float | None = None  # the RL Zoo's figure; None: the target is the bar
    budget_text: str = ""  # the budget of the Zoo figure (or of the target)
    solved: float | None = None  # solved: last-three-evals mean >= this (None: the target)
    seeds: tuple[int, ...] = (0, 1, 2)  # seeds when --seeds is not given
    sb3: dict[str, Any] | None = None  # SB3 keyword arguments (RL Zoo's hyperparams/<algo>.yml)
    sb3_algo: str = "DQN"  # the SB3 class they are for
    sb3_envs: int = 1  # the Zoo's n_envs
    # hours-long presets: both sides save at every eval, and a call that finds an interrupted
    # run in --out continues it (rlpipe from its newest checkpoint, SB3 from its newest save)
    resumable: bool = False

    @property
    def solved_bar(self) -> float:
        return self.target if self.solved is None else self.solved

    @property
    def final_bar(self) -> float:
        """The bar the final evals are counted against: the Zoo figure, else the solved bar."""
        return self.solved_bar if self.zoo is None else self.zoo


class linear:  # noqa: N801 (named as the Zoo's lin_<start>)
    """The RL Zoo's ``lin_<start>`` schedule: ``start`` annealed linearly to 0 (picklable)."""

    def __init__(self, start: float) -> None:
        self.start = start

    def __call__(self, progress_remaining: float) -> float:
        return progress_remaining * self.start

    def __repr__(self) -> str:
        return f"lin_{self.start:g}"


PRESETS: dict[str, Preset] = {
    "dqn_cartpole": Preset(
        "dqn_cartpole",
        "CartPole-v1",
        target=500.0,
        solved=475.0,
        final_episodes=20,
        seeds=(0, 1, 2, 3, 4),
        sb3=dict(
            learning_rate=2.3e-3,
            batch_size=64,
            buffer_size=100_000,
            learning_starts=1000,
            gamma=0.99,
            target_update_interval=10,
            train_freq=256,
            gradient_steps=128,
            exploration_fraction=0.16,
            exploration_final_eps=0.04,
            policy_kwargs=NET_256,
        ),
    ),
    "dqn_mountaincar": Preset(
        "dqn_mountaincar",
        "MountainCar-v0",
        target=-100.8,
        final_episodes=100,
        zoo=-100.8,
        budget_text="120k steps",
        sb3=dict(
            learning_rate=4e-3,
            batch_size=128,
            buffer_size=10_000,
            learning_starts=1000,
            gamma=0.98,
            target_update_interval=600,
            train_freq=16,
            gradient_steps=8,
            exploration_fraction=0.2,
            exploration_final_eps=0.07,
            policy_kwargs=NET_256,
        ),
    ),
    "dqn_lunarlander": Preset(
        "dqn_lunarlander",
        "LunarLander-v3",
        target=154.4,
        final_episodes=100,
        zoo=154.4,
        budget_text="100k steps, measured on v2",
        sb3=dict(
            learning_rate=6.3e-4,
            batch_size=128,
            buffer_size=50_000,
            learning_starts=0,
            gamma=0.99,
            target_update_interval=250,
            train_freq=4,
            gradient_steps=-1,
            exploration_fraction=0.12,
            exploration_final_eps=0.1,
            policy_kwargs=NET_256,
        ),
    ),
    "ars_pendulum": Preset(
        "ars_pendulum",
        "Pendulum-v1",
        target=-212.5,
        final_episodes=100,
        zoo=-212.5,
        budget_text="2M steps",
    ),
    "ars_cartpole": Preset(
        "ars_cartpole",
        "CartPole-v1",
        target=500.0,
        solved=475.0,
        final_episodes=20,
        budget_text="≤ 50k steps",
    ),
    "ars_bipedal": Preset("ars_bipedal", "BipedalWalker-v3", target=300.0, final_episodes=100),
    "ppo_cartpole": Preset(
        "ppo_cartpole",
        "CartPole-v1",
        target=500.0,
        solved=475.0,
        final_episodes=100,
        zoo=500.0,
        budget_text="100k steps",
        sb3=dict(
            n_steps=32,
            batch_size=256,
            gae_lambda=0.8,
            gamma=0.98,
            n_epochs=20,
            ent_coef=0.0,
            learning_rate=linear(1e-3),
            clip_range=linear(0.2),
        ),
        sb3_algo="PPO",
        sb3_envs=8,
    ),
    "sac_pendulum": Preset(
        "sac_pendulum",
        "Pendulum-v1",
        target=-157.0,
        final_episodes=100,
        zoo=-157.0,
        budget_text="20k steps",
        sb3=dict(learning_rate=1e-3),
        sb3_algo="SAC",
    ),
    "sac_bipedal": Preset(
        "sac_bipedal",
        "BipedalWalker-v3",
        target=297.7,
        final_episodes=100,
        zoo=297.7,
        budget_text="500k steps",
        sb3=dict(
            learning_rate=7.3e-4,
            buffer_size=300_000,
            batch_size=256,
            ent_coef="auto",
            gamma=0.98,
            tau=0.02,
            train_freq=64,
            gradient_steps=64,
            learning_starts=10_000,
            use_sde=True,
            policy_kwargs=dict(log_std_init=-3, net_arch=[400, 300]),
        ),
        sb3_algo="SAC",
        resumable=True,  # ~2.5 h per seed and side on 2 cores
    ),
}


@dataclass
class Run:
    """One finished (or failed) run: its evals as (frames, mean, training seconds) rows."""

    preset: str
    seed: int
    which: str  # "rlpipe" or "SB3"
    evals: list[tuple[int, float, float]] = field(default_factory=list)
    final: float | None = None  # the final greedy eval's mean
    seconds: float = 0.0  # wall seconds of the whole job (training, evals, start-up)
    error: str | None = None
    reused: bool = False  # read from an earlier call's --out, not run by this one

    def hit(self, target: float) -> tuple[int, float] | None:
        """(frames, training seconds) of the first eval reaching ``target``."""
        return next(((f, s) for f, m, s in self.evals if m >= target - 1e-6), None)

    @property
    def train_seconds(self) -> float | None:
        """Training seconds of the whole run (evaluations excluded): at its last eval."""
        return self.evals[-1][2] if self.evals else None

    @property
    def last_three(self) -> float | None:
        return float(np.mean([m for _, m, _ in self.evals[-3:]])) if self.evals else None


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
    n_envs: int = 1
    save_dir: str | None = None  # resumable: the saves at every eval go here


def greedy_returns(model: Any, envs: Any, episodes: int, seed: int) -> list[float]:
    """Returns of ``episodes`` greedy episodes on a gymnasium vector env, counted as
    :func:`rlpipe.episodes.evaluate` counts them (a fixed quota per env copy)."""
    n = envs.num_envs
    quotas = episode_quotas(n, episodes).numpy()
    obs, _ = envs.reset(seed=seed)
    running, returns = np.zeros(n), []
    while (quotas > 0).any():
        action, _ = model.predict(obs, deterministic=True)
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
    """One save of an SB3 run: its model, its replay buffer (off-policy) and its evals so far."""

    model: Path
    replay: Path
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
        return Sb3Save(where / "model.zip", where / "replay.pkl", saved["evals"])

    def save(self, model: Any, evals: list[Any]) -> None:
        frames = str(model.num_timesteps)
        where = self.root / frames
        where.mkdir(parents=True, exist_ok=True)
        model.save(where / "model.zip")
        if hasattr(model, "save_replay_buffer"):
            model.save_replay_buffer(where / "replay.pkl")
        tmp = self.progress.with_suffix(".tmp")
        tmp.write_text(json.dumps({"dir": frames, "evals": evals}))
        os.replace(tmp, self.progress)
        for old in self.root.iterdir():  # earlier saves: the newest is all a resume needs
            if old.is_dir() and old.name != frames:
                shutil.rmtree(old)


def run_sb3(job: Sb3Job) -> dict[str, Any]:
    """Train SB3's ``job.algo`` as ``job`` says (one torch thread); evals and the final eval's
    mean."""
    import gymnasium as gym
    import stable_baselines3
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.env_util import make_vec_env

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
            seed = job.seed + 10_000 + len(self.evals)
            mean = float(np.mean(greedy_returns(self.model, self.envs, job.eval_episodes, seed)))
            trained = self.seconds + t0 - self.start - self.off_clock
            self.evals.append((self.num_timesteps, mean, trained))
            if self.saves is not None:
                self.saves.save(self.model, self.evals)
            self.off_clock += time.perf_counter() - t0

    env = make_vec_env(job.env, n_envs=job.n_envs, seed=job.seed)
    algo = getattr(stable_baselines3, job.algo)
    saves = Sb3Saves(Path(job.save_dir)) if job.save_dir else None
    progress = saves.newest() if saves else None
    if progress is None:
        model = algo("MlpPolicy", env, seed=job.seed, device="cpu", **job.kwargs)
        callback = GreedyEval(saves, [], 0.0, 0)
    else:
        model = algo.load(progress.model, env=env, device="cpu")
        if progress.replay.is_file():
            model.load_replay_buffer(progress.replay)
        callback = GreedyEval(saves, progress.evals, progress.evals[-1][2], model.num_timesteps)
    left = max(job.frames - model.num_timesteps, 0)
    model.learn(left, callback=callback, reset_num_timesteps=False)
    if not callback.evals or callback.evals[-1][0] != model.num_timesteps:
        callback.evaluate()  # like rlpipe's runner: always an eval at the end
    callback.envs.close()
    final_envs = gym.make_vec(job.env, num_envs=eval_envs(job.final_episodes))
    final = greedy_returns(model, final_envs, job.final_episodes, seed=0)  # evaluate's seed
    final_envs.close()
    return {"evals": callback.evals, "final": float(np.mean(final))}


def sb3_job(preset: Preset, cfg: Config, seed: int, out: Path) -> Run:
    """Run SB3 in a spawned process; its results also go to ``<out>/sb3.json``."""
    assert preset.sb3 is not None and cfg.total_frames is not None
    job = Sb3Job(
        preset.env,
        seed,
        cfg.total_frames,
        cfg.eval_every,
        cfg.eval_episodes,
        preset.final_episodes,
        preset.sb3,
        preset.sb3_algo,
        preset.sb3_envs,
        str(out / "sb3-saves") if preset.resumable else None,
    )
    saved = out / "sb3.json"
    reused = saved.is_file()  # a finished run of an earlier call with this --out
    if reused:
        result = json.loads(saved.read_text())
    else:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            result = pool.submit(run_sb3, job).result()
        out.mkdir(parents=True, exist_ok=True)
        saved.write_text(json.dumps(result, indent=2) + "\n")
    evals = [(int(f), float(m), float(s)) for f, m, s in result["evals"]]
    return Run(preset.experiment, seed, "SB3", evals, result["final"], reused=reused)


def _call(args: list[str], log: Path, cwd: Path) -> None:
    """``python <args>`` with its output appended to ``log``; a failure raises its last line."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    with open(log, "a") as f:
        f.write(f"$ python {' '.join(args)}\n")
        f.flush()
        code = subprocess.call([sys.executable, *args], stdout=f, stderr=f, env=env, cwd=cwd)
    if code != 0:
        lines = [line for line in log.read_text().splitlines() if line.strip()]
        raise RuntimeError(f"exit {code}: {lines[-1] if lines else '(no output)'} (log: {log})")


def rlpipe_job(
    preset: Preset,
    cfg: Config,
    seed: int,
    frames: int | None,
    episodes: int,
    out: Path,
    extra: Sequence[str] = (),
) -> Run:
    """Train the preset as a user would (plus the ``extra`` overrides), evaluate it, read its
    metrics."""
    run_dir = out / "run"  # not "rlpipe": cwd is on a -m module's path and would shadow it
    out.mkdir(parents=True, exist_ok=True)
    log = out / "rlpipe.log"
    overrides = [
        f"+experiment={preset.experiment}",
        f"seed={seed}",
        "progress=false",
        # resumable: a checkpoint at every eval, and the same command continues a killed run
        f"checkpoint_every={cfg.eval_every if preset.resumable else 0}",
        f"hydra.run.dir={run_dir}",
        *extra,
    ] + ([f"total_frames={frames}"] if frames is not None else [])
    finals = sorted(
        (run_dir / "evaluation").glob("trained-*.json"), key=lambda p: p.stat().st_mtime
    )
    reused = (run_dir / "summary.json").is_file() and bool(finals)  # an earlier call's run
    if not reused:
        _call(["-m", "rlpipe", *overrides], log, out)
        _call(["-m", "rlpipe.evaluate", f"run_dir={run_dir}", f"episodes={episodes}"], log, out)
        finals = sorted(
            (run_dir / "evaluation").glob("trained-*.json"), key=lambda p: p.stat().st_mtime
        )
    seconds = dict(read_scalar(run_dir, "time/train_seconds"))
    evals = [(f, m, seconds[f]) for f, m in read_scalar(run_dir, "eval/return_mean")]
    final = json.loads(finals[-1].read_text())["return_mean"]
    return Run(preset.experiment, seed, "rlpipe", evals, final, reused=reused)


class Scheduler:
    """Runs jobs ``jobs`` at a time, in order; the jobs of one group start together."""

    def __init__(self, jobs: int, total: int) -> None:
        self.jobs, self.total = jobs, total
        self.slots = threading.Semaphore(jobs)
        self.pool = ThreadPoolExecutor(jobs)
        self.futures: list[Future[Run]] = []
        self.start, self.done = time.perf_counter(), 0
        self.lock = threading.Lock()

    def group(self, jobs: Sequence[tuple[str, int, str, Callable[[], Run]]]) -> None:
        """Start ``jobs`` (preset, seed, which, function) at once, as soon as there are slots."""
        if len(jobs) > self.jobs:
            for job in jobs:
                self.group([job])
            return
        for _ in jobs:
            self.slots.acquire()
        self.futures += [self.pool.submit(self._run, *job) for job in jobs]

    def _run(self, preset: str, seed: int, which: str, fn: Callable[[], Run]) -> Run:
        start = time.perf_counter()
        try:
            run = fn()
        except Exception as e:  # one failed run must not sink a long benchmark
            run = Run(preset, seed, which, error=f"{type(e).__name__}: {e}")
        finally:
            self.slots.release()
        run.seconds = time.perf_counter() - start
        with self.lock:
            self.done += 1
            status = f"FAILED ({run.error})" if run.error else "done"
            print(
                f"presets: {preset} seed {seed} {which} {status} in {run.seconds:.0f} s "
                f"({self.done}/{self.total} runs, {time.perf_counter() - self.start:.0f} s "
                "elapsed)",
                file=sys.stderr,
                flush=True,
            )
        return run

    def results(self) -> list[Run]:
        self.pool.shutdown(wait=True)
        return [f.result() for f in self.futures]


def _median(values: Sequence[float], fmt: str) -> str:
    return format(statistics.median(values), fmt) if values else "–"


def _frames_to_target(hits: Sequence[tuple[int, float] | None]) -> str:
    reached = sorted(h[0] for h in hits if h is not None)
    k = f"{len(reached)}/{len(hits)} reached"
    if not reached:
        return k
    spread = "" if reached[0] == reached[-1] else f" ({reached[0]:,}–{reached[-1]:,})"
    return f"{statistics.median(reached):,.0f}{spread}, {k}"


def _kwargs(kwargs: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v}" for k, v in kwargs.items())


def _num(value: float | None, fmt: str = ".1f") -> str:
    return "–" if value is None else format(value, fmt)


def summary_row(preset: Preset, cfg: Config, ours: list[Run], sb3: list[Run]) -> list[str]:
    """The preset's row of the main table."""
    n = len(ours)
    hits = [r.hit(preset.target) for r in ours]
    lasts = [r.last_three for r in ours if r.last_three is not None]
    finals = [r.final for r in ours if r.final is not None]
    solved = sum(x >= preset.solved_bar for x in lasts)
    ends = sorted(r.evals[-1][0] for r in ours if r.evals)
    ran = "" if not ends else f"{ends[0]:,}" + ("" if ends[0] == ends[-1] else f"–{ends[-1]:,}")
    if cfg.total_frames is None:  # the algorithm's own budget (ARS iterations)
        budget_cell = f"{cfg.algo.iterations:,} iterations" + (f" (ran {ran})" if ran else "")
    else:
        budget_cell = f"{cfg.total_frames:,}"
        if ends and ends != [cfg.total_frames] * len(ends):
            budget_cell += f" (ran {ran})"
    target = f"{preset.target:g}"
    if preset.solved is not None:
        target += f" (solved: ≥ {preset.solved:g})"
    if preset.zoo is None and preset.budget_text:
        target += f" at {preset.budget_text}"
    final_cell = ", ".join(f"{x:.1f}" for x in finals) or "–"
    if finals:
        final_cell += f" ({sum(x >= preset.final_bar for x in finals)}/{n} ≥ {preset.final_bar:g})"
    zoo = "–" if preset.zoo is None else f"{preset.zoo:g} at {preset.budget_text}"
    sb3_cell, ratio, whole = "–", "–", "–"
    if sb3:
        sb3_whole = {r.seed: r.train_seconds for r in sb3 if r.train_seconds}
        whole = _median(
            [
                r.train_seconds / sb3_whole[r.seed]
                for r in ours
                if r.train_seconds and r.seed in sb3_whole
            ],
            ".2f",
        )
        sb3_hits = {r.seed: r.hit(preset.target) for r in sb3}
        reached = [h[1] for h in sb3_hits.values() if h is not None]
        sb3_cell = f"{_median(reached, '.1f')} ({len(reached)}/{len(sb3)} reached)"
        ratios = [
            hit[1] / sb3_hits[r.seed][1]
            for r, hit in zip(ours, hits)
            if hit is not None and sb3_hits.get(r.seed) is not None
        ]
        ratio = _median(ratios, ".2f")
    return [
        f"`{preset.experiment}`",
        preset.env,
        budget_cell,
        target,
        f"{solved}/{n}",
        _frames_to_target(hits),
        f"{np.mean(lasts):.1f} ± {np.std(lasts):.1f}" if lasts else "–",
        final_cell,
        _median([h[1] for h in hits if h is not None], ".1f"),
        _median([r.train_seconds for r in ours if r.train_seconds], ".1f"),
        zoo,
        sb3_cell,
        ratio,
        whole,
    ]


def detail_rows(preset: Preset, ours: list[Run], sb3: list[Run]) -> list[list[str]]:
    """One row per seed: rlpipe's figures and SB3's beside them."""
    by_seed = {r.seed: r for r in sb3}
    rows = []
    for r in ours:
        if r.error:
            cells = [f"failed: {r.error}", "–", "–", "–"]
        else:
            hit = r.hit(preset.target)
            cells = [
                "not reached" if hit is None else f"{hit[0]:,}",
                "–" if hit is None else f"{hit[1]:.1f}",
                _num(r.last_three),
                _num(r.final),
            ]
        other = by_seed.get(r.seed)
        if other is None:
            cells += ["–", "–"]
        elif other.error:
            cells += [f"failed: {other.error}", "–"]
        else:
            hit = other.hit(preset.target)
            cells += [
                "not reached" if hit is None else f"{hit[0]:,} / {hit[1]:.1f} s",
                _num(other.final),
            ]
        rows.append([f"`{preset.experiment}`", str(r.seed), *cells])
    return rows


def preset_yaml_exists(name: str) -> bool:
    return (importlib.resources.files("rlpipe.conf") / "experiment" / f"{name}.yaml").is_file()


def choose_presets(names: list[str] | None) -> list[Preset]:
    """The registry's presets asked for (default: every one whose YAML exists)."""
    if names is None:
        chosen = []
        for name, preset in PRESETS.items():
            if preset_yaml_exists(name):
                chosen.append(preset)
            else:
                print(f"presets: skipping {name}: no conf/experiment/{name}.yaml", file=sys.stderr)
        return chosen
    for name in names:
        if name not in PRESETS:
            sys.exit(f"presets.py: unknown preset {name!r}; known: {', '.join(PRESETS)}")
        if not preset_yaml_exists(name):
            sys.exit(f"presets.py: preset {name!r} has no conf/experiment/{name}.yaml (yet)")
    return [PRESETS[name] for name in dict.fromkeys(names)]


def compose(preset: Preset, frames: int | None, extra: Sequence[str] = ()) -> Config:
    """The preset's resolved config (budget, eval cadence) as its runs will see it."""
    overrides = [f"+experiment={preset.experiment}", *extra]
    if frames is not None:
        overrides.append(f"total_frames={frames}")
    try:
        return compose_run(*overrides).resolved()
    except Exception as e:
        sys.exit(f"presets.py: +experiment={preset.experiment} does not compose: {e}")


def report(
    presets: list[Preset],
    configs: dict[str, Config],
    runs: list[Run],
    args: Any,
    loads: tuple[tuple[float, ...], tuple[float, ...]],
    wall: float,
) -> str:
    """The Markdown report: machine and load, the table per preset, notes, per-seed details."""
    rows, details, notes = [], [], []
    for p in presets:
        ours = [r for r in runs if r.preset == p.experiment and r.which == "rlpipe"]
        sb3 = [r for r in runs if r.preset == p.experiment and r.which == "SB3"]
        cfg = configs[p.experiment]
        rows.append(summary_row(p, cfg, ours, sb3))
        details += detail_rows(p, ours, sb3)
        episodes = args.final_episodes or p.final_episodes
        notes.append(
            f"- `{p.experiment}`: seeds {', '.join(str(r.seed) for r in ours)}; a greedy eval of "
            f"{cfg.eval_episodes} episodes every {cfg.eval_every:,} frames and at the end, then "
            f"`python -m rlpipe.evaluate` with {episodes} episodes"
            + (
                f"; SB3 {p.sb3_algo} with the RL Zoo's settings: "
                + _kwargs({"n_envs": p.sb3_envs, **p.sb3} if p.sb3_envs > 1 else p.sb3)
                if sb3
                else ""
            )
        )
    start, end = (", ".join(f"{x:.2f}" for x in load) for load in loads)
    reused = sum(r.reused for r in runs)
    command = " ".join(["python", "benchmarks/presets.py", *sys.argv[1:]])
    return "\n".join(
        [
            "### Tuned presets" + (": rlpipe vs SB3 + RL Zoo" if args.sb3 else ""),
            "",
            machine(PACKAGES),
            "",
            f"Load average (1, 5, 15 min): {start} at the start, {end} at the end; "
            f"{args.jobs} run(s) at once; {wall / 60:.1f} min in all. `{command}`"
            + (
                f" ({reused} of {len(runs)} runs read from earlier calls' `--out`: their load "
                "and time are in those calls' reports)"
                if reused
                else ""
            ),
            "",
            table(
                [
                    "preset",
                    "env",
                    "budget (frames)",
                    "target",
                    "seeds solved",
                    "frames to target",
                    "last-three mean",
                    "final greedy mean per seed",
                    "train s to target (median)",
                    "train s, whole run (median)",
                    "RL Zoo",
                    "SB3 train s to target (median)",
                    "rlpipe/SB3 to target",
                    "rlpipe/SB3 whole run",
                ],
                rows,
            ),
            "",
            "Solved: the mean of the last three evals ≥ the target (or the solved bar named "
            "there). Frames and training seconds (eval time excluded) at the first eval ≥ the "
            "target: median (range) over the seeds that reached it. Last-three mean: mean ± std "
            "over seeds. Final: the final greedy eval per seed, counted against the Zoo figure "
            "(or the solved bar). rlpipe/SB3 to target: median over the seeds both reached of the "
            "ratio of training seconds to the target; whole run: median over seeds of the ratio "
            "of training seconds over the whole budget.",
            "",
            *notes,
            "",
            table(
                [
                    "preset",
                    "seed",
                    "frames to target",
                    "train s to target",
                    "last-three mean",
                    "final eval",
                    "SB3 frames / s to target",
                    "SB3 final",
                ],
                details,
            ),
        ]
    )


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.set_defaults(seeds=None)  # None: each preset's own seeds
    p.add_argument("--presets", nargs="+", metavar="NAME", help=f"of: {', '.join(PRESETS)}")
    p.add_argument("--sb3", action="store_true", help="also run SB3 with RL Zoo's settings")
    p.add_argument("--jobs", type=int, default=2, help="runs at once (default 2)")
    p.add_argument("--frames", type=int, help="override every preset's budget (smoke tests)")
    p.add_argument("--final-episodes", type=int, help="override the final eval's episodes")
    p.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="added to every rlpipe run, e.g. env.backend=envpool (repeatable)",
    )
    p.add_argument(
        "--out",
        type=Path,
        help="where the run dirs go (default: a temp dir); runs finished there by an earlier "
        "call are read, not run again (an interrupted benchmark continues)",
    )
    args = p.parse_args()
    if args.jobs < 1:
        p.error("--jobs must be at least 1")
    if args.sb3 and importlib.util.find_spec("stable_baselines3") is None:
        sys.exit('presets.py: --sb3 needs stable-baselines3: pip install -e ".[bench]"')
    presets = choose_presets(args.presets)
    configs = {pr.experiment: compose(pr, args.frames, args.override) for pr in presets}
    with tempfile.TemporaryDirectory(prefix="presets-") as tmp:
        out = (args.out or Path(tmp)).resolve()
        print(f"presets: run dirs under {out}", file=sys.stderr)
        plan = []
        for preset in presets:
            episodes = args.final_episodes or preset.final_episodes
            for seed in args.seeds or preset.seeds:
                where = out / preset.experiment / f"seed{seed}"
                ours = partial(
                    rlpipe_job,
                    preset,
                    configs[preset.experiment],
                    seed,
                    args.frames,
                    episodes,
                    where,
                    args.override,
                )
                group = [(preset.experiment, seed, "rlpipe", ours)]
                if args.sb3 and preset.sb3 is not None:
                    sb3 = replace(preset, final_episodes=episodes)
                    theirs = partial(sb3_job, sb3, configs[preset.experiment], seed, where)
                    group.append((preset.experiment, seed, "SB3", theirs))
                plan.append(group)
        loads, start = [os.getloadavg()], time.perf_counter()
        scheduler = Scheduler(args.jobs, sum(len(g) for g in plan))
        for group in plan:
            scheduler.group(group)
        runs = scheduler.results()
        loads.append(os.getloadavg())
        wall = time.perf_counter() - start
    publish(report(presets, configs, runs, args, (loads[0], loads[1]), wall), args.append)


if __name__ == "__main__":
    main()
