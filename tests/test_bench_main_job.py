"""benchmarks/main_job.py: the main job as typed, alone and beside a busy process, on a tiny
budget through the script itself; its rows' ratios on made-up results."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import benchmarks_importable

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "main_job.py"


@pytest.fixture(scope="module")
def main_job():
    with benchmarks_importable():
        yield importlib.import_module("main_job")


def test_rows_give_the_busy_run_over_the_lone_one(main_job) -> None:
    alone, beside = main_job.CONDITIONS
    result = {"wall_time": 500.0, "frames": 16_000_000, "final": 301.0}
    results = {
        (100, beside): {**result, "process_s": 900.0, "final": 299.0},
        (100, alone): {**result, "process_s": 600.0},
    }
    rows = main_job.rows_of(results)
    assert [r[1] for r in rows] == [alone, beside]  # the lone run first
    assert rows[0][2:] == ["10.0", "8.3", "16,000,000", "301.0 ✓", "1.00×"]
    assert rows[1][2] == "15.0" and rows[1][5:] == ["299.0 ✗", "1.50×"]


def test_the_script_runs_the_job_both_ways_and_keeps_other_sections(tmp_path) -> None:
    bench = tmp_path / "BENCHMARKS.md"
    bench.write_text("# B\n\n## Other (benchmarks/other.py)\n\nkept\n")
    command = [sys.executable, str(SCRIPT), "--seeds", "0", "--episodes", "2"]
    command += ["--override", "total_frames=1000", "eval_every=0", "--append", str(bench)]
    proc = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    text = bench.read_text()
    assert "## Other (benchmarks/other.py)\n\nkept" in text
    assert "its first line: `rlpipe: ars on env=bipedal with its tuned settings" in text, text
    rows = [line for line in text.splitlines() if line.startswith("| 0 |")]
    assert [r.split(" | ")[1] for r in rows] == ["alone", "beside a busy process"], rows
    finals = {r.split(" | ")[5] for r in rows}
    assert len(finals) == 1, rows  # the same run either way: a busy core changes only its time
