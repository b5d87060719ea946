"""``python -m rlpipe.plot DIR [DIR ...] [agg=iqm] [svg=true] [metric=...] [out=FILE.png]``.

Draws learning curves of any set of run dirs or multirun sweep dirs: runs that differ only by
seed form a group, drawn as the mean (``agg=mean``) or interquartile mean (``agg=iqm``) over
its seeds with a 95% bootstrap confidence band (a group of one seed: no band); groups are
labelled by the overrides that set them apart. A run fine-tuned from another (``init_from``)
is drawn after the run it began from, its frames counted on from that checkpoint's, a dotted
line where it began (``parent=false``: the run alone, from 0). Writes ``curves.png`` beside
the data (in DIR, or in the directory holding every DIR) unless ``out=`` says where, and prints
its path (and the SVG's with ``svg=true``). An argument naming an existing path is a directory
even if it holds ``=`` (``outputs/lr=0.1``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from rlpipe.cli import run_entry_point
from rlpipe.errors import RlpipeError, check
from rlpipe.figures import plot_groups
from rlpipe.files import check_writable
from rlpipe.metrics import EVAL_METRIC
from rlpipe.runs import find_runs, group_runs
from rlpipe.stats import AGGREGATES

OPTIONS = {"agg": "mean", "svg": "false", "metric": EVAL_METRIC, "out": None, "parent": "true"}
BOOLEANS = {"true": True, "false": False}


def parse_args(argv: Sequence[str]) -> tuple[list[str], dict[str, str | None]]:
    """Split ``argv`` into directories and ``key=value`` options (unknown keys refused).

    An argument that names an existing path is a directory, ``=`` or not.
    """
    dirs, options = [], dict(OPTIONS)
    for arg in argv:
        key, eq, value = arg.partition("=")
        if not eq or Path(arg).exists():
            dirs.append(arg)
            continue
        if key not in OPTIONS and ("/" in key or os.sep in key):
            raise RlpipeError(f"{arg} is not a directory (nor an option: {', '.join(OPTIONS)})")
        check(key in OPTIONS, f"unknown option {key!r}; choose from: {', '.join(OPTIONS)}")
        options[key] = value
    check(bool(dirs), "pass at least one run dir or multirun sweep dir")
    check(
        options["agg"] in AGGREGATES,
        f"agg must be one of {', '.join(AGGREGATES)}; got {options['agg']!r}",
    )
    for key in ("svg", "parent"):
        check(options[key] in BOOLEANS, f"{key} must be true or false; got {options[key]!r}")
    return dirs, options


def default_out(dirs: Sequence[str]) -> Path:
    """Beside the data drawn: ``<DIR>/curves.png`` for one directory, else in the directory
    that holds them all (the first one's parent when they share only the filesystem root)."""
    common = Path(os.path.commonpath([os.path.abspath(d) for d in dirs]))
    if len(dirs) > 1 and common == Path(common.anchor):
        common = Path(dirs[0]).absolute().parent
    return (Path(dirs[0]) if len(dirs) == 1 else common) / "curves.png"


def _plot(args: list[str]) -> None:
    dirs, options = parse_args(args)
    runs = find_runs(dirs, options["metric"])
    out = Path(options["out"] or default_out(dirs))
    check_writable(out, "pick a writable place with out=<file.png>")
    if BOOLEANS[options["svg"]]:
        check_writable(out.with_suffix(".svg"), "pick a writable place with out=<file.png>")
    groups = group_runs(runs)
    written = plot_groups(
        groups,
        out,
        metric=options["metric"],
        aggregate=options["agg"],
        svg=BOOLEANS[options["svg"]],
        parents=BOOLEANS[options["parent"]],
    )
    print(f"rlpipe: {len(groups)} group(s) from {len(runs)} run(s):")
    for group in groups:
        print(f"  {group.label}: {len(group.runs)} seed(s)")
    for path in written:
        print(path)


def main(argv: Sequence[str] | None = None) -> None:
    """Command-line entry point; user errors: one line, exit 2."""
    run_entry_point(__doc__, argv, _plot)


if __name__ == "__main__":
    main()
