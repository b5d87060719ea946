"""ARS iteration throughput on BipedalWalker-v3: the local backend vs the Ray backend.

One run each, the same seed and number of iterations, the notebook's hyper-parameters: the local
backend with 1 worker (this process) and 2 worker processes, the Ray backend with 1 and 2
actors on a Ray started here. The search's generator seeds every episode, but BipedalWalker's
Box2D world outlives its resets, so an episode also depends on what its env copy ran before:
on gymnasium's envs runs with the same worker layout (1 worker: one batch here or in one
actor) step the same frames, other layouts somewhat different ones, hence rates rather than
times are compared (on EnvPool, ``env.backend=auto`` where it is installed, all four runs end
on the same θ: the line under the table says which did).
Reported: env steps, wall seconds of the iterations (start-up apart), env-steps/s; the scaling
efficiency (2 workers' rate ÷ twice 1 worker's) per backend; Ray ÷ local at equal workers.

    flock /tmp/bench.lock python benchmarks/ars_ray_scaling.py --iterations 10 \
        --append BENCHMARKS.md
"""

from __future__ import annotations

import os

from common import load_span, parser, publish_section, script, section_head, table, time_ars

from rlpipe import EnvConfig
from rlpipe.envs.backends import backend_of

RUNS = [("local", 1), ("local", 2), ("ray", 1), ("ray", 2)]


def run(seed: int, iterations: int, backend: str, workers: int) -> dict:
    """``iterations`` ARS iterations on BipedalWalker-v3 with this backend and worker count."""
    return time_ars(
        seed,
        iterations,
        f"algo.workers={workers}",
        f"algo.backend={backend}",
        f"algo.ray.num_cpus={os.cpu_count()}",
    )


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=10)
    p.set_defaults(seeds=[1])
    args = p.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    seed = args.seeds[0]
    load_before = os.getloadavg()
    results = {key: run(seed, args.iterations, *key) for key in RUNS}
    load_after = os.getloadavg()
    rate = {key: r["steps"] / r["seconds"] for key, r in results.items()}
    same = [key for key, r in results.items() if r["theta"].equal(results[RUNS[0]]["theta"])]
    rows = [
        [
            backend,
            workers,
            f"{r['steps']:,}",
            f"{r['seconds']:.1f}",
            f"{r['startup']:.1f}",
            f"{rate[backend, workers]:,.0f}",
            f"{rate[backend, workers] / rate['local', workers]:.2f}",
        ]
        for (backend, workers), r in results.items()
    ]
    efficiency = {b: rate[b, 2] / (2 * rate[b, 1]) for b in ("local", "ray")}
    head = section_head(
        "ARS on Ray vs local, BipedalWalker-v3",
        ["torch", "torchrl", "gymnasium", "envpool", "ray"],
        load_span(load_before, load_after),
        f"{args.iterations} iterations, seed {seed}, the notebook's settings (`~tuned`), "
        f"env backend {backend_of(EnvConfig(id='BipedalWalker-v3'))} (`env.backend=auto`)",
    )
    headers = ["backend", "workers", "env steps", "wall s", "start-up s", "env-steps/s"]
    report = "\n".join(
        [
            *head,
            table([*headers, "÷ local, same workers"], rows),
            "",
            f"Scaling efficiency (2 workers ÷ (2 × 1 worker)): local {efficiency['local']:.2f}, "
            f"Ray {efficiency['ray']:.2f}. Runs whose final θ equals local/1's: "
            + ", ".join(f"{backend}/{workers}" for backend, workers in same)
            + (
                "."
                if len(same) == len(RUNS)
                else " (Box2D carries state across resets: see the script's docstring)."
            ),
        ]
    )
    publish_section(report, args.append)


if __name__ == "__main__":
    script(main)
