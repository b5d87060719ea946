"""benchmarks/presets.py through its command line: a refused call, and a tiny run beside SB3 with
its records read back, resumed, stale and from other machines."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rlpipe.episodes import FINAL, episodes_seed

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "presets.py"


def test_a_refused_call_is_one_line_and_writes_nothing(tmp_path) -> None:
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("mine\n")
    command = [sys.executable, str(SCRIPT), "--presets", "dqn_cartpole", "--tune"]
    proc = subprocess.run(
        [*command, "--seeds", "3", "104", "--append", str(page)], capture_output=True, text=True
    )
    assert proc.returncode == 2 and page.read_text() == "mine\n"
    assert proc.stderr.strip().splitlines()[-1].startswith("presets.py: error: --append publishes")


def test_a_closed_console_still_publishes(tmp_path) -> None:
    """``presets.py ... --append BENCHMARKS.md | head``: the reader gone, the table still lands."""
    page = tmp_path / "BENCHMARKS.md"
    page.write_text("## mine\n")
    results = SCRIPT.parent / "results" / "presets"
    command = [sys.executable, str(SCRIPT), "--presets", "dqn_cartpole", "--read-only"]
    read, write = os.pipe()
    os.close(read)
    try:
        done = subprocess.run(
            [*command, "--out", str(results), "--append", str(page)],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
        )
    finally:
        os.close(write)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert (
        page.read_text().startswith("## mine\n\n## ") and "| `dqn_cartpole` |" in page.read_text()
    )


@pytest.mark.skipif(
    importlib.util.find_spec("stable_baselines3") is None, reason='needs the "bench" extra'
)
def test_a_tiny_run_beside_sb3_and_its_read_back(tmp_path) -> None:
    command = [sys.executable, str(SCRIPT), "--presets", "dqn_cartpole", "--seeds", "100"]
    command += ["--frames", "640", "--final-episodes", "2", "--sb3", "--jobs", "2"]
    command += ["--out", str(tmp_path / "runs"), "--figure", str(tmp_path / "profile.png")]
    first = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr
    row = next(line for line in first.stdout.splitlines() if line.startswith("| `dqn_cartpole`"))
    assert "| CartPole-v1 | 640 |" in row and "| 100 |" in row and row.count("|") == 16
    assert (tmp_path / "profile.png").stat().st_size > 10_000
    assert (tmp_path / "runs" / "dqn_cartpole" / "seed100" / "sb3.json").is_file()
    # the per-seed row gives the minutes the run took, kept in its record (run dirs are not)
    job = tmp_path / "runs" / "dqn_cartpole" / "seed100"
    wall = json.loads((job / "run" / "summary.json").read_text())["wall_time"]
    assert json.loads((job / "rlpipe.json").read_text())["wall"] == wall
    per_seed = next(
        line for line in first.stdout.splitlines() if line.startswith("| `dqn_cartpole` | 100 |")
    )
    assert per_seed.split(" | ")[6] == f"{wall / 60:.1f}"
    # the final eval meets the seed's own starts (not seed 0's, which tuning runs met too)
    final = json.loads(next((job / "run" / "evaluation").glob("trained-*.json")).read_text())
    assert final["seed"] == episodes_seed(100, FINAL) != 0
    # the same runs read back, and with --read-only a seed not in --out is left out, not run;
    # an SB3 run under way (a save, no record) says where it goes on from
    saves = tmp_path / "runs" / "dqn_cartpole" / "seed101" / "sb3-saves"
    saves.mkdir(parents=True)
    (saves / "progress.json").write_text(json.dumps({"dir": "320", "evals": [[320, 9.0, 0.5]]}))
    again = subprocess.run(
        [*command, "--read-only", "--seeds", "100", "101"], capture_output=True, text=True
    )
    assert again.returncode == 0, again.stderr
    assert "2 of 2 runs read back" in again.stdout and row in again.stdout
    assert "2 run(s) at once" in first.stdout and "run(s) at once" not in again.stdout
    assert "1-min load average at the runs' starts: M1 " in again.stdout
    left_out = (
        "left out (`--read-only`): dqn_cartpole (rlpipe 101, SB3 101; "
        "SB3 saved, to go on from: 101 at 320 frames)"
    )
    assert left_out in again.stdout
    # the records alone (what benchmarks/results/ keeps, without run dirs) give the same row
    shutil.rmtree(job / "run")
    records = subprocess.run([*command, "--read-only"], capture_output=True, text=True)
    assert records.returncode == 0, records.stderr
    assert "2 of 2 runs read back" in records.stdout and row in records.stdout
    # a record of the preset as it was before a change stands for nothing: left out, not read
    saved = json.loads((job / "rlpipe.json").read_text())
    assert saved["backend"] in ("envpool", "gymnasium")
    first_lr, saved["config"]["algo.lr"] = saved["config"]["algo.lr"], 1.0
    (job / "rlpipe.json").write_text(json.dumps(saved))
    stale = subprocess.run([*command, "--read-only"], capture_output=True, text=True)
    assert stale.returncode == 0, stale.stderr
    assert "left out (`--read-only`): dqn_cartpole (rlpipe 100)" in stale.stdout
    # runs from two machines: each machine's own load range (a 16-core machine's 10 is not 2's)
    sb3 = json.loads((job / "sb3.json").read_text())
    sb3["machine"], sb3["load"] = "a 16-core machine", [12.5, 12.0]
    (job / "sb3.json").write_text(json.dumps(sb3))
    saved["config"]["algo.lr"] = first_lr
    (job / "rlpipe.json").write_text(json.dumps(saved))
    two = subprocess.run([*command, "--read-only"], capture_output=True, text=True)
    assert two.returncode == 0, two.stderr
    assert re.search(r"runs' starts: M1 [\d.]+–[\d.]+; M2 12\.50–12\.50", two.stdout)
    assert "‡" not in two.stdout
    # a record from before evaluations met starts of their own is read back, and its side's
    # figures are marked: SB3's solved cells here, rlpipe's seeds below
    del sb3["eval_starts"]
    (job / "sb3.json").write_text(json.dumps(sb3))
    old = subprocess.run([*command, "--read-only"], capture_output=True, text=True)
    assert old.returncode == 0, old.stderr
    note = "‡ beside a seed's or preset's seeds (rlpipe) or its SB3 solved cell: evaluated before"
    assert "| 100 |" in old.stdout and "| 100 ‡ |" not in old.stdout and note in old.stdout
    assert re.search(r"\| 0/1 ‡ \||\| 1/1 ‡ \|", old.stdout)  # SB3 solved, in the main table
    assert re.search(r"\| [✓✗] ‡ \|", old.stdout) and "left out" not in old.stdout
    saved.pop("eval_starts")
    (job / "rlpipe.json").write_text(json.dumps(saved))
    older = subprocess.run([*command, "--read-only"], capture_output=True, text=True)
    assert older.returncode == 0, older.stderr
    assert "| 100 ‡ |" in older.stdout and len(re.findall(r"\| [✓✗] ‡ \|", older.stdout)) == 2


def test_a_tuning_run_with_your_network_is_evaluated(tmp_path) -> None:
    """``--override algo.network._target_=...``: the final eval imports the network again (the
    run dir is the benchmark's own), and the record names it."""
    examples = SCRIPT.parents[1] / "examples"
    command = [sys.executable, str(SCRIPT), "--presets", "dqn_cartpole", "--tune", "--seeds", "3"]
    command += ["--frames", "640", "--final-episodes", "2", "--out", str(tmp_path)]
    command += ["--override", "algo.network._target_=dueling_dqn.DuelingQNet"]
    env = {**os.environ, "PYTHONPATH": str(examples)}
    done = subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0 and "FAILED" not in done.stdout, done.stdout + done.stderr
    saved = json.loads((tmp_path / "dqn_cartpole" / "seed3" / "rlpipe.json").read_text())
    assert saved["config"]["algo.network._target_"] == "dueling_dqn.DuelingQNet"
    assert saved["final"] is not None
