"""benchmarks/early_stop.py: where a run stops once solved, and the stopped arm derived from a
tiny finished run (its evals cut at the stop, the checkpoint there evaluated), read back."""

from __future__ import annotations

import importlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import benchmarks_importable

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def early_stop():
    with benchmarks_importable():
        yield importlib.import_module("early_stop")


def test_stop_index_is_the_first_window_at_the_target(early_stop):
    assert early_stop.stop_index([100, 300, 310, 280, 320, 330], 300, 3) == 4
    assert early_stop.stop_index([100, 300, 310, 280, 320, 330], 300, 1) == 1
    assert early_stop.stop_index([299.9, 299.9, 299.9], 300, 3) is None
    assert early_stop.stop_index([500, 500], 500, 3) is None


def test_lowest_after_reads_the_full_run_past_the_stop(early_stop):
    saved = {"evals": [[100, 310.0, 1.0], [200, 250.0, 1.0], [300, 320.0, 1.0]]}
    assert early_stop.lowest_after(saved, 100) == 250.0
    assert early_stop.lowest_after(saved, 200) == 320.0
    assert early_stop.lowest_after(saved, 300) is None


def test_early_stop_derives_a_stopped_arm(run_copy: Path, tmp_path: Path) -> None:
    """Seed 1's evals (made up: 500 at 100 frames, 20 at 200) meet dqn_cartpole's target at 100
    frames; seed 2's never do."""
    src, dst = tmp_path / "src" / "dqn_cartpole", tmp_path / "dst"
    for seed, means in ((1, [500.0, 20.0]), (2, [20.0, 30.0])):
        shutil.copytree(run_copy, src / f"seed{seed}" / "run")
        record = {"evals": [[100, means[0], 1.0], [200, means[1], 2.0]], "final": 9.0, "wall": 5}
        (src / f"seed{seed}" / "rlpipe.json").write_text(json.dumps(record))
    command = [sys.executable, str(BENCHMARKS / "early_stop.py"), "--preset", "dqn_cartpole"]
    command += ["--window", "1", str(src.parent), str(dst)]
    proc = subprocess.run(command, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "seed 1: stopped at 100 of 200 frames" in proc.stdout
    assert "lowest eval after it 20.0" in proc.stdout
    assert "seed 2: never met the stop" in proc.stdout
    fell = "early_stop: dqn_cartpole: 1 of 1 stopped runs fell below 452.1 in the full run's"
    assert proc.stdout.splitlines()[-1].startswith(fell) and "(seeds 1)" in proc.stdout
    stopped = json.loads((dst / "dqn_cartpole" / "seed1" / "rlpipe.json").read_text())
    final = json.loads((dst / "dqn_cartpole" / "seed1" / "final-100.json").read_text())
    assert stopped["evals"] == [[100, 500.0, 1.0]] and stopped["stopped_at"] == 100
    assert final["checkpoint"] == "ckpt_000000000100" and final["episodes"] == 100
    assert stopped["final"] == final["return_mean"] and stopped["final_at_end"] == 9.0
    assert 0 < stopped["wall"] < 60
    kept = json.loads((dst / "dqn_cartpole" / "seed2" / "rlpipe.json").read_text())
    assert kept == json.loads((src / "seed2" / "rlpipe.json").read_text())
    stamp = (dst / "dqn_cartpole" / "seed1" / "rlpipe.json").stat().st_mtime_ns
    again = subprocess.run(command, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert again.stdout.splitlines() == proc.stdout.splitlines()[-1:]  # the count, nothing redone
    assert (dst / "dqn_cartpole" / "seed1" / "rlpipe.json").stat().st_mtime_ns == stamp


def test_early_stop_bad_input(tmp_path: Path) -> None:
    command = [sys.executable, str(BENCHMARKS / "early_stop.py"), "--preset", "dqn_cartpole"]
    proc = subprocess.run(
        [*command, str(tmp_path), str(tmp_path / "d")], capture_output=True, text=True
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        f"early_stop: {tmp_path}: no dqn_cartpole runs in it"
    ]
