"""Running benchmarks/presets.py's jobs: one rlpipe run as a user runs it, read back when done.

Each rlpipe run is exactly what a user runs, in a subprocess (``SDL_VIDEODRIVER=dummy``):

    python -m rlpipe +experiment=<preset> seed=<s> progress=false checkpoint_every=0 \
        hydra.run.dir=<dir> [total_frames=<--frames>]
    python -m rlpipe.evaluate run_dir=<dir> episodes=<final episodes> seed=<episodes_seed(s, FINAL)>

then its ``metrics/scalars/eval/return_mean.csv`` and ``time/train_seconds.csv`` give the evals
(frames, mean, training seconds) and ``evaluation/trained-*.json`` the final greedy eval; all of
it, with the machine and load it ran on, goes to the record ``rlpipe.json`` beside the run dir.
A job whose record holds its evals is finished: a later call reads the record, not the run dir,
so records kept without their run dirs (``benchmarks/results/presets/``, committed) carry a
long benchmark across machines. A record from before evaluations met starts of their own
(:data:`EVAL_STARTS`) is read back too, and the table marks it; delete it to run it anew.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from common import machine, read_scalar
from presets_stop import RUNS
from presets_table import Preset

from rlpipe.config import Config, config_class, fingerprint
from rlpipe.episodes import FINAL, episodes_seed
from rlpipe.files import write_atomic
from rlpipe.rundir import RunDir

PACKAGES = ["torch", "torchrl", "tensordict", "gymnasium", "stable_baselines3", "sb3_contrib"]
UNRECORDED = "not recorded (a run of an earlier version of presets.py)"
# how a record's evaluations were seeded; records without it met starts shared by every seed
EVAL_STARTS = "per run and evaluation (rlpipe.episodes.episodes_seed)"


@dataclass
class Run:
    """One finished (or failed) run: its evals as (frames, mean, training seconds) rows."""

    preset: str
    seed: int
    which: str  # "rlpipe" or "SB3"
    evals: list[tuple[int, float, float]] = field(default_factory=list)
    final: float | None = None  # the final greedy eval's mean
    seconds: float = 0.0  # wall seconds of the whole job (training, evals, start-up)
    wall: float | None = None  # rlpipe: the run's own wall seconds (its summary.json)
    error: str | None = None
    reused: bool = False  # read from an earlier call's --out, not run by this one
    machine: str = UNRECORDED  # machine() of the process that ran it
    load: tuple[float, float] | None = None  # 1-min load average at its start and end
    shared_starts: bool = False  # evaluated on the starts every seed met (an older record)

    def hit(self, target: float) -> tuple[int, float] | None:
        """(frames, training seconds) of the first eval reaching ``target``."""
        return next(((f, s) for f, m, s in self.evals if m >= target - 1e-6), None)

    @property
    def train_seconds(self) -> float | None:
        """Training seconds of the whole run (evaluations excluded): at its last eval."""
        return self.evals[-1][2] if self.evals else None

    @property
    def last_three(self) -> float | None:
        return float(np.mean([m for _, m, _ in self.evals[-3:]])) if self.evals else None

    def solved(self, target: float) -> bool:
        """The protocol's rule: the last three evals' mean and the final eval both ≥ target."""
        last = self.last_three
        return last is not None and self.final is not None and min(last, self.final) >= target


def record(where: Path, start_load: float, **result: object) -> dict:
    """Write ``result`` with this process's machine and the load at the start and now to
    ``where`` (JSON); the record is what a later call reads back. It appears whole or not at
    all (:func:`rlpipe.files.write_atomic`): a kill never leaves a torn record to read back."""
    saved = {**result, "machine": machine(PACKAGES), "load": [start_load, os.getloadavg()[0]]}
    saved["eval_starts"] = EVAL_STARTS
    where.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(where, (json.dumps(saved, indent=2) + "\n").encode())
    return saved


def recorded(saved: dict) -> dict:
    """The machine, load, wall and eval starts fields of a record (absent in earlier versions'
    records)."""
    load = saved.get("load")
    return {
        "machine": saved.get("machine", UNRECORDED),
        "load": tuple(load) if load else None,
        "wall": saved.get("wall"),
        "shared_starts": saved.get("eval_starts") != EVAL_STARTS,
    }


# Linux: the run gets SIGTERM (it saves and stops) once the thread that started it is gone, so a
# benchmark killed outright leaves no run training on unseen; prctl's setting outlives exec.
END_WITH_BENCHMARK = (
    "import ctypes, os, sys; ctypes.CDLL(None).prctl(1, 15); "  # PR_SET_PDEATHSIG, SIGTERM
    "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])"
)


def _call(args: list[str], log: Path, cwd: Path) -> None:
    """``python <args>`` with its output appended to ``log``; a failure raises its last line."""
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    guard = ["-c", END_WITH_BENCHMARK] if sys.platform.startswith("linux") else []
    with open(log, "a") as f:
        f.write(f"$ python {' '.join(args)}\n")
        f.flush()
        code = RUNS.call([sys.executable, *guard, *args], stdout=f, stderr=f, env=env, cwd=cwd)
    if code != 0:
        lines = [line for line in log.read_text().splitlines() if line.strip()]
        raise RuntimeError(f"exit {code}: {lines[-1] if lines else '(no output)'} (log: {log})")


def final_evals(run_dir: Path) -> list[Path]:
    """The run's final greedy evaluations (``rlpipe.evaluate``'s JSON), oldest first."""
    found = (run_dir / "evaluation").glob("trained-*.json")
    return sorted(found, key=lambda p: p.stat().st_mtime)


def identity(cfg: Config) -> dict:
    """What a record must match to stand for a run of ``cfg`` on any seed: what decides its
    results (:func:`rlpipe.config.fingerprint`, the seed aside, and the env backend, which
    ``auto`` picks per machine: the record names it), its budget and eval cadence."""
    kept = {k: v for k, v in fingerprint(cfg).items() if k not in ("seed", "env.backend")}
    kept |= {k: getattr(cfg, k) for k in ("total_frames", "eval_every", "eval_episodes")}
    return json.loads(json.dumps(kept, default=str))  # as a record reads back


def same_identity(saved: dict, cfg: Config) -> bool:
    """Whether a record's identity (``saved``) stands for a run of ``cfg``: every key equal,
    and a key the record lacks (a config field added since it ran) at its default, which is
    what the run had before the field existed."""
    ours = identity(cfg)
    defaults = identity(Config(algo=config_class(cfg.algo.name)()))
    return set(saved) <= set(ours) and all(
        saved[k] == v if k in saved else defaults.get(k, object()) == v for k, v in ours.items()
    )


def rlpipe_finished(out: Path, cfg: Config | None = None) -> bool:
    """Whether ``out`` (a job's dir in ``--out``) holds the record of a finished and evaluated
    rlpipe run of ``cfg`` (a preset changed since, or a run on another env backend than the
    one ``cfg`` names: not finished), or such a run from before records held the evals."""
    meta = out / "rlpipe.json"
    if meta.is_file() and "evals" in (saved := json.loads(meta.read_text())):
        if cfg is None:
            return True
        # a backend the preset or an --override names must be the record's; auto's is EnvPool
        # or gymnasium as the machine has EnvPool, but gymnasium for one env copy everywhere
        backend = cfg.env.backend
        if backend == "auto" and cfg.stepped_copies() == 1:
            backend = "gymnasium"
        return same_identity(saved.get("config", {}), cfg) and backend in (
            "auto",
            saved.get("backend"),
        )
    return (out / "run" / "summary.json").is_file() and bool(final_evals(out / "run"))


def read_run(run_dir: Path) -> dict:
    """A finished run's evals, as ``[frames, mean, training seconds]``, its final eval and its
    own wall seconds (training and its evals, imports aside: its ``summary.json``)."""
    seconds = dict(read_scalar(run_dir, "time/train_seconds"))
    evals = [[f, m, seconds[f]] for f, m in read_scalar(run_dir, "eval/return_mean")]
    final = json.loads(final_evals(run_dir)[-1].read_text())["return_mean"]
    summary = json.loads((run_dir / "summary.json").read_text())
    return {"evals": evals, "final": final, "wall": summary["wall_time"]}


def rlpipe_job(
    preset: Preset,
    cfg: Config,
    seed: int,
    frames: int | None,
    episodes: int,
    out: Path,
    extra: Sequence[str] = (),
) -> Run:
    """Train the preset as a user would (plus the ``extra`` overrides), evaluate it, read its
    metrics."""
    run_dir = out / "run"  # not "rlpipe": cwd is on a -m module's path and would shadow it
    out.mkdir(parents=True, exist_ok=True)
    log, meta = out / "rlpipe.log", out / "rlpipe.json"
    overrides = [
        f"+experiment={preset.experiment}",
        f"seed={seed}",
        "progress=false",
        # resumable: a checkpoint at every eval, and the same command continues a killed run
        f"checkpoint_every={cfg.eval_every if preset.resumable else 0}",
        f"hydra.run.dir={run_dir}",
        *extra,
    ] + ([f"total_frames={frames}"] if frames is not None else [])
    reused = rlpipe_finished(out, cfg)  # an earlier call's run of this preset
    if not reused and meta.is_file():  # the record of a preset since changed: run it anew
        meta.unlink()
        shutil.rmtree(run_dir, ignore_errors=True)
    if reused:
        saved = json.loads(meta.read_text()) if meta.is_file() else {}
        if "evals" not in saved or ("wall" not in saved and run_dir.is_dir()):
            saved.update(read_run(run_dir))  # a record from before records held these
    else:
        start = os.getloadavg()[0]
        _call(["-m", "rlpipe", *overrides], log, out)
        final = f"seed={episodes_seed(seed, FINAL)}"  # SB3's final eval meets the same starts
        # the run dir is this call's own: a network's or env's module named by an --override
        # (algo.network._target_=...) is imported again to evaluate it
        trusted = "allow_env_import=true"
        evaluate = ["-m", "rlpipe.evaluate", f"run_dir={run_dir}", f"episodes={episodes}"]
        _call([*evaluate, final, trusted], log, out)
        ran = RunDir(run_dir).read_config(allow_code=True)
        saved = record(
            meta, start, **read_run(run_dir), config=identity(ran), backend=ran.env.backend
        )
    return record_run(preset.experiment, seed, saved, reused)


def record_run(preset: str, seed: int, saved: dict, reused: bool = False) -> Run:
    """The rlpipe run a record (``rlpipe.json``, holding its evals) tells of."""
    evals = [(int(f), float(m), float(s)) for f, m, s in saved["evals"]]
    return Run(preset, seed, "rlpipe", evals, saved.get("final"), reused=reused, **recorded(saved))


class Scheduler:
    """Runs jobs ``jobs`` at a time, in order; the jobs of one group start together. Of the
    ``total`` jobs, ``read_back`` are done (records read back): a line for each of the others
    as it ends, none for those."""

    def __init__(self, jobs: int, total: int, read_back: int = 0) -> None:
        self.jobs, self.to_run = jobs, total - read_back
        self.slots = threading.Semaphore(jobs)
        self.pool = ThreadPoolExecutor(max(1, total))  # the slots, not the pool, bound the runs
        self.futures: list[Future[Run]] = []
        self.start, self.done = time.perf_counter(), 0
        self.lock = threading.Lock()

    def group(self, jobs: Sequence[tuple[str, int, str, Callable[[], Run], bool]]) -> None:
        """Start ``jobs`` (preset, seed, which, function, done) at once, as soon as there are
        slots; a done job (its record is read back) takes none, so it holds up no other run."""
        running = [job for job in jobs if not job[4]]
        if len(running) > self.jobs:
            for job in jobs:
                self.group([job])
            return
        for _ in running:
            self.slots.acquire()
        self.futures += [self.pool.submit(self._run, *job) for job in jobs]

    def _run(self, preset: str, seed: int, which: str, fn: Callable[[], Run], done: bool) -> Run:
        start = time.perf_counter()
        try:
            run = fn()
        except Exception as e:  # one failed run must not sink a long benchmark
            run = Run(preset, seed, which, error=f"{type(e).__name__}: {e}")
        finally:
            if not done:
                self.slots.release()
        run.seconds = time.perf_counter() - start
        with self.lock:
            self.done += not done
            status = f"FAILED ({run.error})" if run.error else "done"
            if run.error and RUNS.stopping:  # asked to stop (or not started): not a failure
                status = "stopped"
            if not done or run.error:  # a record read back says nothing unless it failed
                print(
                    f"presets: {preset} seed {seed} {which} {status} in {run.seconds:.0f} s "
                    f"({self.done}/{self.to_run} runs, {time.perf_counter() - self.start:.0f} s "
                    "elapsed)",
                    file=sys.stderr,
                    flush=True,
                )
        return run

    def wait(self) -> None:
        """Until every job started has ended: its future, not its thread, as a join a signal
        interrupts takes the thread for ended from then on (CPython before 3.13)."""
        wait(self.futures)

    def results(self) -> list[Run]:
        self.wait()
        self.pool.shutdown(wait=True)
        return [f.result() for f in self.futures]
