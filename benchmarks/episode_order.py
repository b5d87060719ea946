"""Returns by episode order after an env's creation: rlpipe's 100-episode evaluation on 32 copies
against 100 consecutive episodes on one env, and early falls by each copy's episode number.

BipedalWalker-v3's Box2D world outlives ``reset``: after its third reset a copy runs with other
contact physics from the first step (gymnasium and EnvPool alike; after the other resets its
first steps match a fresh env's). rlpipe's evaluation steps ``min(episodes, 32)`` copies in
lock-step, so 100 episodes hold 32 such episodes, where the classic definition of solved
("100 consecutive trials") holds one. Per trained run (its newest checkpoint, the run's
backend, one evaluation seed): the mean and early falls (return < 0 within 200 steps) of
rlpipe's evaluation, of 100 consecutive episodes on one env, and the early falls of 16 fresh
copies' 1st to 4th episodes (capped at 300 steps; on gymnasium, seeding resets a copy once
before its first episode). Results are saved in ``<run>/evaluation/order-*.json`` and read
back, so a call with the same arguments continues.

    python benchmarks/episode_order.py RUN [RUN ...] [--episodes 100] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from common import (
    greedy_episodes,
    publish_section,
    run_name,
    run_rows,
    runs_parser,
    script,
    section_head,
    table,
)
from tensordict.nn import TensorDictModuleBase

from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.episodes import EvalResult, eval_envs, evaluate
from rlpipe.pipeline import LoadedRun

EARLY = 200  # an episode that ends below 0 within this many steps fell at its start
COPIES, ORDER, CAP = 16, 4, 300  # fresh copies, episodes each, steps an episode at most


def early_falls(result: EvalResult) -> int:
    """Episodes that ended below 0 within :data:`EARLY` steps."""
    return sum(r < 0 and n <= EARLY for r, n in zip(result.returns, result.lengths))


def falls_by_order(policy: TensorDictModuleBase, env_cfg: EnvConfig, seed: int) -> list[int]:
    """Early falls among the 1st, 2nd, ... :data:`ORDER`-th episodes of :data:`COPIES` fresh
    copies stepped in lock-step (episodes capped at :data:`CAP` steps)."""
    env = make_env(dataclasses.replace(env_cfg, max_episode_steps=CAP), num_envs=COPIES, seed=seed)
    try:
        episodes = greedy_episodes(policy, env, [ORDER] * COPIES)
    finally:
        env.close()
    counts = [0] * ORDER
    for episode in episodes:
        if episode["return"] < 0 and episode["steps"] <= EARLY:
            counts[episode["order"]] += 1
    return counts


def measure(run: Path, loaded: LoadedRun, episodes: int, seed: int) -> dict:
    """A loaded run's three measurements."""
    policy, env_cfg = loaded.algo.policy, loaded.cfg.env
    lockstep = eval_envs(episodes)
    figures = {"run": str(run), "backend": env_cfg.backend, "lockstep_copies": lockstep}
    for name, copies in (("rlpipe", lockstep), ("consecutive", 1)):
        env = make_env(env_cfg, num_envs=copies, seed=seed)
        try:
            result = evaluate(policy, env, episodes)
        finally:
            env.close()
        figures[name] = {"mean": result.mean, "early_falls": early_falls(result)}
    figures["falls_by_order"] = falls_by_order(policy, env_cfg, seed)
    return figures


def row(run: Path, figures: dict) -> list[str]:
    """One table row."""
    cells = [f"`{run_name(run)}`", figures["backend"]]
    for key in ("rlpipe", "consecutive"):
        cells += [f"{figures[key]['mean']:.1f}", str(figures[key]["early_falls"])]
    return [*cells, " / ".join(f"{n} of {COPIES}" for n in figures["falls_by_order"])]


def main() -> None:
    args = runs_parser(__doc__.splitlines()[0]).parse_args()
    rows, load = run_rows(
        args.runs,
        f"order-{args.episodes}-seed{args.seed}.json",
        lambda run, loaded: measure(run, loaded, args.episodes, args.seed),
        row,
        "returns",
    )
    copies = eval_envs(args.episodes)
    headers = ["run", "backend", f"rlpipe's evaluation ({copies} copies) mean", "its early falls"]
    headers += ["consecutive on one env: mean", "its early falls"]
    headers += [f"early falls in episodes 1 / 2 / 3 / 4 of {COPIES} fresh copies"]
    head = section_head(
        "Returns by episode order after an env's creation",
        ["torch", "torchrl", "gymnasium", "envpool", "Box2D"],
        load,
        f"each run's newest checkpoint, {args.episodes} greedy episodes each way, evaluation seed "
        f"{args.seed}; early fall: an episode ending below 0 within {EARLY} steps; the fresh "
        f"copies' episodes capped at {CAP} steps",
    )
    publish_section("\n".join([*head, table(headers, rows)]), args.append)


if __name__ == "__main__":
    script(main)
