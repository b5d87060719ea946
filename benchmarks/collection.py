"""What collecting one env step costs: TorchRL's Collector against rlpipe's lean loop
(``rlpipe.algos.collectors``), on the same env, policy and batches, per preset and backend.

For each preset and backend one process builds the preset's algorithm (seed 0, one torch thread),
whose collector is the lean ``ArrayCollector``, and a ``TorchRLCollector`` running the
algorithm's TensorDict collecting policy on a second env from the same factory (what rlpipe
used before). Rounds alternate the two (``--rounds``, each about ``--steps`` env steps in batches
of the preset's size); the table gives each one's median milliseconds per env step of all
copies, per frame, and their ratio.

    python benchmarks/collection.py [--presets dqn_cartpole sac_pendulum ppo_cartpole]
        [--backends gymnasium envpool] [--rounds 5] [--steps 320] [--append BENCHMARKS.md]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time
from functools import partial
from pathlib import Path

import torch
from common import machine, publish_section, script, table
from tensordict.nn import TensorDictSequential

from rlpipe import compose_run
from rlpipe.algos import make_algorithm
from rlpipe.algos.collectors import ArrayCollector, TorchRLCollector
from rlpipe.envs import make_env
from rlpipe.envs.backends import envpool_version, resolve_backend
from rlpipe.runtime import seed_everything

PRESETS = ("dqn_cartpole", "sac_pendulum", "ppo_cartpole")
# each algorithm's TensorDict collecting policy: what TorchRL's Collector ran
POLICIES = {
    "dqn": lambda algo: TensorDictSequential(algo.policy, algo.exploration),
    "sac": lambda algo: algo.policy,
    "ppo": lambda algo: algo.policy,
}


def seconds_per_batch(collector, steps: int, batches: int) -> float:
    start = time.perf_counter()
    for _ in range(batches):
        collector.batch(steps)
    return (time.perf_counter() - start) / batches


def measure(preset: str, backend: str, rounds: int, env_steps: int) -> dict:
    """Median ms per env step of the lean loop and of TorchRL's Collector, and the copies."""
    cfg = compose_run(f"+experiment={preset}", "seed=0", f"env.backend={backend}").resolved()
    env_cfg, _ = resolve_backend(cfg.env)
    seed_everything(0)
    factory = partial(make_env, env_cfg, threads=1, seed=0)
    algo = make_algorithm(factory, cfg.algo, device="cpu")
    lean, (copies, steps) = algo.collector, algo.collect().batch_size
    assert isinstance(lean, ArrayCollector), type(lean)
    batches = math.ceil(env_steps / steps)
    theirs = TorchRLCollector(factory(), POLICIES[cfg.algo.name](algo), steps, algo.device)
    times: dict[str, list[float]] = {"lean": [], "collector": []}
    try:
        seconds_per_batch(lean, steps, 2)  # warm-up
        seconds_per_batch(theirs, steps, 2)
        for r in range(rounds):
            order = [("lean", lean), ("collector", theirs)]
            for name, collector in order if r % 2 == 0 else order[::-1]:
                times[name].append(seconds_per_batch(collector, steps, batches) / steps)
    finally:
        theirs.close()
        algo.close()
    return {name: 1e3 * statistics.median(ts) for name, ts in times.items()} | {"copies": copies}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=list(PRESETS), choices=PRESETS)
    parser.add_argument("--backends", nargs="+", default=["gymnasium", "envpool"])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=320, help="env steps per round and path")
    parser.add_argument("--append", type=Path, help="replace this section of a Markdown file")
    args = parser.parse_args()
    torch.set_num_threads(1)
    backends = [b for b in args.backends if b != "envpool" or envpool_version() is not None]
    load = os.getloadavg()[0]
    rows = []
    for preset in args.presets:
        for backend in backends:
            r = measure(preset, backend, args.rounds, args.steps)
            rows.append(
                [
                    f"`{preset}`",
                    backend,
                    r["copies"],
                    f"{r['collector']:.3f}",
                    f"{r['lean']:.3f}",
                    f"{r['collector'] / r['copies']:.4f}",
                    f"{r['lean'] / r['copies']:.4f}",
                    f"**{r['collector'] / r['lean']:.1f}×**",
                ]
            )
    headers = [
        "preset",
        "backend",
        "copies",
        "Collector ms / step",
        "lean ms / step",
        "Collector ms / frame",
        "lean ms / frame",
        "lean speed-up",
    ]
    lines = [
        "## Collection: TorchRL's Collector against the lean loop (benchmarks/collection.py)",
        "",
        f"- machine: {machine(['torch', 'torchrl', 'tensordict', 'gymnasium', 'envpool'])}",
        f"- load before: {load:.2f}; command: `python benchmarks/collection.py --presets "
        f"{' '.join(args.presets)} --backends {' '.join(backends)} --rounds {args.rounds} "
        f"--steps {args.steps}`",
        "- a step: one env step of all copies with the preset's collecting policy (seed 0, one "
        f"torch thread), batches of the preset's size; medians of {args.rounds} alternating "
        "rounds in one process",
        "",
        table(headers, rows),
    ]
    publish_section("\n".join(lines), args.append)


if __name__ == "__main__":
    script(main)
