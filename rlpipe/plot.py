"""``python -m rlpipe.plot DIR [DIR ...] [agg=iqm] [svg=true] [metric=...] [out=FILE.png]``.

Draws learning curves of any set of run dirs or multirun sweep dirs: runs that differ only by
seed form a group, drawn as the mean (``agg=mean``) or interquartile mean (``agg=iqm``) over
its seeds with a 95% bootstrap confidence band; groups are labelled by the overrides that set
them apart. Prints the path of the PNG (and SVG with ``svg=true``).
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from pathlib import Path

from rlpipe.cli import fail
from rlpipe.curves import AGGREGATES, EVAL_METRIC, find_runs, group_runs, plot_groups
from rlpipe.errors import RlpipeError, check

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


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry point; user errors: one line, exit 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    if {"-h", "--help"} & set(args):
        print(__doc__.strip())
        return
    try:
        dirs, options = parse_args(args)
        groups = group_runs(find_runs(dirs, options["metric"]))
        written = plot_groups(
            groups,
            options["out"] or default_out(dirs),
            metric=options["metric"],
            aggregate=options["agg"],
            svg=BOOLEANS[options["svg"]],
        )
    except RlpipeError as err:
        fail(err)
    runs = sum(len(group.runs) for group in groups)
    print(f"rlpipe: {len(groups)} group(s) from {runs} run(s):")
    for group in groups:
        print(f"  {group.label}: {len(group.runs)} seed(s)")
    for path in written:
        print(path)


if __name__ == "__main__":
    main()
