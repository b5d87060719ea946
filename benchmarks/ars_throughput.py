"""ARS throughput on BipedalWalker-v3: rlpipe's ARS vs the notebook's loop (reference_ars.py).

Both run in this process, one after the other, with the notebook's hyper-parameters (16
directions, all kept, α 0.02, ν 0.03, clipped rewards, normalised observations), the same seed
and number of iterations. Reported: env steps, wall seconds of the iterations (rlpipe's worker
start-up is excluded and shown apart) and env-steps/s; the ratio is against the reference. The
reference's steps include its one evaluation episode per iteration (part of the notebook loop).
CPU µs/step (CPU time per env step: the reference's process, rlpipe's rollouts in every process)
shows the per-step cost apart from the machine's load: on a shared machine the workers get less
than a core each, and env-steps/s ≈ cores available / CPU µs/step.

    python benchmarks/ars_throughput.py --iterations 10 --append BENCHMARKS.md
"""

from __future__ import annotations

import os
import time

from common import machine, parser, publish, table, time_ars
from reference_ars import HP, ARSTrainer


def run_reference(seed: int, iterations: int) -> dict:
    trainer = ARSTrainer(HP(seed=seed))
    start, cpu = time.perf_counter(), time.process_time()
    for step in range(iterations):
        trainer.train_step(step)
    return {
        "steps": trainer.env_steps,
        "seconds": time.perf_counter() - start,
        "cpu": time.process_time() - cpu,
        "startup": 0.0,
    }


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=10)
    p.set_defaults(seeds=[1])
    args = p.parse_args()
    rows = []
    load_before = os.getloadavg()[0]
    for seed in args.seeds:
        runs = {
            "reference (notebook loop, 1 process)": run_reference(seed, args.iterations),
            "rlpipe ARS, algo.workers=1": time_ars(seed, args.iterations, "algo.workers=1"),
            f"rlpipe ARS, algo.workers={os.cpu_count()}": time_ars(
                seed, args.iterations, "algo.workers=0"
            ),
        }
        reference = runs["reference (notebook loop, 1 process)"]
        base = reference["steps"] / reference["seconds"]
        for name, run in runs.items():
            rate = run["steps"] / run["seconds"]
            rows.append(
                [
                    seed,
                    name,
                    f"{run['steps']:,}",
                    f"{run['seconds']:.1f}",
                    f"{run['startup']:.1f}",
                    f"{run['cpu'] / run['steps'] * 1e6:.0f}",
                    f"{rate:,.0f}",
                    f"{rate / base:.2f}×",
                ]
            )
    load_after = os.getloadavg()[0]
    report = "\n".join(
        [
            f"### ARS throughput, BipedalWalker-v3, {args.iterations} iterations",
            "",
            machine(["torch", "torchrl", "gymnasium", "numpy"]),
            f"· 1-min load average {load_before:.2f} before, {load_after:.2f} after",
            "",
            table(
                [
                    "seed",
                    "run",
                    "env steps",
                    "wall s",
                    "start-up s",
                    "CPU µs/step",
                    "env-steps/s",
                    "vs reference",
                ],
                rows,
            ),
        ]
    )
    publish(report, args.append)


if __name__ == "__main__":
    main()
