"""benchmarks/screen.py: arms of a tuning screen compared on records made up by hand."""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import benchmarks_importable

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "screen.py"


def write(folder: Path, seed: int, means: list[float], final: float, nested: bool = True) -> None:
    """A record as benchmarks/presets.py --out writes it (``nested``) or presets-more keeps it."""
    where = folder / "dqn_cartpole" if nested else folder
    evals = [[5_000 * (i + 1), m, 2.0 * (i + 1)] for i, m in enumerate(means)]
    record = {"evals": evals, "final": final, "wall": 30.0 + seed, "machine": "box"}
    path = where / f"seed{seed}" / "rlpipe.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record))


def screen(*args: str) -> subprocess.CompletedProcess:
    command = [sys.executable, str(SCRIPT), "--preset", "dqn_cartpole", *args]
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def test_the_screen_counts_solves_wins_and_falls(tmp_path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    solved, fell, missed = [500, 500, 500], [500, 100, 500, 500, 500], [200, 300, 400, 450]
    for seed in range(4):  # the reference solves seeds 0 and 1, the variant 0, 1, 2 and 3
        write(a, seed, solved if seed < 2 else missed, 500.0 if seed < 2 else 420.0)
        write(b, seed, fell if seed == 1 else solved, 500.0, nested=False)
    write(b, 9, solved, 500.0, nested=False)  # a seed only one arm ran: left out
    done = screen(f"ref={a}", f"var={b}")
    assert done.returncode == 0, done.stderr
    rows = {line.split(" | ")[0].strip("| "): line for line in done.stdout.splitlines()}
    assert "on seeds 0–3, 4 finished by every arm; reference arm: ref" in done.stdout
    # solved, alone (this / reference) with its sign test, fell below 452.1, reached, frames
    assert rows["ref"].startswith("| ref | 2 of 4 | – | 0 | 2 of 4 | 5,000 |")
    assert rows["var"].startswith("| var | 4 of 4 | 2 / 0, p = 0.250 | 1 | 4 of 4 | 5,000 |")
    assert "- ref misses (last three / final): 2: 383.3 / 420.0; 3: 383.3 / 420.0" in done.stdout
    assert "- var misses (last three / final): none" in done.stdout


@pytest.fixture(scope="module")
def bench():
    with benchmarks_importable():
        yield importlib.import_module("screen")


def test_sign_test_is_the_exact_binomial_tail(bench) -> None:
    assert bench.sign_test(5, 1) == pytest.approx(7 / 64) and bench.sign_test(0, 0) == 1.0
    assert bench.sign_test(3, 0) == pytest.approx(1 / 8) and bench.sign_test(0, 3) == 1.0


@pytest.mark.parametrize(
    "arms, message",
    [
        (["only=a"], "give two or more arms as NAME=DIR"),
        (["a=a", "b"], "give two or more arms as NAME=DIR"),
        (["a=a", "b=missing"], "missing: no finished dqn_cartpole records"),
        (["a=a", "c=c"], "the arms share no finished seed"),
    ],
)
def test_bad_arms_end_in_one_line(bench, tmp_path, monkeypatch, arms, message) -> None:
    monkeypatch.chdir(tmp_path)
    write(tmp_path / "a", 0, [500, 500, 500], 500.0)
    write(tmp_path / "c", 1, [500, 500, 500], 500.0)
    monkeypatch.setattr(sys, "argv", ["screen.py", "--preset", "dqn_cartpole", *arms])
    with pytest.raises(SystemExit) as ended:
        bench.main()
    assert message in str(ended.value.code) and "\n" not in str(ended.value.code)
