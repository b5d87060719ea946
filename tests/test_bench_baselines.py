"""benchmarks/baselines.py: BipedalWalker's baselines through ``python -m rlpipe.evaluate``, on
lock-step copies and on one env; the summaries kept and read back."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def test_baselines_script_rows_saved_and_read_back(tmp_path: Path) -> None:
    out, md = tmp_path / "results", tmp_path / "BENCH.md"
    command = [sys.executable, str(BENCHMARKS / "baselines.py"), "--episodes", "2"]
    command += ["--policies", "random", "--out", str(out), "--append", str(md)]
    proc = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in md.read_text().splitlines() if line.startswith("| `random`")]
    assert [r.split(" | ")[1] for r in rows] == [
        "2 copies in lock-step",
        "one env, one after another",
    ]
    lockstep = json.loads((out / "random-2-copies2-seed0.json").read_text())
    alone = json.loads((out / "random-2-copies1-seed0.json").read_text())
    assert (lockstep["copies"], alone["copies"]) == (2, 1)
    assert f"{alone['return_mean']:.2f} ± {alone['return_std']:.2f}" in rows[1]
    stamps = [p.stat().st_mtime_ns for p in sorted(out.iterdir())]
    again = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path)
    assert again.returncode == 0 and "2 of 2 evaluations read back" in again.stdout, again.stderr
    assert [p.stat().st_mtime_ns for p in sorted(out.iterdir())] == stamps
