"""Learning-curve figures: ``curve.png`` of one run (drawn when a run ends) and seed-grouped
comparisons of many (``python -m rlpipe.plot``). Reading the metric CSVs and grouping runs:
:mod:`rlpipe.metrics`."""

from __future__ import annotations

import io
import os
import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from rlpipe.errors import check
from rlpipe.files import write_atomic
from rlpipe.metrics import EVAL_METRIC
from rlpipe.rundir import RunDir
from rlpipe.runs import Group, history
from rlpipe.stats import AGGREGATES, bootstrap_band

WINDOW = 100  # episodes in the training-return moving average (as the DQN notebook plotted)


def moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the trailing ``window`` values at each point (fewer at the start)."""
    sums = np.cumsum(np.concatenate([[0.0], values]))
    ends = np.arange(1, len(values) + 1)
    starts = np.maximum(ends - window, 0)
    return (sums[ends] - sums[starts]) / (ends - starts)


def _title(run_dir: Path) -> str:
    """``<algo> on <env id>: <run dir>``, the dir relative to the working directory when under it
    (a figure should not show where a home directory is)."""
    env_id, algo = RunDir(run_dir).identity()
    where = (
        Path(os.path.relpath(run_dir.resolve()))
        if run_dir.resolve().is_relative_to(Path.cwd())
        else Path(run_dir.name)
    )
    return f"{algo} on {env_id}: {where}"


def plot_run(run_dir: str | Path, path: str | Path | None = None) -> Path:
    """Draw ``run_dir``'s greedy eval return and training episode return into ``curve.png``."""
    path = Path(path) if path else Path(run_dir) / RunDir.CURVE
    save_figure(run_figure(run_dir), path)
    return path


def run_figure(run_dir: str | Path) -> Figure:
    """The figure :func:`plot_run` saves: the greedy eval mean with its ± std band (clipped to
    each evaluation's lowest and highest return), the training returns and their average."""
    run_dir = Path(run_dir)
    run = RunDir(run_dir)
    frames, mean = run.metric(EVAL_METRIC)
    check(
        len(frames) > 0,
        f"no metrics in {run_dir}: {run.metric_path(EVAL_METRIC)} is missing or empty "
        "(runs with logger=none write none)",
    )
    fig = Figure(figsize=(12, 4.5), dpi=100, layout="constrained")
    left, right = fig.subplots(1, 2)
    _, std = run.metric("eval/return_std")
    left.plot(frames, mean, marker="o", color="C0", label="greedy eval mean")
    if len(std) == len(mean):
        low, high = _within_returns(run, mean - std, mean + std)
        left.fill_between(frames, low, high, color="C0", alpha=0.2, label="± std, within min/max")
    _label(left, "greedy evaluation return")
    ep_frames, returns = run.metric("train/episode_return")
    if len(returns):
        right.plot(ep_frames, returns, color="C1", alpha=0.35, lw=0.8, label="episode return")
        average = moving_average(returns, WINDOW)
        right.plot(ep_frames, average, color="C3", lw=2, label=f"{WINDOW}-episode moving average")
    _label(right, "training episode return")
    fig.suptitle(_title(run_dir), fontsize=10)
    return fig


def _within_returns(
    run: RunDir, low: np.ndarray, high: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The band ``low``-``high`` clipped to each evaluation's lowest and highest return (no
    band shows returns the env cannot give, e.g. below Acrobot's -500)."""
    _, lowest = run.metric("eval/return_min")
    _, highest = run.metric("eval/return_max")
    if len(lowest) == len(low) == len(highest):
        return np.maximum(low, lowest), np.minimum(high, highest)
    return low, high


def save_figure(fig: Figure, path: Path) -> None:
    """Write ``fig`` to ``path`` (its format by the suffix) atomically: a link at ``path`` is
    replaced, never written through."""
    data = io.BytesIO()
    fig.savefig(data, format=path.suffix.lstrip(".") or "png")
    write_atomic(path, data.getvalue())


def _label(ax: Axes, title: str) -> None:
    ax.set_title(title)
    ax.set_xlabel("frames")
    ax.set_ylabel("return")
    ax.grid(alpha=0.3)
    if ax.has_data():
        ax.legend(loc="best", fontsize=8)


# ---- many runs: seeds grouped, mean/IQM line with a bootstrap band -------------------------


def aligned(
    runs: Sequence[Path], metric: str, *, parents: bool = False
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """``(frames, values[run, frame], starts)`` on the frames of the shortest run
    (interpolated); ``parents``: each run after the runs it was fine-tuned from
    (:func:`~rlpipe.runs.history`), ``starts`` the frames where fine-tuning began."""
    curves = [
        history(run, metric) if parents else (*RunDir(run).metric(metric), []) for run in runs
    ]
    grid = min((frames for frames, _, _ in curves), key=lambda f: f[-1])
    values = np.stack([np.interp(grid, frames, values) for frames, values, _ in curves])
    return grid, values, sorted({start for *_, starts in curves for start in starts})


# what a metric is, for titles (any other metric is named by its key)
METRIC_NAMES = {EVAL_METRIC: "greedy evaluation return", "train/episode_return": "training return"}
MARKERS_UP_TO = 40  # points per line: markers on each point up to this many
LEGEND_WIDTH, LEGEND_LINES = 60, 3  # a legend entry's characters per line, lines at most


def plot_groups(
    groups: Sequence[Group],
    path: str | Path,
    *,
    metric: str = EVAL_METRIC,
    aggregate: str = "mean",
    svg: bool = False,
    title: str | None = None,
    parents: bool = True,
) -> list[Path]:
    """Draw one line per group (``aggregate`` over its seeds) with a 95% bootstrap band.

    One panel per env when the groups span several, each titled by its env and algorithm(s).
    ``parents``: a fine-tuned run's line starts with the runs it began from (``init_from``), a
    dotted line where fine-tuning began."""
    fig = groups_figure(groups, metric=metric, aggregate=aggregate, title=title, parents=parents)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path)
    written = [path]
    if svg:
        written.append(path.with_suffix(".svg"))
        save_figure(fig, written[-1])
    return written


def groups_figure(
    groups: Sequence[Group],
    *,
    metric: str,
    aggregate: str,
    title: str | None = None,
    parents: bool = True,
) -> Figure:
    """The figure :func:`plot_groups` saves."""
    check(aggregate in AGGREGATES, f"agg must be one of {', '.join(AGGREGATES)}; got {aggregate!r}")
    panels: dict[str, list[tuple[int, Group, str]]] = {}
    for i, group in enumerate(groups):
        env_id, algo = RunDir(group.runs[0]).identity()
        panels.setdefault(env_id, []).append((i, group, algo))
    columns = min(len(panels), 3)
    rows = -(-len(panels) // columns)
    fig = Figure(figsize=(6.5 * columns, 4.5 * rows + 0.5), dpi=100, layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, columns, squeeze=False).ravel())
    for ax, (env_id, members) in zip(axes, panels.items()):
        for i, group, _ in members:
            frames, values, starts = aligned(group.runs, metric, parents=parents)
            line = AGGREGATES[aggregate](values)
            n = len(group.runs)
            label = _legend(group.label, several_envs=len(panels) > 1)
            label = f"{label} ({aggregate} of {n})" if label else f"{aggregate} of {n} seeds"
            ax.plot(
                frames,
                line,
                color=f"C{i}",
                lw=2,
                label=label,
                marker="o" if len(frames) <= MARKERS_UP_TO else None,
                markersize=4,
            )
            if n > 1:
                low, high = bootstrap_band(values, aggregate)
                ax.fill_between(frames, low, high, color=f"C{i}", alpha=0.2)
            for start in starts:
                ax.axvline(
                    start,
                    color=f"C{i}",
                    ls=":",
                    lw=1.5,
                    label=f"fine-tuning began ({start:,} frames)",
                )
        algos = sorted({algo for _, _, algo in members})
        ax.set_title(f"{env_id} · {', '.join(algos)}")
        ax.set_xlabel("frames")
        ax.set_ylabel("return" if metric in METRIC_NAMES else metric)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
        _honest_range(ax)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    what = METRIC_NAMES.get(metric, metric)
    fig.suptitle(title or f"{what}: {_band_title(groups, aggregate)}", fontsize=11)
    return fig


def _band_title(groups: Sequence[Group], aggregate: str) -> str:
    """What the lines and bands are: a band only where a line has two seeds or more."""
    seeds = {len(group.runs) for group in groups}
    if seeds == {1}:
        return "one seed per line (no confidence band)"
    if 1 in seeds:
        return f"{aggregate} over seeds, 95% bootstrap CI (lines of one seed: no band)"
    return f"{aggregate} over seeds, 95% bootstrap CI"


def _legend(label: str, *, several_envs: bool) -> str:
    """A group's legend entry: its label without the env (the panel names it), wrapped to
    :data:`LEGEND_WIDTH` characters and at most :data:`LEGEND_LINES` lines."""
    if several_envs:
        kept = [o for o in label.split() if not o.lstrip("+~").startswith(("env=", "env.id="))]
        label = " ".join(kept)
    short = textwrap.shorten(label, LEGEND_WIDTH * LEGEND_LINES, placeholder=" …")
    return "\n".join(textwrap.wrap(short, LEGEND_WIDTH))


def _honest_range(ax: Axes) -> None:
    """Widen a y-range that would blow noise up: at least 10% of the values' magnitude."""
    low, high = ax.get_ylim()
    span, size = high - low, max(abs(low), abs(high), 1.0)
    if span < 0.1 * size:
        middle = (low + high) / 2
        ax.set_ylim(middle - 0.05 * size, middle + 0.05 * size)
