"""benchmarks/presets.py killed outright (no clean stop): neither its SB3 process nor its rlpipe
run trains on, orphaned and unseen, for hours."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
# the benchmark's side: starts a child that writes its pid to sys.argv[1], then waits
SB3_SIDE = """
import os, subprocess, sys, time
sys.path.insert(0, {bench!r})
child = (
    "import os, sys, time; sys.path.insert(0, {bench!r}); from presets_sb3 import end_with; "
    + ("end_with(os.getppid(), every=0.05); " if {guarded} else "")
    + "open(sys.argv[1], 'w').write(str(os.getpid())); time.sleep(30)"
)
subprocess.Popen([sys.executable, "-c", child, sys.argv[1]])
time.sleep(60)
"""
RLPIPE_SIDE = """
import sys
sys.path.insert(0, {bench!r})
import presets_runs
from pathlib import Path
if not {guarded}:
    presets_runs.sys.platform = "off"
child = "import os, sys, time; open(sys.argv[1], 'w').write(str(os.getpid())); time.sleep(30)"
presets_runs._call(["-c", child, sys.argv[1]], Path(sys.argv[1] + ".log"), Path.cwd())
"""

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads /proc; the rlpipe side's guard is Linux's"
)


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.parametrize("side", [SB3_SIDE, RLPIPE_SIDE], ids=["sb3", "rlpipe"])
@pytest.mark.parametrize("guarded", [True, False])
def test_a_run_ends_with_its_killed_benchmark(tmp_path, side, guarded):
    """Kill the benchmark with SIGKILL: its child is gone within 5 s (and, unguarded, is not:
    what the guard prevents)."""
    pid_file = tmp_path / "child.pid"
    code = side.format(bench=str(BENCHMARKS), guarded=guarded)
    benchmark = subprocess.Popen([sys.executable, "-c", code, str(pid_file)], cwd=tmp_path)
    deadline = time.monotonic() + 30
    while not pid_file.is_file() or not pid_file.read_text():
        assert time.monotonic() < deadline and benchmark.poll() is None, "no child started"
        time.sleep(0.05)
    pid = int(pid_file.read_text())
    benchmark.kill()
    benchmark.wait()
    deadline = time.monotonic() + 5
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        assert _alive(pid) is not guarded
    finally:
        if _alive(pid):
            os.kill(pid, signal.SIGKILL)
