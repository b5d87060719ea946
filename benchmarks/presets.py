"""Every tuned preset on its held-out seeds, beside SB3 with the RL Zoo's settings: one section.

The protocol (``presets_table.py``): presets are tuned on seeds below 100 or from 1000 up and
published on their held-out seeds, 100-109 (``sac_bipedal``: 100-102), which no tuning run may
touch. By default every preset runs on its held-out seeds; ``--tune --seeds 0 1 2`` runs tuning
seeds and refuses any seed from 100 to 999, and ``--override`` (anything beyond ``env.backend``,
``threads``, ``device``) needs ``--tune``. Solved, per seed: the last three evals' mean and the
final 100-episode greedy eval both ≥ the target. The section (``presets_report.py``) gives per
preset the seeds solved, the IQM of the final evals with a 95% bootstrap CI, frames and training
seconds to the target, SB3's figures on the same seeds and the ratio of training seconds to the
target; over all presets the IQM of the normalised finals with a 95% stratified-bootstrap CI, and
with ``--figure`` the performance profile as a PNG (``presets_figure.py``).

How the runs run (``presets_runs.py``, ``presets_sb3.py``): each rlpipe run as a user runs it, in
a subprocess, then ``python -m rlpipe.evaluate``; SB3 in a spawned process. ``--jobs`` runs go at
once (rlpipe seed s and SB3 seed s side by side). Runs finished in ``--out`` by an earlier call
are read, not run again (taking no slot), with the machine they ran on, so an interrupted
benchmark continues (the hours-long presets from their last eval, on both sides) and the section
can be made again. Ctrl-C or SIGTERM stops every run where it is, saved (``presets_stop.py``),
and ends the call with one line; a kill leaves no run training on. ``--read-only`` makes the
section from what ``--out`` holds and runs nothing (runs not there: left out, an SB3 run under
way with the frames of its newest save).
Each job leaves a small record (``rlpipe.json``, ``sb3.json``: evals, final eval, machine, load);
under ``benchmarks/results/presets`` git keeps the records and ignores the run dirs, so the
published table is remade from the repo and a benchmark spread over machines and days goes on.
Git keeps SB3's ARS saves too (tens of KB, no replay buffer): its hours-long seeds go on from
them on the next machine; the other saves stay on the machine that made them.

    pip install -e ".[dev,bench]"
    python benchmarks/presets.py --sb3 --out benchmarks/results/presets --append BENCHMARKS.md \
        --figure docs/presets_profile.png                                  # everything (long)
    python benchmarks/presets.py --presets dqn_cartpole --sb3 --out benchmarks/results/presets
    python benchmarks/presets.py --sb3 --out benchmarks/results/presets --read-only \
        --append BENCHMARKS.md
    python benchmarks/presets.py --presets dqn_cartpole --tune --seeds 0 1 2   # tuning
    python benchmarks/screen.py --preset dqn_cartpole A=DIR_A B=DIR_B     # arms compared
    python benchmarks/presets.py --presets dqn_cartpole --seeds 100 --frames 2000 \
        --final-episodes 3 --sb3                                           # smoke test
"""

from __future__ import annotations

import argparse
import importlib.resources
import importlib.util
import os
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import NoReturn

from common import compose_run, load_span, parser, publish_section, script, section_head
from presets_figure import profile_figure
from presets_report import machines, profile_series, seed_text, tables
from presets_runs import PACKAGES, Run, Scheduler, rlpipe_finished, rlpipe_job
from presets_sb3 import Sb3Saves, sb3_finished, sb3_job
from presets_stop import Stop, stop_runs, stop_signals
from presets_table import PRESETS, Preset, seeds_for

from rlpipe.config import Config
from rlpipe.errors import RlpipeError, check


def choose_presets(names: list[str] | None) -> list[Preset]:
    """The presets asked for (default: every one whose ``conf/experiment`` YAML exists)."""
    exists = {
        name: (importlib.resources.files("rlpipe.conf") / "experiment" / f"{name}.yaml").is_file()
        for name in PRESETS
    }
    if names is None:
        for name in (n for n, ok in exists.items() if not ok):
            print(f"presets: skipping {name}: no conf/experiment/{name}.yaml", file=sys.stderr)
        return [p for name, p in PRESETS.items() if exists[name]]
    for name in names:
        check(name in PRESETS, f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
        check(exists[name], f"preset {name!r} has no conf/experiment/{name}.yaml (yet)")
    return [PRESETS[name] for name in dict.fromkeys(names)]


def compose(preset: Preset, frames: int | None, extra: list[str]) -> Config:
    """The preset's resolved config (budget, eval cadence) as its runs will see it."""
    overrides = [f"+experiment={preset.experiment}", *extra]
    overrides += [f"total_frames={frames}"] if frames is not None else []
    try:
        return compose_run(*overrides).resolved()
    except Exception as e:
        raise RlpipeError(f"+experiment={preset.experiment} does not compose: {e}") from e


def arguments() -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    """The command line's parser and its arguments."""
    p = parser(
        __doc__.splitlines()[0], "each preset's held-out seeds (100-109; sac_bipedal 100-102)"
    )
    p.set_defaults(seeds=None)  # None: each preset's held-out seeds
    p.epilog = (
        "Ctrl-C or SIGTERM stops every run where it is, saved; the same command (the same --out) "
        "continues."
    )
    p.add_argument("--presets", nargs="+", metavar="NAME", help=f"of: {', '.join(PRESETS)}")
    p.add_argument(
        "--tune", action="store_true", help="a tuning run: --seeds below 100 or from 1000 up"
    )
    p.add_argument("--sb3", action="store_true", help="also run SB3 with the RL Zoo's settings")
    p.add_argument(
        "--jobs",
        type=int,
        default=max(1, (os.cpu_count() or 2) // 2),
        help="runs at once (default: half the cores)",
    )
    p.add_argument("--frames", type=int, help="override every preset's budget (smoke tests)")
    p.add_argument("--final-episodes", type=int, help="override the final eval's episodes")
    p.add_argument(
        "--override",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="added to every rlpipe run (repeatable); beyond env.backend, threads and device "
        "only with --tune",
    )
    p.add_argument(
        "--out",
        type=Path,
        help="where the run dirs go (default: a temp dir); runs finished there by an earlier "
        "call are read, not run again (an interrupted benchmark continues)",
    )
    p.add_argument("--figure", type=Path, help="write the performance profile to this PNG")
    p.add_argument(
        "--read-only",
        action="store_true",
        help="run nothing: the section from the runs finished in --out (the others left out)",
    )
    return p, p.parse_args()


def checked(args: argparse.Namespace) -> tuple[list[Preset], dict[str, tuple[int, ...]]]:
    """The presets and each one's seeds, or a one-line error for what the protocol refuses."""
    check(args.jobs >= 1, "--jobs must be at least 1")
    check(args.out is not None or not args.read_only, "--read-only reads --out: name it")
    smoke = args.frames is not None or args.final_episodes is not None
    check(
        not (args.append and (args.tune or smoke)),
        "--append publishes results: not with --tune, --frames or --final-episodes",
    )
    presets = choose_presets(args.presets)
    seeds = seeds_for(presets, args.seeds, args.tune, args.override)
    if args.sb3:
        needed = {"stable_baselines3"} | {"sb3_contrib" for p in presets if p.sb3_algo == "ARS"}
        missing = sorted(m for m in needed if importlib.util.find_spec(m) is None)
        check(not missing, f'--sb3 needs {", ".join(missing)}: pip install -e ".[bench]"')
    return presets, seeds


def plan(
    args: argparse.Namespace,
    presets: list[Preset],
    seeds: dict[str, tuple[int, ...]],
    configs: dict[str, Config],
    out: Path,
) -> tuple[list[list[tuple]], list[tuple[str, int, str, int | None]]]:
    """The jobs, a group per preset and seed (rlpipe's run, and SB3's where it runs), each with
    whether ``out`` holds it finished, and with ``--read-only`` the runs left out since ``out``
    has no finished one, each with the frames of its newest SB3 save (None: none)."""
    groups, missing = [], []
    for preset in presets:
        episodes = args.final_episodes or preset.final_episodes
        cfg = configs[preset.experiment]
        for seed in seeds[preset.experiment]:
            where = out / preset.experiment / f"seed{seed}"
            ours = partial(rlpipe_job, preset, cfg, seed, args.frames, episodes, where)
            jobs = [("rlpipe", partial(ours, args.override), partial(rlpipe_finished, cfg=cfg))]
            if args.sb3 and preset.sb3 is not None:
                jobs.append(
                    ("SB3", partial(sb3_job, preset, cfg, seed, episodes, where), sb3_finished)
                )
            group = []
            for which, job, finished in jobs:
                done = finished(where)
                if args.read_only and not done:
                    save = Sb3Saves(where / "sb3-saves").newest() if which == "SB3" else None
                    frames = save.evals[-1][0] if save else None
                    missing.append((preset.experiment, seed, which, frames))
                else:
                    group.append((preset.experiment, seed, which, job, done))
            groups += [group] if group else []
    return groups, missing


def section(
    args: argparse.Namespace,
    presets: list[Preset],
    configs: dict[str, Config],
    runs: list[Run],
    loads: list[tuple[float, ...]],
    wall: float,
    missing: list[tuple[str, int, str, int | None]],
) -> str:
    """The benchmark's section of BENCHMARKS.md."""
    used = seed_text(sorted({r.seed for r in runs}))
    title, seeds = (
        "Tuned presets",
        (
            f"seeds: held-out, {used}; no tuning run, sweep or trial used them (each preset's "
            "tuning seeds: its note)"
        ),
    )
    if args.tune:
        title, seeds = (
            "Tuned presets — TUNING seeds",
            f"seeds: TUNING, {used} (--tune): not a result",
        )
    if args.override:  # its own section: env.backend=gymnasium beside the default backend
        title += f" — {' '.join(args.override)}"
    if args.frames is not None or args.final_episodes is not None:
        title += " — smoke test, budgets overridden"
    reused = sum(r.reused for r in runs)
    starts: dict[str, list[float]] = {}  # per machine: its cores set what a load means
    labels = machines(runs)
    for r in runs:
        if r.load:
            starts.setdefault(labels[r.machine], []).append(r.load[0])
    ran = f"{args.jobs} run(s) at once; " if reused < len(runs) else ""  # none ran: no jobs
    facts = [
        seeds,
        f"{ran}{wall / 60:.1f} min in all"
        + (
            f"; {reused} of {len(runs)} runs read back from earlier calls' `--out`"
            if reused
            else ""
        ),
    ]
    if starts:  # the call's own load says nothing of runs read back: theirs, from the records
        spans = "; ".join(
            f"{tag} {min(loads):.2f}–{max(loads):.2f}" for tag, loads in starts.items()
        )
        facts.append(f"1-min load average at the runs' starts: {spans}")
    if missing:  # per preset, each side's seeds: "dqn_cartpole (rlpipe 101, SB3 101)"
        sides: dict[str, dict[str, list[int]]] = {}
        saved: dict[str, list[str]] = {}  # SB3 runs under way: "102 at 8,000,000"
        for name, seed, which, frames in missing:
            sides.setdefault(name, {}).setdefault(which, []).append(seed)
            saved.setdefault(name, []).extend([f"{seed} at {frames:,}"] if frames else [])
        under_way = {
            name: f"; SB3 saved, to go on from: {', '.join(at)} frames" if at else ""
            for name, at in saved.items()
        }
        left = "; ".join(
            f"{name} ("
            + ", ".join(f"{w} {seed_text(s)}" for w, s in by.items())
            + f"{under_way[name]})"
            for name, by in sides.items()
        )
        facts.append(
            f"no record in `--out` of the preset as it is now, left out (`--read-only`): {left}"
        )
    if args.figure is not None:
        shown = args.figure
        if args.append:
            shown = Path(os.path.relpath(args.figure.resolve(), args.append.resolve().parent))
        facts.append(f"performance profile: ![performance profile]({shown.as_posix()})")
    head = section_head(title, PACKAGES, load_span(*loads), *facts)
    return "\n".join(head + tables(presets, configs, runs, own=not args.override))


def stopped(scheduler: Scheduler, stop: Stop, out: Path | None) -> NoReturn:
    """Stop the runs under way (:mod:`presets_stop`), wait for them, say so in one line, exit."""
    asked = stop_runs()
    print(
        f"presets: {stop}: stopping {asked} run(s) where they are (another signal kills them)",
        file=sys.stderr,
        flush=True,
    )
    scheduler.wait()
    kept = f"the same command continues from what they saved under {out}"
    if out is None:
        kept = "they ran in a temporary dir, now gone (--out keeps runs to continue)"
    print(f"presets: stopped by {stop}; {kept}", file=sys.stderr)
    sys.exit(128 + stop.signum)


def main() -> None:
    p, args = arguments()
    try:
        presets, seeds = checked(args)
        configs = {pr.experiment: compose(pr, args.frames, args.override) for pr in presets}
    except RlpipeError as e:
        p.exit(2, f"presets.py: error: {e}\n")
    with tempfile.TemporaryDirectory(prefix="presets-") as tmp:
        out = (args.out or Path(tmp)).resolve()
        print(f"presets: run dirs under {out}", file=sys.stderr)
        groups, missing = plan(args, presets, seeds, configs, out)
        total = sum(len(g) for g in groups)
        read_back = sum(job[4] for g in groups for job in g)
        print(f"presets: {read_back} of {total} runs read back from earlier calls", file=sys.stderr)
        loads, start = [os.getloadavg()], time.perf_counter()
        scheduler = Scheduler(args.jobs, total, read_back)
        with stop_signals():
            try:
                for group in groups:
                    scheduler.group(group)
                runs = scheduler.results()
            except Stop as stop:
                stopped(scheduler, stop, args.out)
        loads.append(os.getloadavg())
        wall = time.perf_counter() - start
    if args.figure is not None:
        used = f"seeds {seed_text(sorted({r.seed for r in runs}))}"
        profile_figure(profile_series(presets, runs), args.figure, used)
    publish_section(section(args, presets, configs, runs, loads, wall, missing), args.append)


if __name__ == "__main__":
    script(main)
