"""``python -m rlpipe.plot DIR [DIR ...] [agg=iqm] [svg=true] [metric=...] [out=FILE.png]``.

Draws learning curves of any set of run dirs or multirun sweep dirs: runs that differ only by
seed form a group, drawn as the mean (``agg=mean``) or interquartile mean (``agg=iqm``) over
its seeds with a 95% bootstrap confidence band; groups are labelled by the overrides that set
them apart. Prints the path of the PNG (and SVG with ``svg=true``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from rlpipe.cli import run_entry_point
from rlpipe.errors import check
from rlpipe.figures import AGGREGATES, plot_groups
from rlpipe.metrics import EVAL_METRIC, find_runs, group_runs

OPTIONS = {"agg": "mean", "svg": "false", "metric": EVAL_METRIC, "out": None}
BOOLEANS = {"true": True, "false": False}


def parse_args(argv: Sequence[str]) -> tuple[list[str], dict[str, str | None]]:
    """Split ``argv`` into directories and ``key=value`` options (unknown keys refused)."""
    dirs, options = [], dict(OPTIONS)
    for arg in argv:
        key, eq, value = arg.partition("=")
        if not eq:
            dirs.append(arg)
            continue
        check(key in OPTIONS, f"unknown option {key!r}; choose from: {', '.join(OPTIONS)}")
        options[key] = value
    check(bool(dirs), "pass at least one run dir or multirun sweep dir")
    check(
        options["agg"] in AGGREGATES,
        f"agg must be one of {', '.join(AGGREGATES)}; got {options['agg']!r}",
    )
    check(options["svg"] in BOOLEANS, f"svg must be true or false; got {options['svg']!r}")
    return dirs, options


def default_out(dirs: Sequence[str]) -> Path:
    """``<DIR>/curves.png`` for one directory, else ``curves.png`` here."""
    return Path(dirs[0]) / "curves.png" if len(dirs) == 1 else Path("curves.png")


def _plot(args: list[str]) -> None:
    dirs, options = parse_args(args)
    groups = group_runs(find_runs(dirs, options["metric"]))
    written = plot_groups(
        groups,
        options["out"] or default_out(dirs),
        metric=options["metric"],
        aggregate=options["agg"],
        svg=BOOLEANS[options["svg"]],
    )
    runs = sum(len(group.runs) for group in groups)
    print(f"rlpipe: {len(groups)} group(s) from {runs} run(s):")
    for group in groups:
        print(f"  {group.label}: {len(group.runs)} seed(s)")
    for path in written:
        print(path)


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry point; user errors: one line, exit 2."""
    run_entry_point(__doc__, argv, _plot)


if __name__ == "__main__":
    main()
