"""ARS throughput on BipedalWalker-v3: rlpipe's ARS vs the notebook's loop (reference_ars.py).

Each runs in this process, one after the other, with the notebook's hyper-parameters (16
directions, all kept, α 0.02, ν 0.03, clipped rewards, normalised observations: rlpipe with
``~tuned``, not the tuned preset the main job picks), the same seed and number of iterations;
rlpipe on both env backends (gymnasium's vector envs and EnvPool), with 1 worker and with one
per core. Reported: env steps, wall seconds of the iterations (rlpipe's worker start-up is
excluded and shown apart) and env-steps/s; the ratio is against the reference. The reference's
steps include its one evaluation episode per iteration (part of the notebook loop). The ceiling
row runs one reference loop per core at once, each in its own process (same seed): what the
machine gives independent single-process loops, with no coordination and no waiting for the
slowest episode; the line under the table puts rlpipe's multi-worker runs against it. CPU
µs/step (CPU time per env step: the reference's process, rlpipe's rollouts in every process)
shows the per-step cost apart from the machine's load.

With ``--repeats R`` the runs of a seed go round R times, interleaved, and each cell is the
median over the rounds (the ratio: the median of each round's ratio to that round's
reference), so a burst of load on a shared machine moves one round, not the result. Each
condition (``--conditions``: alone, and beside a CPU-bound competitor process) has its rows.

    python benchmarks/ars_throughput.py --iterations 10 --repeats 3 --append BENCHMARKS.md
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from statistics import median

from common import (
    busy,
    load_span,
    parser,
    publish_section,
    ratio_cell,
    script,
    section_head,
    table,
    time_ars,
)
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


def _reference_job(seed: int, iterations: int, results: mp.Queue) -> None:
    results.put(run_reference(seed, iterations))


def run_reference_copies(seed: int, iterations: int, copies: int) -> dict:
    """``copies`` reference loops in as many processes at once: their summed steps and CPU
    over the wall time until the last one ends."""
    ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
    results = ctx.Queue()
    procs = [
        ctx.Process(target=_reference_job, args=(seed, iterations, results)) for _ in range(copies)
    ]
    start = time.perf_counter()
    for proc in procs:
        proc.start()
    runs = [results.get() for _ in procs]
    seconds = time.perf_counter() - start
    for proc in procs:
        proc.join()
    return {
        "steps": sum(r["steps"] for r in runs),
        "seconds": seconds,
        "cpu": sum(r["cpu"] for r in runs),
        "startup": 0.0,
    }


def rate(run: dict) -> float:
    """Env steps per wall second."""
    return run["steps"] / run["seconds"]


CONDITIONS = {"alone": False, "busy": True}
BESIDE = {"alone": "alone", "busy": "beside a busy core"}


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--repeats", type=int, default=1, help="interleaved rounds per seed")
    p.add_argument(
        "--conditions",
        nargs="+",
        choices=list(CONDITIONS),
        default=list(CONDITIONS),
        help="alone, and beside a CPU-bound competitor process (default: both)",
    )
    p.set_defaults(seeds=[1])
    args = p.parse_args()
    rows = []
    load_before = os.getloadavg()
    cores = os.cpu_count() or 1
    reference = "reference (notebook loop, 1 process)"
    ceiling = f"ceiling: {cores} reference loops at once, 1 process each"
    rlpipe = {
        f"rlpipe ARS, env.backend={backend}, algo.workers={n}": (backend, workers)
        for backend in ("gymnasium", "envpool")
        for n, workers in ((1, 1), (cores, 0))
    }
    parallel = [name for name, (_, workers) in rlpipe.items() if workers == 0]

    def run(name: str, seed: int) -> dict:
        if name == reference:
            return run_reference(seed, args.iterations)
        if name == ceiling:
            return run_reference_copies(seed, args.iterations, cores)
        backend, workers = rlpipe[name]
        overrides = (f"algo.workers={workers}", f"env.backend={backend}")
        return time_ars(seed, args.iterations, *overrides)

    def rate_ratios(rounds: list[dict], name: str, base: str) -> list[float]:
        return [rate(r[name]) / rate(r[base]) for r in rounds]

    names = [reference, ceiling, *rlpipe]
    of_ceiling = []
    for condition in args.conditions:
        for seed in args.seeds:
            with busy(CONDITIONS[condition]):
                rounds = [{name: run(name, seed) for name in names} for _ in range(args.repeats)]
            for name in parallel:
                of_ceiling.append(
                    f"{BESIDE[condition]}, seed {seed}, {name.removeprefix('rlpipe ARS, ')} "
                    + ratio_cell(rate_ratios(rounds, name, ceiling))
                )
            for name in names:
                done = [r[name] for r in rounds]
                rows.append(
                    [
                        BESIDE[condition],
                        seed,
                        name,
                        f"{median(r['steps'] for r in done):,.0f}",
                        f"{median(r['seconds'] for r in done):.1f}",
                        f"{median(r['startup'] for r in done):.1f}",
                        f"{median(r['cpu'] / r['steps'] for r in done) * 1e6:.0f}",
                        f"{median(rate(r) for r in done):,.0f}",
                        ratio_cell(rate_ratios(rounds, name, reference)),
                    ]
                )
    head = section_head(
        "ARS throughput on BipedalWalker-v3: rlpipe vs the notebook's loop",
        ["torch", "torchrl", "gymnasium", "envpool", "numpy"],
        load_span(load_before, os.getloadavg()),
        f"{args.iterations} iterations with the notebook's settings, median of {args.repeats} "
        'interleaved round(s) per seed; busy core: `python -c "while True: pass"` beside it',
    )
    headers = ["condition", "seed", "run", "env steps", "wall s", "start-up s"]
    headers += ["CPU µs/step", "env-steps/s", "vs reference"]
    report = "\n".join(
        [
            *head,
            table(headers, rows),
            "",
            "rlpipe's multi-worker runs ÷ ceiling, env-steps/s (median, range over rounds): "
            + "; ".join(of_ceiling),
        ]
    )
    publish_section(report, args.append)


if __name__ == "__main__":
    script(main)
