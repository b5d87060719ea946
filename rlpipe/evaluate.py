"""``python -m rlpipe.evaluate run_dir=... [episodes=100] [video=true] [policy=...]``.

Loads a run's config (``run_dir=latest``: the newest run under ``outputs/``) and its newest
checkpoint (``checkpoint=best``: the best evaluation's; ``checkpoint=<frames>`` or ``<file>``),
runs greedy episodes (on ``copies`` env copies in lock-step: by default one per episode up to
32; ``copies=1``: one after another on one env, the classic "100 consecutive trials";
``render=human``: live in a window), prints mean ± std, min, max and the mean episode length,
and writes a JSON summary (plus, with ``video=true``, an mp4 of ``video_episodes`` more greedy
episodes). ``policy=random``, ``policy=naive`` (the notebook's hand-written BipedalWalker
controller) and ``policy=heuristic`` (a hand-written BipedalWalker gait) are baselines on the
run's env, or on any ``env=<option>`` without a run dir (their summary goes to
``outputs/evaluation/<env>-<policy>.json``). The output location is checked before any episode
runs. A run dir's ``env.id`` of the form ``module:Id`` (which imports ``module``) is refused
unless ``allow_env_import=true``: run dirs are data, not code.
"""

from __future__ import annotations

import dataclasses
import json
import re
import sys
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from hydra.core.config_store import ConfigStore
from omegaconf import MISSING
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import EnvBase

from rlpipe.cli import compose_config, run_entry_point
from rlpipe.config import ENV_BACKENDS, EnvConfig
from rlpipe.envs import envpool_env, make_env
from rlpipe.episodes import EvalResult, eval_envs, evaluate
from rlpipe.errors import check, check_fields
from rlpipe.files import check_writable, write_atomic
from rlpipe.heuristic import heuristic_policy, naive_policy, random_policy
from rlpipe.loggers import require_extra
from rlpipe.outcomes import counted
from rlpipe.pipeline import load_run
from rlpipe.rundir import RunDir
from rlpipe.runs import latest_run
from rlpipe.runtime import resolve_device, seed_everything
from rlpipe.video import check_display, frame_rate, make_render_env, record_episode, write_mp4

POLICIES = ("trained", "random", "naive", "heuristic")
BASELINES = {"random": random_policy, "naive": naive_policy, "heuristic": heuristic_policy}
BASELINES_DIR = Path("outputs") / "evaluation"  # summaries of baselines without a run dir


@dataclass
class EvaluateConfig:
    """``conf/evaluate.yaml``: what to evaluate, how many episodes, where the results go."""

    # a training run's directory (its env and checkpoints); latest: the newest under outputs/
    run_dir: str | None = None
    # a file in <run_dir>/checkpoints, or its frames (4096); best: the best evaluation's; null:
    # the newest
    checkpoint: str | None = None
    policy: str = "trained"  # trained | random | naive | heuristic
    episodes: int = 10
    # env copies stepped in lock-step, each its share of the episodes; null: one per episode, at
    # most 32 (fast); 1: the episodes one after another on one env ("100 consecutive trials")
    copies: int | None = None
    # human: watch the episodes live in a window (one env copy, at the env's frame rate)
    render: str | None = None
    video: bool = False  # also write an mp4 of greedy episodes
    video_episodes: int = 1  # how many episodes the mp4 shows, one after the other
    seed: int = 0
    device: str = "cpu"
    # the env backend the episodes run on (auto, gymnasium, envpool); null: the run's (videos
    # and render=human always render with gymnasium)
    backend: str | None = None
    # the JSON summary; null: <run_dir>/evaluation/<policy>[-<ckpt>].json, without a run dir
    # outputs/evaluation/<env>-<policy>.json
    out: str | None = None
    # let a run dir's env.id import its module (module:Id); only for run dirs you trust
    allow_env_import: bool = False
    env: EnvConfig | None = field(default_factory=lambda: EnvConfig(id=MISSING))

    def __post_init__(self) -> None:
        check(self.episodes >= 1, f"episodes must be >= 1, got {self.episodes}")
        check(
            self.copies is None or 1 <= self.copies <= self.episodes,
            f"copies must be between 1 and episodes ({self.episodes}) or null (one per episode, "
            f"at most 32); got {self.copies}",
        )
        check(
            self.render is None or self.copies in (None, 1),
            f"render=human runs one env copy; drop copies={self.copies} (or render=human)",
        )
        check(self.video_episodes >= 1, f"video_episodes must be >= 1, got {self.video_episodes}")
        check_fields(self, "", device=("device",))
        check(
            self.backend in (None, *ENV_BACKENDS),
            f"backend must be one of {', '.join(ENV_BACKENDS)} or null (the run's); "
            f"got {self.backend!r}",
        )
        check(
            self.render in (None, "human"),
            f"render must be human (a live window) or null, got {self.render!r}",
        )
        check(
            self.policy in POLICIES,
            f"policy must be one of {', '.join(POLICIES)}; got {self.policy!r}",
        )
        check(
            self.run_dir is not None or self.policy != "trained",
            "policy=trained needs run_dir=<a training run's directory> "
            "(or evaluate a baseline: policy=random env=<option>)",
        )
        check(
            self.run_dir is None or self.env is None,
            "the env comes from the run dir's config; drop env=... (or drop run_dir=...)",
        )
        check(
            self.run_dir is not None or self.env is not None,
            "pass run_dir=<a training run's directory> or env=<option> (e.g. env=bipedal)",
        )


def _policy(cfg: EvaluateConfig, stack: ExitStack) -> tuple[TensorDictModuleBase, EnvConfig, str]:
    """The policy to evaluate, its env config and a name for the outputs."""
    if cfg.policy == "trained":
        device = resolve_device(cfg.device)
        loaded = load_run(
            cfg.run_dir,
            cfg.checkpoint,
            device=device,
            allow_env_import=cfg.allow_env_import,
            backend=cfg.backend,
        )
        stack.callback(loaded.algo.close)
        return loaded.algo.policy, loaded.cfg.env, f"trained-{loaded.checkpoint.stem}"
    env_cfg = (
        RunDir(cfg.run_dir).read_config(allow_code=cfg.allow_env_import).env
        if cfg.run_dir
        else cfg.env
    )
    if cfg.backend is not None:
        env_cfg = dataclasses.replace(env_cfg, backend=cfg.backend)
    probe = make_env(env_cfg, num_envs=1)
    stack.callback(probe.close)
    return BASELINES[cfg.policy](probe), env_cfg, cfg.policy


def _out_path(cfg: EvaluateConfig, env_cfg: EnvConfig, name: str) -> Path:
    if cfg.out:
        return Path(cfg.out)
    if cfg.run_dir:
        return Path(cfg.run_dir) / RunDir.EVALUATION / f"{name}.json"
    return BASELINES_DIR / f"{re.sub(r'[^A-Za-z0-9._-]+', '_', env_cfg.id)}-{name}.json"


def run(cfg: EvaluateConfig) -> dict[str, Any]:
    """Evaluate as ``cfg`` says; write and return the JSON summary."""
    if cfg.video:
        require_extra("video", "video=true")
    if cfg.run_dir == "latest":
        cfg = dataclasses.replace(cfg, run_dir=str(latest_run()))
    seed_everything(cfg.seed)
    with ExitStack() as stack:
        policy, env_cfg, name = _policy(cfg, stack)
        path = _out_path(cfg, env_cfg, name)
        hint = "pick a writable place for the summary with out=<file.json>"
        check_writable(path, hint)
        if cfg.video:
            check_writable(path.with_suffix(".mp4"), hint)
        render_env = make_render_env(env_cfg, seed=cfg.seed) if cfg.video else None
        if render_env is not None:
            stack.callback(render_env.close)
        if cfg.render == "human":  # one copy, episode after episode, drawn as it steps
            check_display("render=human")
            env = make_env(env_cfg, num_envs=1, seed=cfg.seed, render_mode="human")
        else:
            copies = cfg.copies or eval_envs(cfg.episodes)  # each a share, in lock-step
            env = make_env(env_cfg, num_envs=copies, seed=cfg.seed)
        stack.callback(env.close)
        result = evaluate(policy, env, cfg.episodes)
        summary: dict[str, Any] = {
            "policy": cfg.policy,
            "env": env_cfg.id,
            "backend": "gymnasium" if envpool_env(env) is None else "envpool",
            "run_dir": cfg.run_dir,
            "checkpoint": name.removeprefix("trained-") if cfg.policy == "trained" else None,
            "episodes": cfg.episodes,
            "copies": env.batch_size.numel(),
            "seed": cfg.seed,
            **result.metrics(prefix=""),
            "returns": result.returns,
            "lengths": result.lengths,
            "video": None,
        }
        if render_env is not None:
            episodes = [record_episode(policy, render_env) for _ in range(cfg.video_episodes)]
            video = write_mp4(
                np.concatenate(episodes), path.with_suffix(".mp4"), frame_rate(render_env)
            )
            summary["video"] = str(video)
            summary["video_frames"] = [len(frames) for frames in episodes]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, (json.dumps(summary, indent=2) + "\n").encode())
    summary["json"] = str(path)
    return summary


def summary_line(summary: dict[str, Any]) -> str:
    """One line: the policy, env and return statistics, and where the files went."""
    what = summary["policy"] + (f" ({summary['checkpoint']})" if summary["checkpoint"] else "")
    copies = summary["copies"]
    on = "one env" if copies == 1 else f"{copies} env copies"
    line = (
        f"{what} on {summary['env']}: return {summary['return_mean']:.2f} ± "
        f"{summary['return_std']:.2f} over {counted(summary['episodes'], 'episode')} on {on} "
        f"(min {summary['return_min']:.2f}, max {summary['return_max']:.2f}) | "
        f"episode length {summary['length_mean']:.1f} | summary {summary['json']}"
    )
    return line + (f" | video {summary['video']}" if summary["video"] else "")


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m rlpipe.evaluate key=value ...``; user errors: one line, exit 2."""
    doc = __doc__.strip() + "\n\nkeys (conf/evaluate.yaml): " + ", ".join(_keys())
    run_entry_point(doc, argv, _evaluate)


def _evaluate(args: list[str]) -> None:
    summary = run(compose_config("evaluate", args))
    print(f"rlpipe: {summary_line(summary)}")


def _keys() -> list[str]:
    return [f.name for f in dataclasses.fields(EvaluateConfig)]


ConfigStore.instance().store(name="evaluate_schema", node=EvaluateConfig)


class _CallableModule(ModuleType):
    """This module, also callable as the evaluation function :func:`rlpipe.episodes.evaluate`.

    Why: ``rlpipe/__init__.py`` exports that function as ``rlpipe.evaluate``, and importing this
    command's module (``from rlpipe.evaluate import main``) makes Python rebind the package
    attribute ``rlpipe.evaluate`` to the module. Calls pass through, so ``rlpipe.evaluate(policy,
    env, episodes)`` works either way, and ``rlpipe.evaluate.main`` too.
    """

    __wrapped__ = staticmethod(evaluate)  # what a call runs (inspect.signature follows it)

    def __call__(self, policy: TensorDictModuleBase, env: EnvBase, episodes: int) -> EvalResult:
        return evaluate(policy, env, episodes)


sys.modules[__name__].__class__ = _CallableModule

if __name__ == "__main__":
    main()
