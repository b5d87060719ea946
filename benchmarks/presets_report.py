"""The Markdown section of benchmarks/presets.py: a row per preset, the aggregate, a row per seed.

Per preset: seeds solved (the protocol's rule: the last three evals' mean and the final greedy
eval both ≥ the target), the interquartile mean (IQM) of the final evals with its 95% bootstrap
interval over seeds, frames and training seconds to the target (first eval ≥ it: median and
range over the seeds that reach it), the same for SB3 with the RL Zoo's settings on the same
seeds, and the median over seeds both reach (run on one machine) of rlpipe's training seconds
to the target over SB3's. Over all presets: the IQM of the normalised finals with a 95%
stratified-bootstrap interval (rliable's protocol), and the performance-profile figure
(``presets_figure.py``).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from common import table
from presets_runs import Run
from presets_table import Preset

from rlpipe.config import Config
from rlpipe.stats import iqm, pooled_iqm, pooled_iqm_band

DASH = "–"
TUNING_LOG = "docs/tuning.md"  # a section per preset: what was tried, the checks run after
SHARED = "‡"  # beside a side's figures evaluated on the starts every seed met
SHARED_NOTE = (
    f"{SHARED} beside a seed's or preset's seeds (rlpipe) or its SB3 solved cell: evaluated "
    "before each run's evaluations met starts of their own: every held-out "
    "seed's periodic evals met nearly the same episode starts (seed + 10000 on consecutive "
    "seeds), and every final eval seed 0's 100, which the tuning runs' final evals met too; "
    "such records are kept until run again"
)
DAYS = "runs on different days"  # beside a ratio whose two sides ran on different days
DAYS_NOTE = (
    f'a ratio marked "{DAYS}" compares the two sides\' runs on one machine on different '
    "days (one side re-run or run later), not runs made beside each other"
)
SPEED_TARGET = 0.5  # the issue's aim: rlpipe's time to the target at most half SB3's
SOLVED_TARGET = 0.8  # and 8 of 10 held-out seeds solved


def seed_text(seeds: Sequence[int]) -> str:
    """The seeds in order, each run of three or more consecutive ones as ``first–last``
    (``0–9, 90–99``; ``3, 4``)."""
    runs: list[list[int]] = []
    for seed in sorted(seeds):
        if runs and seed == runs[-1][-1] + 1:
            runs[-1].append(seed)
        else:
            runs.append([seed])
    parts = [f"{r[0]}–{r[-1]}" if len(r) > 2 else ", ".join(map(str, r)) for r in runs]
    return ", ".join(parts) or DASH


def spread(values: Sequence[float], fmt: str) -> str:
    """``median (min–max)`` of ``values``; ``–`` when there are none."""
    if not values:
        return DASH
    low, high = min(values), max(values)
    text = format(statistics.median(values), fmt)
    return text if low == high else f"{text} ({low:{fmt}}–{high:{fmt}})"


def iqm_cell(finals: Sequence[float]) -> str:
    """The IQM of the finals with its 95% bootstrap interval over seeds."""
    if not finals:
        return DASH
    low, high = pooled_iqm_band([np.asarray(finals, dtype=float)])
    return f"{float(iqm(np.asarray(finals, dtype=float))):.1f} [{low:.1f}, {high:.1f}]"


@dataclass
class Side:
    """One library's runs of one preset, and what the table says of them."""

    preset: Preset
    runs: list[Run]

    @property
    def finals(self) -> list[float]:
        return [r.final for r in self.runs if r.final is not None]

    @property
    def normalised(self) -> np.ndarray:
        """The finals on the scale where a random policy is 0 and the target 1."""
        return np.array([self.preset.normalised(x) for x in self.finals])

    @property
    def hits(self) -> dict[int, tuple[int, float]]:
        """seed -> (frames, training seconds) at its first eval ≥ the target."""
        hits = {r.seed: r.hit(self.preset.target) for r in self.runs}
        return {seed: hit for seed, hit in hits.items() if hit is not None}

    def solved_count(self) -> int:
        return sum(r.solved(self.preset.target) for r in self.runs)

    def solved(self) -> str:
        return f"{self.solved_count()}/{len(self.runs)}"

    def to_target(self) -> tuple[str, str]:
        """Frames and training seconds to the target: median (range), k/n reached."""
        hits = self.hits.values()
        reached = f"{len(hits)}/{len(self.runs)} reached"
        frames = spread([h[0] for h in hits], ",.0f")
        return (reached if not hits else f"{frames}, {reached}"), spread(
            [h[1] for h in hits], ".1f"
        )


def seconds_to(run: Run, target: float) -> float | None:
    """Training seconds at ``run``'s first eval ≥ ``target`` (None: never)."""
    hit = run.hit(target)
    return None if hit is None else hit[1]


def ratio(ours: Side, theirs: Side, value: Callable[[Run], float | None]) -> tuple[str, float]:
    """Median over seeds of ``value(rlpipe run) / value(SB3 run)`` where both have one and
    both ran on the same machine (seconds from two machines are not compared): as the table
    shows it, and unrounded (nan: none)."""
    mine = {r.seed: r for r in ours.runs}
    pairs = [(mine[r.seed], r) for r in theirs.runs if r.seed in mine]
    ratios, elsewhere, days = [], 0, False
    for a, b in pairs:
        if (va := value(a)) is None or not (vb := value(b)):
            continue
        (day_a, where_a), (day_b, where_b) = split_day(a.machine), split_day(b.machine)
        if where_a != where_b:
            elsewhere += 1
            continue
        ratios.append(va / vb)
        days |= day_a != day_b
    if ratios:
        median = statistics.median(ratios)
        return format(median, ".2f") + (f" ({DAYS})" if days else ""), median
    return (f"{DASH} (on other machines)" if elsewhere else DASH), math.nan


def target_ratio(preset: Preset, ours: Side, theirs: Side) -> tuple[str, float]:
    """``ratio`` of the training seconds to the preset's target."""
    return ratio(ours, theirs, lambda r: seconds_to(r, preset.target))


def budget(cfg: Config, runs: list[Run]) -> str:
    """The preset's frame budget (or its own: ARS iterations, REINFORCE epochs) and what ran."""
    ends = sorted(r.evals[-1][0] for r in runs if r.evals)
    ran = "" if not ends else f"{ends[0]:,}" + ("" if ends[0] == ends[-1] else f"–{ends[-1]:,}")
    if cfg.total_frames is None:
        own = next(k for k in ("iterations", "epochs") if hasattr(cfg.algo, k))
        return f"{getattr(cfg.algo, own):,} {own}" + (f" (ran {ran} frames)" if ran else "")
    shown = f"{cfg.total_frames:,}"
    return shown if not ends or ends == [cfg.total_frames] * len(ends) else f"{shown} (ran {ran})"


def summary_row(
    preset: Preset, cfg: Config, ours: Side, theirs: Side, where: str, own: bool = True
) -> list[str]:
    """The preset's row of the main table (``own``: of the preset as it is, not overridden)."""
    frames, seconds = ours.to_target()
    cells = [f"`{preset.experiment}`", preset.env, budget(cfg, ours.runs), f"{preset.target:g}"]
    flag = " (short of 8/10: see its note)" if short(preset, ours, own) else ""
    solved = ours.solved() + flag
    seeds = seed_text([r.seed for r in ours.runs]) + _shared(ours.runs)
    if not ours.runs:  # left out (--read-only), as the line above the table says: no 0/0
        solved, frames, seconds = "no record: left out", DASH, DASH
    cells += [seeds, solved, iqm_cell(ours.finals)]
    cells += [frames, seconds]
    if not theirs.runs:
        side = preset.no_sb3 or ("not run (--sb3)" if ours.runs else DASH)  # none yet: neither
        cells += [side, DASH, DASH, DASH, DASH]
    else:
        cells += [theirs.solved() + _shared(theirs.runs), iqm_cell(theirs.finals)]
        cells.append(theirs.to_target()[1])
        to_target, median = target_ratio(preset, ours, theirs)
        if median > SPEED_TARGET:  # unrounded: 0.503 shows as 0.50, yet misses the aim
            to_target += f" (above {SPEED_TARGET:g}" + (": see its note)" if preset.slow else ")")
        cells.append(to_target)
        cells.append(ratio(ours, theirs, lambda r: r.train_seconds)[0])
    return [*cells, where]


def short(preset: Preset, ours: Side, own: bool = True) -> bool:
    """Whether the row says it is short of 8 of 10: its runs are, and its note says why (the
    preset's own runs, ``own``) or points to the preset's own row (runs overridden)."""
    below = ours.solved_count() < SOLVED_TARGET * len(ours.runs)
    return below and (bool(preset.short_of) or not own)


def slow(preset: Preset, ours: Side, theirs: Side) -> bool:
    """Whether the row's time to the target is above half SB3's (not so without pairs: nan)
    and its note says why."""
    return bool(preset.slow) and target_ratio(preset, ours, theirs)[1] > SPEED_TARGET


def _shared(runs: list[Run]) -> str:
    """The mark for figures of which any were evaluated on the shared starts, else nothing."""
    return f" {SHARED}" if any(r.shared_starts for r in runs) else ""


def _hit_text(run: Run, target: float) -> str:
    hit = run.hit(target)
    return "not reached" if hit is None else f"{hit[0]:,} / {hit[1]:.1f} s"


def _num(value: float | None) -> str:
    return DASH if value is None else f"{value:.1f}"


def _seed_cells(run: Run | None, target: float) -> list[str]:
    """A run's solved mark, frames / seconds to ``target``, last three evals and final eval."""
    if run is None:
        return [DASH] * 4
    if run.error:
        return [f"failed: {run.error}", DASH, DASH, DASH]
    mark = ("✓" if run.solved(target) else "✗") + _shared([run])
    return [mark, _hit_text(run, target), _num(run.last_three), _num(run.final)]


def detail_rows(preset: Preset, ours: Side, theirs: Side, label: dict[str, str]) -> list[list[str]]:
    """One row per seed: rlpipe's figures, the minutes its run took, SB3's figures, and the
    machine (SB3's too where its run ran on another)."""
    by_seed = {r.seed: r for r in theirs.runs}
    rows = []
    for r in ours.runs:
        wall = DASH if r.wall is None else f"{r.wall / 60:.1f}"
        sb3 = by_seed.get(r.seed)
        cells = [f"`{preset.experiment}`", f"{r.seed}", *_seed_cells(r, preset.target), wall]
        cells += _seed_cells(sb3, preset.target)
        where = label.get(r.machine, DASH)
        if sb3 is not None and label.get(sb3.machine, DASH) != where:
            where += f" (SB3: {label.get(sb3.machine, DASH)})"
        rows.append([*cells, where])
    return rows


def sides(presets: list[Preset], runs: list[Run], which: str) -> list[Side]:
    """Each preset's runs of one library (``rlpipe`` or ``SB3``)."""
    return [
        Side(p, [r for r in runs if r.preset == p.experiment and r.which == which]) for p in presets
    ]


def profile_series(presets: list[Preset], runs: list[Run]) -> dict[str, list[np.ndarray]]:
    """Each library's normalised finals, one array per preset with finished runs."""
    series = {
        w: [s.normalised for s in sides(presets, runs, w) if s.finals] for w in ("rlpipe", "SB3")
    }
    return {which: groups for which, groups in series.items() if groups}


def aggregate(of: list[Side]) -> str:
    """IQM of the normalised finals over every preset that has runs, with its 95%
    stratified-bootstrap interval, and the seeds solved in all."""
    groups = [s.normalised for s in of if s.finals]
    if not groups:
        return "no finished runs"
    low, high = pooled_iqm_band(groups)
    solved = sum(r.solved(s.preset.target) for s in of for r in s.runs)
    runs = sum(len(s.runs) for s in of)
    return (
        f"IQM {pooled_iqm(groups):.2f} [{low:.2f}, {high:.2f}] over {len(groups)} preset(s), "
        f"{sum(map(len, groups))} run(s); {solved}/{runs} seeds solved"
    )


def split_day(machine: str) -> tuple[str, str]:
    """A record's machine line as (the day it ran, the rest); ``common.machine`` starts with the
    day, which earlier records may lack (day "")."""
    day, _, rest = machine.partition(" · ")
    return (day, rest) if day[:4].isdigit() and rest else ("", machine)


def machines(runs: list[Run]) -> dict[str, str]:
    """A short label (M1, M2, ...) for each record's machine line: one per machine, whatever
    the days its runs ran on."""
    lines = dict.fromkeys(r.machine for r in runs)
    tags = {m: f"M{i}" for i, m in enumerate(dict.fromkeys(split_day(m)[1] for m in lines), 1)}
    return {m: tags[split_day(m)[1]] for m in lines}


def legend(runs: list[Run]) -> list[str]:
    """One line per machine label: the machine and the days its runs ran on."""
    days: dict[tuple[str, str], list[str]] = {}
    for m, tag in machines(runs).items():
        day, rest = split_day(m)
        days.setdefault((tag, rest), []).extend([day] if day else [])
    return [
        f"- {tag}: {rest}" + (f" (runs of {', '.join(sorted(d))})" if d else "")
        for (tag, rest), d in days.items()
    ]


def note(
    p: Preset, cfg: Config, ours: Side, theirs: Side, with_sb3: bool = True, own: bool = True
) -> str:
    """What the preset's row stands on: target and its source, tuning seeds, evals, SB3 (where
    ``with_sb3``: the section has SB3's side), where the row's runs stay short of 8 of 10 seeds
    or of half SB3's time to the target, why (where ``own``: of the preset as it is; a section
    of overridden runs points to its own row), and a link to its section of the tuning log."""
    text = (
        f"- `{p.experiment}`: target {p.target:g} ({p.target_from}); random policy {p.floor:g}; "
        f"tuned on seeds {seed_text(p.tuned_on)}; a greedy eval of {cfg.eval_episodes} episodes "
        f"every {cfg.eval_every:,} frames and at the end"
    )
    if with_sb3 and p.sb3 is None:
        text += f"; {p.no_sb3}"
    elif with_sb3:
        kwargs = ", ".join(f"{k}={v}" for k, v in {"n_envs": p.sb3_envs, **p.sb3}.items())
        normalize = ", VecNormalize(norm_obs=True, norm_reward=False)" if p.sb3_normalize else ""
        text += f"; SB3: {p.sb3_algo}('{p.sb3_policy}', {kwargs}{normalize})"
    why = p.short_of if own else OVERRIDDEN_SHORT
    text += f"; **short of 8 of 10 held-out seeds**: {why}" if short(p, ours, own) else ""
    text += (
        f"; **time to the target above {SPEED_TARGET:g}× SB3's**: {p.slow}"
        if slow(p, ours, theirs)
        else ""
    )
    log = f"[{TUNING_LOG}]({TUNING_LOG}#{p.experiment})"
    return text + f"; what was tried, and seeds run as checks: {log}"


# a short row's note in a section of overridden runs: the preset's own note speaks of its own runs
OVERRIDDEN_SHORT = (
    "these runs, with the section's override, are not the preset's own: its own held-out "
    "runs, and what was tried, are in the tuned presets' table"
)

HEADERS = [
    "preset",
    "env",
    "budget (frames)",
    "target",
    "seeds",
    "solved",
    "final: IQM [95% CI]",
    "frames to target",
    "train s to target",
    "SB3 solved",
    "SB3 final: IQM [95% CI]",
    "SB3 train s to target",
    "rlpipe/SB3 s to target",
    "rlpipe/SB3 s, whole run",
    "machine",
]
DETAIL_HEADERS = ["preset", "seed", "solved", "frames / train s to target", "last three"]
DETAIL_HEADERS += ["final", "wall min", "SB3 solved", "SB3 frames / s to target", "SB3 last three"]
DETAIL_HEADERS += ["SB3 final", "machine"]


def tables(
    presets: list[Preset], configs: dict[str, Config], runs: list[Run], own: bool = True
) -> list[str]:
    """The main table, the aggregate line, the notes per preset, the per-seed table and the
    machines' legend (``own``: of the presets as they are; not so for a section of runs with an
    --override)."""
    label = machines(runs)
    ours_all, theirs_all = sides(presets, runs, "rlpipe"), sides(presets, runs, "SB3")
    rows, details = [], []
    for p, ours, theirs in zip(presets, ours_all, theirs_all):
        ran = [label[r.machine] for r in ours.runs + theirs.runs]
        where = ", ".join(dict.fromkeys(ran)) or DASH
        rows.append(summary_row(p, configs[p.experiment], ours, theirs, where, own))
        details += detail_rows(p, ours, theirs, label)
    measured = [s for s in theirs_all if s.runs]
    summary = (
        "Normalised finals ((final − random) / (target − random); 1 = the target): rlpipe "
        + aggregate(ours_all)
        + ("; SB3 " + aggregate(measured) if measured else "")
        + "."
    )
    notes = [
        note(p, configs[p.experiment], *s, with_sb3=bool(measured), own=own)
        for p, *s in zip(presets, ours_all, theirs_all)
    ]
    if any(r.shared_starts for r in runs):
        summary += f"\n\n{SHARED_NOTE}."
    if any(DAYS in cell for row in rows for cell in row):
        summary += f"\n\n{DAYS_NOTE}."
    lines = legend(runs)
    return [table(HEADERS, rows), "", summary, "", *notes, "", table(DETAIL_HEADERS, details)] + [
        "",
        "Machines:",
        *lines,
    ]
