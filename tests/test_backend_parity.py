"""benchmarks/backend_parity.py on a tiny trained run: both backends evaluated, one table row,
a second call reads the evaluations back instead of running them again, and a call with another
number of episodes runs its own."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rlpipe.envs.backends import envpool_version

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "backend_parity.py"


@pytest.mark.skipif(envpool_version() is None, reason="needs EnvPool (Linux x86_64, Python>=3.11)")
def test_backend_parity_evaluates_a_run_on_both_backends(run_copy, tmp_path):
    command = [sys.executable, str(SCRIPT), str(run_copy), "--episodes", "3"]
    out = tmp_path / "BENCH.md"
    proc = subprocess.run([*command, "--append", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rows = [line for line in out.read_text().splitlines() if line.startswith("| dqn on")]
    assert len(rows) == 1 and rows[0].count("|") == 7, out.read_text()
    saved = {p.name: p.stat().st_mtime_ns for p in (run_copy / "evaluation").glob("parity-*")}
    assert sorted(saved) == ["parity-envpool-3-seed7.json", "parity-gymnasium-3-seed7.json"]
    again = subprocess.run(command, capture_output=True, text=True)
    assert again.returncode == 0 and rows[0] in again.stdout, again.stderr
    assert {
        p.name: p.stat().st_mtime_ns for p in (run_copy / "evaluation").glob("parity-*")
    } == saved
    more = subprocess.run([*command[:-1], "4"], capture_output=True, text=True)
    assert more.returncode == 0, more.stderr
    four = json.loads((run_copy / "evaluation" / "parity-envpool-4-seed7.json").read_text())
    assert len(four["returns"]) == 4
