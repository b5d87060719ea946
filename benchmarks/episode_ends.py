"""How a trained run's greedy episodes end: in a fall, at the goal, or at the time limit.

A preset's miss can come from a policy that falls now and then, one that walks too slowly to
finish, or one that never gets going; the mean return alone does not tell them apart. Per trained
run (its newest checkpoint, the run's env and backend, one evaluation seed), the episodes run as
rlpipe's evaluation runs them (``min(episodes, 32)`` copies in lock-step, each its share of the
episodes) and each is sorted by its end: a fall (terminated on a last reward of ``--fall-reward``
or less: BipedalWalker's and LunarLander's -100), another termination (BipedalWalker: the end of
the course), or the time limit (truncated). Results are saved in ``<run>/evaluation/ends-*.json``
and read back, so a call with the same arguments continues.

    python benchmarks/episode_ends.py RUN [RUN ...] [--episodes 100] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import statistics
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
from torchrl.envs import EnvBase

from rlpipe.envs import make_env
from rlpipe.episodes import eval_envs
from rlpipe.pipeline import LoadedRun


def episode_ends(
    policy: TensorDictModuleBase, env: EnvBase, episodes: int, fall_reward: float
) -> list[dict]:
    """Each episode's return, steps and end (``fall``, ``terminated`` or ``time limit``):
    ``episodes`` greedy episodes on ``env``'s copies, copy ``i`` running ``episodes // n`` of
    them, one more for the first ``episodes % n``."""
    copies = env.batch_size.numel()
    quota = [episodes // copies + (i < episodes % copies) for i in range(copies)]
    ends = []
    for episode in greedy_episodes(policy, env, quota):
        fell = not episode["truncated"] and episode["last_reward"] <= fall_reward
        end = "time limit" if episode["truncated"] else "fall" if fell else "terminated"
        ends.append({"return": episode["return"], "steps": episode["steps"], "end": end})
    return ends


def measure(run: Path, loaded: LoadedRun, episodes: int, seed: int, fall_reward: float) -> dict:
    """A loaded run's episodes and their ends."""
    env = make_env(loaded.cfg.env, num_envs=eval_envs(episodes), seed=seed)
    try:
        ends = episode_ends(loaded.algo.policy, env, episodes, fall_reward)
    finally:
        env.close()
    return {"run": str(run), "fall_reward": fall_reward, "episodes": ends}


def row(run: Path, figures: dict) -> list[str]:
    """One table row: the mean, then each kind of end's count, mean return and steps."""
    eps = figures["episodes"]
    cells = [f"`{run_name(run)}`", f"{statistics.fmean(e['return'] for e in eps):.1f}"]
    for end in ("fall", "terminated", "time limit"):
        these = [e for e in eps if e["end"] == end]
        if not these:
            cells += ["0", "–"]
            continue
        ret = statistics.fmean(e["return"] for e in these)
        steps = sorted(e["steps"] for e in these)
        span = f"{steps[0]:,}–{steps[-1]:,}" if steps[0] < steps[-1] else f"{steps[0]:,}"
        cells += [str(len(these)), f"{ret:.1f} / {statistics.median(steps):,.0f} ({span})"]
    return cells


def main() -> None:
    parser = runs_parser(__doc__.splitlines()[0])
    parser.add_argument("--fall-reward", type=float, default=-100.0, help="a fall's last reward")
    args = parser.parse_args()
    rows, load = run_rows(
        args.runs,
        f"ends-{args.episodes}-seed{args.seed}.json",
        lambda run, loaded: measure(run, loaded, args.episodes, args.seed, args.fall_reward),
        row,
        "episodes",
    )
    headers = ["run", "mean return"]
    for end in ("falls", "other terminations", "time limits"):
        headers += [end, "their mean return / median steps (range)"]
    head = section_head(
        "How trained runs' greedy episodes end",
        ["torch", "torchrl", "gymnasium", "envpool", "Box2D"],
        load,
        f"each run's newest checkpoint, {args.episodes} greedy episodes on "
        f"{eval_envs(args.episodes)} copies as rlpipe's evaluation runs them, evaluation seed "
        f"{args.seed}; a fall: terminated on a last reward of {args.fall_reward:g} or less",
    )
    publish_section("\n".join([*head, table(headers, rows)]), args.append)


if __name__ == "__main__":
    script(main)
