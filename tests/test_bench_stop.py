"""benchmarks/presets.py stopped (Ctrl-C, SIGTERM): its runs stop where they are, saved, and it
ends with one line, no traceback and no run called failed; killed outright (no clean stop):
neither its SB3 process nor its rlpipe run trains on, orphaned and unseen, for hours."""

from __future__ import annotations

import importlib.util
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPT = BENCHMARKS / "presets.py"
pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux"), reason="reads /proc; the rlpipe run's guard is Linux's"
)
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

# a run that ignores SIGINT, so only a kill ends it; it writes its pid to sys.argv[1]
STUBBORN = (
    "import os, signal, sys, time; signal.signal(signal.SIGINT, signal.SIG_IGN); "
    "open(sys.argv[1], 'w').write(str(os.getpid())); time.sleep(60)"
)


@pytest.fixture
def stop_module(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import presets_stop

    return presets_stop


def _state(pid: int) -> tuple[str, int] | None:
    """``pid``'s state letter and parent (Linux: /proc); None: no such process."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError):
        return None
    return fields[0], int(fields[1])


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead but not yet reaped, does not)."""
    state = _state(pid)
    return state is not None and state[0] != "Z"


def _children(pid: int) -> list[int]:
    """The live processes whose parent is ``pid``."""
    pids = [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()]
    return [c for c in pids if _alive(c) and (_state(c) or ("", 0))[1] == pid]


def test_a_run_asked_to_stop_gets_one_sigint_then_a_kill_and_none_starts_after(
    stop_module, tmp_path
):
    runs, pid_file = stop_module.Runs(), tmp_path / "pid"
    codes: list[int] = []
    command = [sys.executable, "-c", STUBBORN, str(pid_file)]
    caller = threading.Thread(target=lambda: codes.append(runs.call(command)))
    caller.start()
    deadline = time.monotonic() + 30
    while not pid_file.is_file() or not pid_file.read_text():
        assert time.monotonic() < deadline, "the run did not start"
        time.sleep(0.05)
    assert runs.signal(signal.SIGINT) == 1
    caller.join(0.5)
    assert caller.is_alive()  # it ignores SIGINT: still running
    assert runs.signal(signal.SIGKILL) == 1
    caller.join(10)
    assert codes == [-signal.SIGKILL]
    with pytest.raises(stop_module.Stopped):  # stopping: no run starts
        runs.call([sys.executable, "-c", "open('started', 'w')"], cwd=tmp_path)
    assert not (tmp_path / "started").exists()


def test_the_stop_signals_raise_stop_and_leave_an_ignored_sigint_ignored(stop_module):
    before = signal.getsignal(signal.SIGTERM)
    # SIGINT as a terminal leaves it (pytest started as a background job inherits it ignored)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with stop_module.stop_signals():
            with pytest.raises(stop_module.Stop) as stop:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
            for signum in (signal.SIGINT, signal.SIGTERM):  # from the first Stop on, another kills
                assert signal.getsignal(signum) is stop_module._kill_runs
        assert stop.value.signum == signal.SIGTERM and str(stop.value) == "SIGTERM"
        assert signal.getsignal(signal.SIGTERM) is before
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        with stop_module.stop_signals():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


@pytest.mark.skipif(
    importlib.util.find_spec("stable_baselines3") is None, reason='needs the "bench" extra'
)
@pytest.mark.parametrize("how", ["ctrl-c", "sigterm"])
def test_a_stopped_benchmark_ends_its_runs_saved_with_one_line(tmp_path, how):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it) or SIGTERM to the
    benchmark alone: each run gets one SIGINT (the rlpipe run checkpoints once: two would stop it
    unsaved), none outlives the benchmark, and its last line says how to go on."""
    out = tmp_path / "runs"
    command = [sys.executable, str(SCRIPT), "--presets", "dqn_cartpole", "--seeds", "100"]
    command += ["--frames", "1000000", "--sb3", "--jobs", "2", "--out", str(out)]
    # SIGINT at its default in the benchmark, as a terminal's shell leaves it (a background
    # pytest would hand it down ignored, and an ignored SIGINT stays ignored there)
    bench = subprocess.Popen(
        command,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    log = out / "dqn_cartpole" / "seed100" / "rlpipe.log"
    deadline = time.monotonic() + 120
    while "env backend" not in (log.read_text() if log.is_file() else ""):
        assert time.monotonic() < deadline and bench.poll() is None, "the runs did not start"
        time.sleep(0.2)
    time.sleep(2)  # into training
    runs = _children(bench.pid)
    assert len(runs) >= 2  # the rlpipe run, the SB3 process (and multiprocessing's tracker)
    if how == "ctrl-c":
        os.killpg(bench.pid, signal.SIGINT)
    else:
        bench.send_signal(signal.SIGTERM)
    _, err = bench.communicate(timeout=120)
    signum = signal.SIGINT if how == "ctrl-c" else signal.SIGTERM
    assert bench.returncode == 128 + signum, err
    lines = err.strip().splitlines()
    assert lines[-1].startswith(f"presets: stopped by {signal.Signals(signum).name}; the same")
    assert "Traceback" not in err and "FAILED" not in err
    assert sum(" stopped in " in line for line in lines) == 2, err
    assert log.read_text().count("checkpointing after this iteration") == 1
    assert list((out / "dqn_cartpole" / "seed100" / "run" / "checkpoints").glob("ckpt_*.pt"))
    deadline = time.monotonic() + 5  # multiprocessing's tracker ends once it sees the pipe shut
    while any(map(_alive, runs)) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(map(_alive, runs)), "a run outlived the benchmark"


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
