"""Sweeps: the per-sweep summary, failed jobs, bad sweep input, launchers and the Optuna sweeper."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
from pathlib import Path

import pytest
import yaml
from conftest import TINY, needs_extra, run_module
from hydra.errors import ConfigCompositionException, MissingConfigException

from rlpipe.cli import format_error
from rlpipe.command import check_launcher
from rlpipe.errors import RlpipeError
from rlpipe.sweep import write_summary

# a tiny sweep of two jobs, the second of which fails on a bad value
FAST = [*TINY, "logger=none", "checkpoint_every=0", "threads=1"]
ONE_FAILS = ["algo.lr=0.001,-1"]


def make_job(sweep: Path, num: int, overrides: list[str], result: dict | None) -> Path:
    """A job directory as Hydra and rlpipe leave it (``result``: summary.json or error.json)."""
    job = sweep / str(num)
    (job / ".hydra").mkdir(parents=True)
    (job / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (job / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump({"hydra": {"job": {"num": num}}}))
    if result is not None:
        name = "error.json" if "error" in result else "summary.json"
        (job / name).write_text(json.dumps(result))
    return job


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path) as f:
        return list(csv.DictReader(f))


def run_sweep(tmp_path: Path, *args: str):
    """``python -m rlpipe -m args...`` with the sweep dir ``tmp_path/sweep``."""
    sweep = tmp_path / "sweep"
    return run_module("rlpipe", "-m", *args, f"hydra.sweep.dir={sweep}", cwd=tmp_path), sweep


def test_summary_has_one_row_per_job_in_job_order(tmp_path):
    summary = {"eval_mean": 9.5, "eval_std": 0.5, "eval_episodes": 2, "frames": 200}
    make_job(tmp_path, 10, ["seed=0", "algo=dqn"], {**summary, "wall_time": 3.0})
    make_job(
        tmp_path,
        2,
        ["seed=1", "algo=dqn"],
        {"error": "algo.lr must be a finite number > 0", "wall_time": 0.1},
    )
    make_job(tmp_path, 3, ["seed=2", "algo=dqn"], None)  # killed before it finished
    rows, rejected = write_summary(tmp_path)
    assert rejected == []
    assert [(r.job, r.status) for r in rows] == [(2, "failed"), (3, "unfinished"), (10, "ok")]
    table = read_csv(tmp_path / "summary.csv")
    assert [r["overrides"] for r in table] == [
        "seed=1 algo=dqn",
        "seed=2 algo=dqn",
        "seed=0 algo=dqn",
    ]
    assert table[2]["eval_mean"] == "9.5" and table[2]["frames"] == "200"
    assert table[0]["error"] == "algo.lr must be a finite number > 0"
    markdown = (tmp_path / "summary.md").read_text()
    assert markdown.startswith("every job: `algo=dqn`")  # shared overrides shown once
    assert "| 10 | seed=0 | 9.50 ± 0.50 | 200 | 3.0 |  |" in markdown
    assert "| 2 | seed=1 | failed | – | 0.1 | algo.lr must be a finite number > 0 |" in markdown
    assert "| 3 | seed=2 | unfinished | – | – | did not finish" in markdown


def test_no_job_no_summary(tmp_path):
    assert write_summary(tmp_path) == ([], [])
    assert not (tmp_path / "summary.csv").exists() and not (tmp_path / "summary.md").exists()


def test_rejected_jobs_are_shown_apart_and_each_job_counts_once(tmp_path):
    summary = {"eval_mean": 9.5, "eval_std": 0.5, "eval_episodes": 2, "frames": 200}
    for num in (0, 1):
        make_job(tmp_path, num, [f"seed={num}"], {**summary, "wall_time": 3.0})
        refused = {"error": f"{tmp_path / str(num)} belongs to another run", "wall_time": 0.1}
        make_job(tmp_path / "rejected", num, [f"seed={num}", "algo.lr=0.1"], refused)
    rows, rejected = write_summary(tmp_path)
    assert [(r.job, r.status) for r in rows] == [(0, "ok"), (1, "ok")]
    assert [(r.job, r.status) for r in rejected] == [(0, "rejected"), (1, "rejected")]
    table = read_csv(tmp_path / "summary.csv")
    assert [(r["job"], r["status"]) for r in table] == [
        ("0", "ok"),
        ("1", "ok"),
        ("0", "rejected"),
        ("1", "rejected"),
    ]
    markdown = (tmp_path / "summary.md").read_text()
    jobs, _, apart = markdown.partition("Rejected: their dir belonged to another run")
    assert jobs.count("| ok |") == 0 and jobs.count("9.50 ± 0.50") == 2 and "failed" not in jobs
    assert "| 0 | seed=0 algo.lr=0.1 | " in apart and "belongs to another run" in apart


def test_summary_aggregates_each_group_of_seeds(tmp_path):
    def job(num: int, overrides: list[str], mean: float, env_id: str) -> None:
        result = {"eval_mean": mean, "eval_std": 0.0, "eval_episodes": 2, "frames": 200}
        made = make_job(tmp_path, num, overrides, {**result, "wall_time": 1.0})
        (made / "config.yaml").write_text(f"env:\n  id: {env_id}\nalgo:\n  name: dqn\n")

    means = [400.0, 480.0, 500.0, 490.0]
    for seed, mean in enumerate(means):
        job(seed, [f"seed={seed}", "algo.lr=0.1"], mean, "CartPole-v1")  # target 475
    job(4, ["seed=0", "algo.lr=0.2"], 100.0, "CartPole-v1")
    job(5, ["seed=0", "env=pendulum"], -150.0, "Pendulum-v1")  # no target in the registry
    rows, _ = write_summary(tmp_path)
    markdown = (tmp_path / "summary.md").read_text()
    group = next(line for line in markdown.splitlines() if line.startswith("| algo.lr=0.1 |"))
    cells = [cell.strip() for cell in group.strip("|").split("|")]
    assert cells[1] == "4" and cells[4] == "3/4 (≥ 475)", cells
    assert cells[2].startswith("467.50 [") and cells[3].startswith("485.00 ["), cells  # mean, IQM
    low, high = map(float, cells[2].partition("[")[2].rstrip("]").split(", "))
    assert 400.0 <= low < 467.5 < high <= 500.0
    assert "| algo.lr=0.2 | 1 | 100.00 | 100.00 | 0/1 (≥ 475) |" in markdown
    assert "| env=pendulum | 1 | -150.00 | -150.00 | – (no known target) |" in markdown


def test_two_sweeps_into_one_dir_list_each_job_once(tmp_path):
    """The second sweep's jobs resolve to the first's dirs: one is the same run (it reports
    its result), the other another run (rejected, shown apart; nothing of the first changes)."""
    proc, sweep = run_sweep(tmp_path, *FAST, "seed=0,1")
    assert proc.returncode == 0, proc.stderr
    first = (sweep / "1" / "summary.json").read_bytes()
    proc = run_module("rlpipe", "-m", *FAST, "seed=0,2", f"hydra.sweep.dir={sweep}", cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert "sweep of 2 jobs, 0 failed, 1 rejected" in proc.stdout, proc.stdout
    rows = read_csv(sweep / "summary.csv")
    assert [(r["job"], r["overrides"].split()[-1], r["status"]) for r in rows] == [
        ("0", "seed=0", "ok"),
        ("1", "seed=1", "ok"),
        ("1", "seed=2", "rejected"),
    ]
    assert (sweep / "1" / "summary.json").read_bytes() == first


def test_ray_launcher_runs_the_jobs_as_ray_tasks(tmp_path):
    """hydra/launcher=ray (hydra-ray-launcher): each job a Ray task on a Ray started here
    (hydra.launcher.ray.init.address=<head>:6379 for a cluster's)."""
    needs_extra("hydra_plugins.hydra_ray_launcher", "ray")
    options = [
        "+hydra.launcher.ray.init.num_cpus=2",
        "+hydra.launcher.ray.init.include_dashboard=false",
    ]
    proc, sweep = run_sweep(tmp_path, "hydra/launcher=ray", *options, *FAST, "seed=0,1")
    assert proc.returncode == 0, proc.stderr
    rows = read_csv(sweep / "summary.csv")
    assert [(r["job"], r["status"]) for r in rows] == [("0", "ok"), ("1", "ok")]
    assert "Ray Launcher is launching 2 jobs" in proc.stdout + proc.stderr
    workers = re.findall(r"\(_run_job pid=(\d+)\)", proc.stdout + proc.stderr)
    assert workers and str(os.getpid()) not in workers  # the jobs ran in Ray's worker processes


def test_a_failed_job_is_reported_and_the_others_run(tmp_path):
    proc, sweep = run_sweep(tmp_path, *FAST, *ONE_FAILS)
    assert proc.returncode == 1, proc.stderr  # the sweep ran, but not every job succeeded
    assert "rlpipe: error: algo.lr must be a finite number > 0, got -1.0" in proc.stderr
    assert "Traceback" not in proc.stderr
    rows = read_csv(sweep / "summary.csv")
    assert [(r["job"], r["status"]) for r in rows] == [("0", "ok"), ("1", "failed")]
    ok = json.loads((sweep / "0" / "summary.json").read_text())
    assert float(rows[0]["eval_mean"]) == ok["eval_mean"] and rows[0]["frames"] == "200"
    assert rows[1]["error"] == "algo.lr must be a finite number > 0, got -1.0"
    assert "| 1 | algo.lr=-1 | failed |" in proc.stdout  # the table is printed too
    assert str(sweep / "summary.md") in proc.stdout


def test_sweeping_a_key_that_does_not_exist_is_one_line_and_no_summary(tmp_path):
    proc, sweep = run_sweep(tmp_path, "progress=false", "algo.nope=1,2")
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error: ") and "'nope'" in lines[0]
    assert not list(sweep.glob("summary.*")) and not list(sweep.glob("*/summary.json"))


def test_missing_launcher_plugin_names_the_extra():
    err = MissingConfigException(
        "Could not find 'hydra/launcher/joblib'", "hydra/launcher/joblib", ["basic"]
    )
    assert format_error(err) == (
        "unknown hydra/launcher option 'joblib'; choose one of: basic; "
        'install it with: pip install "rlpipe[joblib]"'
    )


@pytest.mark.skipif(shutil.which("srun") is not None, reason="this machine is a Slurm node")
def test_slurm_launcher_without_slurm_is_one_line_and_writes_nothing(tmp_path):
    proc, sweep = run_sweep(tmp_path, "hydra/launcher=submitit_slurm", "seed=0,1", *FAST)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "rlpipe: error: hydra/launcher=submitit_slurm needs a Slurm cluster, and srun is not on "
        "the PATH here: run the sweep on a Slurm login node, or here with "
        "hydra/launcher=submitit_local (or joblib)"
    ]
    assert not sweep.exists() and not (tmp_path / "outputs").exists()


def test_slurm_launcher_is_let_through_where_srun_is(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: f"/usr/bin/{name}")
    check_launcher(["hydra/launcher=submitit_slurm", "seed=0,1"])
    monkeypatch.setattr(shutil, "which", lambda name: None)
    check_launcher(["hydra/launcher=submitit_local"])
    with pytest.raises(RlpipeError, match="needs a Slurm cluster"):
        check_launcher(["hydra/launcher=joblib", "+hydra/launcher=submitit_slurm"])


def test_composition_error_keeps_its_reason():
    err = ConfigCompositionException(
        "In 'sweep/x': ConfigKeyError raised while composing config:\nKey 'seed' not in 'Grid'"
    )
    assert format_error(err) == (
        "In 'sweep/x': ConfigKeyError raised while composing config: Key 'seed' not in 'Grid'"
    )


def test_joblib_launcher_runs_jobs_in_parallel_processes(tmp_path):
    needs_extra("hydra_plugins.hydra_joblib_launcher", "joblib")
    with_bars = [arg for arg in FAST if arg != "progress=false"]
    proc, sweep = run_sweep(
        tmp_path, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", *with_bars, *ONE_FAILS
    )
    assert proc.returncode == 1, proc.stderr
    # parallel jobs draw no progress bars over each other: each prints its summary line
    assert "frame/s" not in proc.stderr + proc.stdout and "rlpipe: final eval" in proc.stdout
    rows = read_csv(sweep / "summary.csv")
    assert [r["status"] for r in rows] == ["ok", "failed"]
    assert rows[1]["error"] == "algo.lr must be a finite number > 0, got -1.0"


@pytest.mark.parametrize("sampler", ["random", "grid"])
def test_optuna_sweeper_maximises_the_returned_eval_mean(tmp_path, sampler):
    """rlpipe's Optuna sweeper on current Optuna: a failed trial is recorded and the search
    goes on (the grid's search ends with its grid, whatever n_trials says)."""
    optuna = needs_extra("optuna", "optuna")
    assert int(optuna.__version__.split(".")[0]) >= 4
    proc = run_module(
        "rlpipe",
        "+sweep=dqn_cartpole",  # hydra.mode=MULTIRUN: no -m
        *FAST,
        f"hydra/sweeper/sampler={sampler}",
        *(["hydra.sweeper.sampler.seed=0"] if sampler == "random" else []),
        f"hydra.sweeper.n_trials={2 if sampler == 'random' else 5}",
        "hydra.sweeper.params=null",
        "algo.lr=choice(0.001, -1)",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        cwd=tmp_path,
    )
    sweep = tmp_path / "sweep"
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr  # a trial failed
    rows = {r["overrides"].split()[0]: r for r in read_csv(sweep / "summary.csv")}
    assert len(rows) == 2 and "[I " not in proc.stderr  # no Optuna INFO lines
    assert rows["algo.lr=-1"]["status"] == "failed"
    ok = rows["algo.lr=0.001"]
    assert ok["status"] == "ok"
    results = yaml.safe_load((sweep / "optimization_results.yaml").read_text())
    assert results["best_params"] == {"algo.lr": 0.001}
    assert results["best_value"] == pytest.approx(float(ok["eval_mean"]))


def test_a_signal_stops_the_whole_sweep_and_resume_sweep_continues_it(tmp_path):
    """The first SIGINT checkpoints the running job and stops the sweep (no next job starts);
    ``-m resume_sweep=<dir>`` then reports the finished job, resumes the interrupted one from
    its checkpoint and runs the rest."""
    import os
    import signal
    import subprocess
    import sys
    import time

    sweep = tmp_path / "sweep"
    args = [
        "-m",
        "seed=0,1,2",
        "total_frames=3200",
        "eval_every=1600",
        "eval_episodes=2",
        "progress=false",
        f"hydra.sweep.dir={sweep}",
    ]
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "rlpipe", *args],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 240
    while not (sweep / "1" / "metrics").is_dir() and time.monotonic() < deadline:
        time.sleep(0.2)  # job 1 has started training
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    last = err.strip().splitlines()[-1]
    assert "sweep stopped: SIGINT during job 1 (checkpointed), 1 jobs finished" in last
    assert f"python -m rlpipe -m resume_sweep={sweep}" in last
    assert not (sweep / "2").exists()  # the next job never started
    assert "| 1 | seed=1 | interrupted |" in out
    stopped_at = json.loads((sweep / "1" / "interrupted.json").read_text())
    assert "SIGINT received: stopped at" in stopped_at["error"]
    finished = (sweep / "0" / "summary.json").read_text()

    done = run_module("rlpipe", "-m", f"resume_sweep={sweep}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "resuming" in done.stdout and "already finished" in done.stdout
    assert (sweep / "0" / "summary.json").read_text() == finished  # reported, not retrained
    rows = list(csv.DictReader((sweep / "summary.csv").open()))
    assert [(r["job"], r["status"], r["frames"]) for r in rows] == [
        ("0", "ok", "3200"),
        ("1", "ok", "3200"),
        ("2", "ok", "3200"),
    ]
    assert not (sweep / "1" / "interrupted.json").exists()


def test_resume_sweep_of_a_directory_that_is_not_a_sweep_is_one_line(tmp_path):
    done = run_module("rlpipe", "-m", f"resume_sweep={tmp_path}", cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.strip() == (
        f"rlpipe: error: {tmp_path} is not a sweep directory (no multirun.yaml); pass the "
        "directory a python -m rlpipe -m ... run wrote (outputs/multirun/<date>/<time>)"
    )
