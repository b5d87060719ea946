"""How far a reader travels through rlpipe/ to follow a command: files, moves and returns.

Runs ``python -m rlpipe <overrides>`` (a tiny budget) under a profiler and rebuilds the path a
newcomer reading top-down would take: the first call of each rlpipe function is followed into its
file, later calls of a function already read are not (loops are read once), and every return to
the caller's file is a move back; what modules run while they are imported is not followed.
Printed, for two readings:

- **main job**: from ``rlpipe/__main__.py`` to the summary line: distinct files, moves between
  files, and moves into a file already read ("returns");
- **cfg from train**: only the functions that receive a config object (``Config``, ``EnvConfig``,
  an algorithm config, ``LoggerConfig``) as an argument, from ``pipeline.train`` down: modules
  entered, moves, and moves back up to a calling module ("climbs").

    python benchmarks/reading_path.py [--append BENCHMARKS.md] [overrides ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import os
import runpy
import sys
import tempfile
from pathlib import Path

from common import machine, publish_section, script

ROOT = Path(importlib.util.find_spec("rlpipe").origin).parent  # the rlpipe being read
DEFAULT = [
    "algo=ars",
    "env=bipedal",
    "algo.iterations=2",
    "algo.num_directions=2",
    "algo.num_best=2",
    "algo.workers=1",
    "algo.episode_length=20",
    "eval_episodes=1",
    "progress=false",
]


class Reader:
    """Records the path through rlpipe's files: first calls followed, repeats skipped."""

    def __init__(self) -> None:
        self.seen: set[object] = set()
        self.path: list[tuple[str, str]] = []  # (file, "in" | "back") of every move, in order
        self.cfg_path: list[tuple[str, str]] = []  # (module, "in" | "back") of cfg moves
        self.stack: list[tuple[str, bool, bool]] = []  # (file, followed, takes cfg)
        self.skip_depth = 0  # inside a function already read: nothing is recorded
        self.in_train = False

    def __call__(self, frame, event, arg):  # noqa: ANN001  (sys.setprofile's signature)
        if event not in ("call", "return"):
            return
        code = frame.f_code
        file = code.co_filename
        ours = file.startswith(str(ROOT))
        if event == "call":
            if self.skip_depth:
                self.skip_depth += 1
                return
            if not ours:
                self.stack.append(("", False, False))
                return
            if code.co_name == "<module>":  # the command's own module is read; an import's is not
                if frame.f_globals.get("__name__") == "__main__":
                    self.stack.append(("", False, False))
                else:
                    self.skip_depth = 1
                return
            if code in self.seen:
                self.skip_depth = 1
                return
            self.seen.add(code)
            name = str(Path(file).relative_to(ROOT.parent))
            if code.co_name == "train" and name.endswith("pipeline.py"):
                self.in_train = True
            takes_cfg = self.in_train and _has_config(frame)
            self.stack.append((name, True, takes_cfg))
            self._move(name, "in")
            if takes_cfg:
                self._cfg_move(name, "in")
            return
        if self.skip_depth:
            self.skip_depth -= 1
            return
        if not self.stack:
            return
        name, followed, takes_cfg = self.stack.pop()
        caller = next((f for f, followed_, _ in reversed(self.stack) if followed_), None)
        if followed and caller is not None:
            self._move(caller, "back")
        if takes_cfg:
            cfg_caller = next((f for f, _, c in reversed(self.stack) if c), None)
            if cfg_caller is not None:
                self._cfg_move(cfg_caller, "back")

    def _move(self, name: str, how: str) -> None:
        if not self.path or self.path[-1][0] != name:
            self.path.append((name, how))

    def _cfg_move(self, name: str, how: str) -> None:
        if not self.cfg_path or self.cfg_path[-1][0] != name:
            self.cfg_path.append((name, how))


def _has_config(frame) -> bool:  # noqa: ANN001
    from rlpipe.config import AlgoConfig, Config, EnvConfig, LoggerConfig

    kinds = (Config, EnvConfig, LoggerConfig, AlgoConfig)
    code = frame.f_code
    names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
    values = [frame.f_locals.get(n) for n in names]
    return any(isinstance(v, kinds) and dataclasses.is_dataclass(v) for v in values)


def counts(path: list[tuple[str, str]]) -> dict[str, int]:
    """Distinct files, moves between files, moves into a file already read (returns), calls
    into a file already read (a reader goes back to it for something new), and returns to a
    calling file (climbs)."""
    names = [name for name, _ in path]
    again = [i for i, name in enumerate(names) if name in names[:i]]
    return {
        "files": len(set(names)),
        "moves": len(path) - 1,
        "returns": len(again),
        "calls back": sum(1 for i in again if path[i][1] == "in"),
        "climbs": sum(1 for _, how in path[1:] if how == "back"),
    }


def trace(overrides: list[str]) -> Reader:
    reader = Reader()
    with tempfile.TemporaryDirectory() as tmp:
        sys.argv = ["rlpipe", *overrides, f"hydra.run.dir={tmp}/run"]
        sys.setprofile(reader)
        try:
            runpy.run_module("rlpipe", run_name="__main__", alter_sys=True)
        except SystemExit:
            pass
        finally:
            sys.setprofile(None)
    return reader


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--append", help="replace this benchmark's section in a Markdown file")
    parser.add_argument("overrides", nargs="*", default=DEFAULT)
    args = parser.parse_args()
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    reader = trace(args.overrides)
    job, cfg = counts(reader.path), counts(reader.cfg_path)
    lines = [
        "## Reading path (benchmarks/reading_path.py)",
        "",
        f"- machine: {machine(['hydra-core', 'torch', 'torchrl'])}",
        f"- command: `python -m rlpipe {' '.join(args.overrides)}`",
        "",
        "| reading | " + " | ".join(job) + " |",
        "|---|" + "---|" * len(job),
        "| main job, `__main__` to the summary line | " + " | ".join(map(str, job.values())) + " |",
        "| `cfg` from `pipeline.train` | " + " | ".join(map(str, cfg.values())) + " |",
        "",
        "Files in the order first read: "
        + ", ".join(dict.fromkeys(Path(name).name for name, _ in reader.path)),
    ]
    publish_section("\n".join(lines), args.append)


if __name__ == "__main__":
    script(main)
