"""The tests' forked runs (tests/warm.py) behave as ``python -m`` does where tests rely on it."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import textwrap
import uuid

import pytest
import warm
from conftest import TINY, run_module
from fault_harness import TAG_VAR, assert_no_live_processes, live_processes, same_run_files

PROBE = """
import json, os, sys, time
mode = sys.argv[1]
print(json.dumps({"argv": sys.argv[1:], "cwd": os.getcwd(), "name": __name__,
                  "fault": os.environ.get("RLPIPE_FAULT"), "tag": os.environ.get("{tag}")}))
print("to stderr", file=sys.stderr)
if mode == "exit2":
    sys.exit(2)
if mode == "kill":
    os.kill(os.getpid(), 9)
if mode == "raise":
    raise RuntimeError("boom")
if mode == "orphan":  # a child that outlives the run, as a leaked worker would
    import subprocess
    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
if mode == "hang":
    time.sleep(60)
"""


@pytest.fixture
def probe(tmp_path):
    """A module ``probe`` in ``tmp_path`` (the run's cwd): run it forked with ``run(mode)``."""
    (tmp_path / "probe.py").write_text(textwrap.dedent(PROBE).replace("{tag}", TAG_VAR))

    def run(mode: str, env: dict[str, str] | None = None, timeout: float = 60):
        return warm.run("probe", [mode], cwd=tmp_path, env=env or {}, timeout=timeout)

    return run


def test_argv_cwd_environment_and_output_are_the_runs_own(probe, tmp_path):
    done = probe("ok", env={"RLPIPE_FAULT": "eval@1"})
    assert done.returncode == 0, done.stderr
    seen = {"argv": ["ok"], "cwd": str(tmp_path), "name": "__main__", "fault": "eval@1"}
    assert json.loads(done.stdout) == {**seen, "tag": None}
    assert done.stderr == "to stderr\n"
    assert probe("ok").stdout.count('"fault": null') == 1  # the last run's variable is gone


@pytest.mark.parametrize(
    "mode, code, stderr",
    [
        ("exit2", 2, "to stderr\n$"),
        ("kill", -signal.SIGKILL, "to stderr\n$"),
        ("raise", 1, "RuntimeError: boom\n$"),
    ],
)
def test_exit_codes_are_pythons(probe, mode, code, stderr):
    done = probe(mode)
    assert done.returncode == code
    assert re.search(stderr, done.stderr), done.stderr


def test_a_process_left_behind_is_found_by_the_runs_tag(probe):
    tag = uuid.uuid4().hex
    assert probe("orphan", env={TAG_VAR: tag}).returncode == 0
    pids = live_processes(tag)
    assert len(pids) == 1
    with pytest.raises(AssertionError, match="outlived"):
        assert_no_live_processes(tag, grace=0.5)
    warm._kill_session(warm.SESSIONS[tag][0])
    assert_no_live_processes(tag)


def test_a_timeout_kills_the_run_and_raises(probe):
    tag = uuid.uuid4().hex
    with pytest.raises(subprocess.TimeoutExpired):
        probe("hang", env={TAG_VAR: tag}, timeout=3)
    assert_no_live_processes(tag)


def test_a_forked_run_writes_what_a_fresh_interpreter_writes(tmp_path):
    """The same tiny run, forked and in a fresh interpreter: the same metrics, config, summary
    (but its clock) and checkpoint names, and the same console lines but for times and paths."""
    consoles = {}
    for fresh in (False, True):
        run = tmp_path / ("fresh" if fresh else "forked")
        done = run_module("rlpipe", *TINY, f"hydra.run.dir={run}", cwd=tmp_path, fresh=fresh)
        assert done.returncode == 0, done.stderr
        consoles[fresh] = re.sub(
            r"[\d.]+ s\b|\S*/(fresh|forked)\b", "<>", done.stdout + done.stderr
        )
    assert same_run_files(tmp_path / "forked") == same_run_files(tmp_path / "fresh")
    assert consoles[False] == consoles[True]
