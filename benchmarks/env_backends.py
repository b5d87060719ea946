"""Env backends in the training loop: each preset's env steps/s on gymnasium and on EnvPool.

One preset per env and algorithm, each measured in a fresh process (this script with
``--measure``) that builds it as ``python -m rlpipe +experiment=<preset> env.backend=<b>`` does
(the run's threads, its env factory and seeds, ARS's workers started first), then times
``train_step`` for a frame or iteration budget: env steps per wall second of the training
loop, updates included (not the raw env). DQN and SAC presets are timed from their
``algo.learning_starts`` on, as they spend nearly all their frames: the random-action start
before it (all of a 1,000-frame budget for ``sac_bipedal``, which starts at 10,000) is untimed.
The main job, ``python -m rlpipe algo=ars env=bipedal`` (a frame budget, no evaluation but the
final one-episode one), is timed whole beside the notebook's loop (``reference_ars.py``).
Backends take turns within every round (A B A B ...), the rounds run alone and then beside a
CPU-bound competitor (``python -c "while True: pass"``); a cell is the median over rounds, a
ratio the median of the rounds' ratios.
Each measurement is saved to ``--state`` as it ends: a call with the same file continues.

    python benchmarks/env_backends.py --rounds 3 --append BENCHMARKS.md
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from functools import partial
from pathlib import Path
from statistics import median
from typing import Any

from common import busy, machine, publish_section, ratio_cell, script, table

BACKENDS = ("gymnasium", "envpool")
CONDITIONS = ("alone", "beside a busy core")
# preset -> (the env and its copies, as the table names them; budget: frames or ARS iterations,
# timed after an off-policy preset's learning_starts frames: about 2 s or more of its updates)
PRESETS = {
    "ars_bipedal": ("BipedalWalker-v3, 64 episodes", ("iterations", 1)),
    # from a walking policy (WALKER): the phase where a 16 M-frame run spends most of its frames
    "ars_bipedal:walking": ("BipedalWalker-v3, from a walking policy", ("iterations", 2)),
    "ars_pendulum": ("Pendulum-v1, ARS", ("iterations", 20)),
    "ars_cartpole": ("CartPole-v1, ARS", ("iterations", 10)),
    "dqn_cartpole": ("CartPole-v1 ×16, DQN", ("frames", 8_192)),
    # 40 updates: where most seeds' runs reach 500 (the span a time to the target measures)
    "ppo_cartpole": ("CartPole-v1 ×16, PPO", ("frames", 20_480)),
    "ppo_lunarlander": ("LunarLander-v3 ×16, PPO", ("frames", 16_384)),
    "dqn_lunarlander": ("LunarLander-v3 ×8, DQN", ("frames", 3_000)),
    "dqn_mountaincar": ("MountainCar-v0 ×8, DQN", ("frames", 6_144)),
    "dqn_acrobot": ("Acrobot-v1 ×8, DQN", ("frames", 3_000)),
    "sac_pendulum": ("Pendulum-v1, SAC", ("frames", 1_000)),
    "sac_bipedal": ("BipedalWalker-v3, SAC", ("frames", 512)),
    "sac_mountaincar_continuous": ("MountainCarContinuous-v0, SAC", ("frames", 2_000)),
}
MAIN_JOB = ["algo=ars", "env=bipedal"]
MAIN_FRAMES = 150_000
REFERENCE_ITERATIONS = 3
# a walking linear policy and its normaliser, as ars_bipedal's checkpoint holds them (tuning seed
# 22 after 16 M frames: a 100-episode greedy mean of 297), that "<preset>:walking" starts from
WALKER = Path(__file__).parent / "results" / "ars_bipedal_walker.json"


def load_walker(policy: Any) -> None:
    """Put :data:`WALKER`'s θ and normaliser into ``policy`` (``ars_bipedal``'s ARS policy)."""
    import torch

    walker = json.loads(WALKER.read_text())
    own = policy.state_dict()
    policy.load_state_dict({k: torch.tensor(walker[k], dtype=v.dtype) for k, v in own.items()})


def measure(preset: str, backend: str) -> dict:
    """Build ``preset`` on ``backend`` as a run does and time its training loop."""
    from rlpipe.algos import make_algorithm
    from rlpipe.cli import compose_run
    from rlpipe.envs import make_env
    from rlpipe.envs.backends import resolve_backend
    from rlpipe.runtime import env_threads, resolve_device, seed_everything, set_threads

    name, _, start = preset.partition(":")
    cfg = compose_run(f"+experiment={name}", f"env.backend={backend}", "seed=0").resolved()
    cfg = replace(cfg, env=resolve_backend(cfg.env)[0])
    device = resolve_device(cfg.device)
    seed_everything(0)
    set_threads(cfg.threads, device)
    factory = partial(make_env, cfg.env, seed=0, threads=env_threads(cfg.threads))
    algo = make_algorithm(factory, cfg.algo, device=device)
    unit, budget = PRESETS[preset][1]
    if start == "walking":
        load_walker(algo.policy)
    try:
        if hasattr(algo, "search"):
            algo.search.start()  # its workers or pool, started before the clock
        warmup = getattr(cfg.algo, "learning_starts", 0)  # off-policy: its random-action start
        while algo.frames < warmup:
            algo.train_step()
        done = partial(getattr, algo, unit)  # iterations or frames so far
        end, frames, start = done() + budget, algo.frames, time.perf_counter()
        while done() < end:
            algo.train_step()
        seconds = time.perf_counter() - start
        return {"steps": algo.frames - frames, "seconds": seconds, "from": frames}
    finally:
        algo.close()


def main_job(backend: str) -> dict:
    """``python -m rlpipe algo=ars env=bipedal`` for :data:`MAIN_FRAMES` frames: its frames
    over its own wall seconds (start-up and the final one-episode evaluation included)."""
    with tempfile.TemporaryDirectory() as tmp:
        overrides = [
            f"env.backend={backend}",
            f"total_frames={MAIN_FRAMES}",
            "eval_every=0",
            "eval_episodes=1",
            "checkpoint_every=0",
            "logger=none",
            "progress=false",
            f"hydra.run.dir={tmp}",
        ]
        subprocess.run([sys.executable, "-m", "rlpipe", *MAIN_JOB, *overrides], check=True)
        summary = json.loads((Path(tmp) / "summary.json").read_text())
        return {"steps": summary["frames"], "seconds": summary["wall_time"]}


def reference() -> dict:
    """The notebook's loop (``reference_ars.py``, one process) for a few iterations."""
    from ars_throughput import run_reference

    return run_reference(1, REFERENCE_ITERATIONS)


def run_measure(what: str, backend: str) -> dict:
    """One measurement in a fresh process (this script with ``--measure``)."""
    out = subprocess.run(
        [sys.executable, __file__, "--measure", what, backend],
        check=True,
        capture_output=True,
        text=True,
        env={**os.environ, "SDL_VIDEODRIVER": "dummy"},
    ).stdout
    return json.loads(out.strip().splitlines()[-1])


def jobs() -> list[tuple[str, str]]:
    """Every measurement of a round, backends taking turns."""
    named = [(name, backend) for name in PRESETS for backend in BACKENDS]
    main = [("main job", backend) for backend in BACKENDS]
    return [*named, *main, ("notebook loop", "-")]


def collect(state: Path, rounds: int) -> list[dict]:
    """Run what ``state`` does not hold yet; every record, in order."""
    done = [json.loads(line) for line in state.read_text().splitlines()] if state.exists() else []
    have = {(r["condition"], r["round"], r["name"], r["backend"]) for r in done}
    for condition in CONDITIONS:
        todo = [
            (k, name, backend)
            for k in range(rounds)
            for name, backend in jobs()
            if (condition, k, name, backend) not in have
        ]
        if not todo:
            continue
        with busy(condition != "alone"):
            for k, name, backend in todo:
                load = os.getloadavg()[0]
                result = run_measure(name, backend)
                record = {"condition": condition, "round": k, "name": name, "backend": backend}
                record.update(result, load=load)
                done.append(record)
                with state.open("a") as f:
                    f.write(json.dumps(record) + "\n")
                print(json.dumps(record), file=sys.stderr)
    return done


def rate(record: dict) -> float:
    return record["steps"] / record["seconds"]


def cell(values: list[float], digits: int = 0) -> str:
    return f"{median(values):,.{digits}f}"


def auto_backend(preset: str) -> str:
    """The backend ``env.backend=auto`` (the preset's default, unless it names one) picks for
    ``preset`` here, as a run resolves it."""
    from rlpipe.cli import compose_run
    from rlpipe.envs.backends import resolve_backend

    cfg = compose_run(f"+experiment={preset}").resolved()
    return resolve_backend(cfg.env, copies=cfg.stepped_copies())[0].backend


def report(records: list[dict], rounds: int) -> str:
    """The Markdown section: per preset and condition, each backend's env steps/s and the ratio;
    the main job beside the notebook's loop."""
    by = {}
    for r in records:
        by.setdefault((r["condition"], r["name"], r["backend"]), []).append(r)
    rows, main_rows, loads = [], [], {}
    runs_on = {name: auto_backend(name.partition(":")[0]) for name in PRESETS}
    for condition in CONDITIONS:
        loads[condition] = [r["load"] for r in records if r["condition"] == condition]
        for name, (what, _) in PRESETS.items():
            gym, pool = (by.get((condition, name, b), []) for b in BACKENDS)
            if not (gym and pool):
                continue
            ratios = [rate(p) / rate(g) for g, p in zip(gym, pool)]
            rows.append(
                [
                    condition,
                    f"`{name.partition(':')[0]}`",
                    what,
                    cell([rate(g) for g in gym]),
                    cell([rate(p) for p in pool]),
                    ratio_cell(ratios),
                    runs_on[name],
                ]
            )
        notebook = by.get((condition, "notebook loop", "-"), [])
        gym = by.get((condition, "main job", "gymnasium"), [])
        for backend in BACKENDS:
            runs = by.get((condition, "main job", backend), [])
            if not (runs and notebook and gym):
                continue
            of_gym = [rate(r) / rate(g) for r, g in zip(runs, gym)]
            of_notebook = [rate(r) / rate(n) for r, n in zip(runs, notebook)]
            main_rows.append(
                [
                    condition,
                    f"main job, env.backend={backend}",
                    cell([rate(r) for r in runs]),
                    ratio_cell(of_gym),
                    ratio_cell(of_notebook),
                ]
            )
        if notebook:
            main_rows.append(
                [
                    condition,
                    "notebook loop (reference_ars.py, 1 process)",
                    cell([rate(n) for n in notebook]),
                    "–",
                    "1.00×",
                ]
            )
    load_text = "; ".join(f"{c}: {min(v):.2f}–{max(v):.2f}" for c, v in loads.items() if v)
    return "\n".join(
        [
            "## Env backends in the training loop (benchmarks/env_backends.py)",
            "",
            f"- machine: {machine(['torch', 'torchrl', 'gymnasium', 'envpool', 'numpy'])}",
            f"- command: `python benchmarks/env_backends.py --rounds {rounds}`; 1-min load "
            f"average before each measurement: {load_text}",
            "- env steps/s of the training loop (updates included; ARS: rollouts and the "
            "update, workers started before the clock; DQN and SAC: timed from their "
            "`algo.learning_starts`, past the random-action start), each in a fresh process "
            "built as "
            "`python -m rlpipe +experiment=<preset> env.backend=<b> seed=0` builds it; median "
            f"of {rounds} interleaved rounds; ratio: EnvPool ÷ gymnasium, median (range) of "
            'the rounds\' ratios; busy core: `python -c "while True: pass"` beside it; '
            "the preset runs on: the backend `python -m rlpipe +experiment=<preset>` takes "
            "(its `env.backend`, auto unless it names one: EnvPool where it runs the id, but "
            "gymnasium for one env copy; `rlpipe/envs/backends.py:resolve_backend`)",
            "",
            table(
                [
                    "condition",
                    "preset",
                    "env, copies",
                    "gymnasium steps/s",
                    "EnvPool steps/s",
                    "EnvPool ÷ gymnasium",
                    "the preset runs on",
                ],
                rows,
            ),
            "",
            f"Main job, `python -m rlpipe {' '.join(MAIN_JOB)} total_frames={MAIN_FRAMES:,} "
            "eval_every=0 eval_episodes=1 checkpoint_every=0 logger=none progress=false` "
            "(frames over the run's own wall seconds, start-up and the final evaluation "
            f"included), beside the notebook's loop ({REFERENCE_ITERATIONS} iterations, seed 1):",
            "",
            table(
                ["condition", "run", "frames/s", "÷ gymnasium main job", "÷ notebook loop"],
                main_rows,
            ),
        ]
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds per condition")
    p.add_argument(
        "--state",
        type=Path,
        default=Path("env_backends.jsonl"),
        help="measurements so far (a call with the same file continues)",
    )
    p.add_argument("--append", type=Path, help="put the section into this Markdown file")
    p.add_argument("--measure", nargs=2, metavar=("WHAT", "BACKEND"), help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.measure:
        what, backend = args.measure
        if what == "main job":
            result = main_job(backend)
        elif what == "notebook loop":
            result = reference()
        else:
            result = measure(what, backend)
        print(json.dumps(result))
        return
    records = collect(args.state, args.rounds)
    publish_section(report(records, args.rounds), args.append)


if __name__ == "__main__":
    script(main)
