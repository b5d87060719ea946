"""The train command, ``python -m rlpipe [overrides]``: one run (or a ``-m`` sweep) from the Hydra
config, from the arguments to the summary line. Config errors and a bad run dir (its layout, its
config.yaml) are answered before torch loads (the training pipeline is imported once they have
passed their checks); the env's own (an unknown id, actions the algorithm cannot take) after.

Read top-down: :func:`main` prepares the arguments and hands them to Hydra, which composes the
config and calls :func:`task` once per run (or sweep job)."""

from __future__ import annotations

import os
import re
import shutil
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import hydra
from hydra import compose, initialize_config_module
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from rlpipe.cli import (
    USER_ERRORS,
    check_choices,
    fail,
    open_entries,
    register_configs,
    register_sweeper,
    to_config,
    trap_notice,
    tuned_elsewhere_notice,
    tuned_notice,
    without_hydra,
)
from rlpipe.console import say
from rlpipe.errors import RlpipeError, check
from rlpipe.outcomes import RunResult
from rlpipe.rundir import RunDir
from rlpipe.sweep import SweepStopped, SweepSummary, resume_sweep, run_sweep_job
from rlpipe.sweep_summary import REJECTED


def main() -> None:
    """Run the command on ``sys.argv``; user errors end in one line and exit 2."""
    try:
        register_configs()  # a plug-in that does not import: one line
        argv = open_entries(resume_in_place(resume_sweep(sys.argv[1:])))
        sys.argv[1:] = argv = quote_letters(argv)
        check_launcher(argv)
        if {"-c", "--cfg"} & set(argv):
            if show_job_config(argv):
                return  # printed; other --cfg uses are Hydra's to print, without calling the job
        elif is_sweep(argv):  # a sweep's jobs are checked one by one
            register_sweeper()
        else:
            validate_overrides(argv)  # every config error, before Hydra makes a run dir
    except USER_ERRORS as err:
        fail(err)
    os.environ.setdefault("HYDRA_FULL_ERROR", "1")  # let errors reach us instead of Hydra's print
    try:
        task()
    except USER_ERRORS as err:
        fail(err)
    except OSError as err:  # e.g. Hydra cannot create the run directory
        where = f" {err.filename}" if err.filename else ""
        fail(
            RlpipeError(
                f"cannot write{where}: {err.strerror or err}; pick a writable directory "
                "with hydra.run.dir=<dir> (hydra.sweep.dir=<dir> for -m)"
            )
        )
    except SweepStopped as stop:
        print(f"\n{stop.table}")
        print(f"rlpipe: {stop.message}", file=sys.stderr)
        sys.exit(stop.exit_code)
    finally:
        NewRunDir.remove_if_empty()
    if SweepSummary.failed_jobs:
        sys.exit(1)  # the sweep's summary, just printed, names the failed jobs and their errors


def resume_in_place(argv: list[str]) -> list[str]:
    """``resume=<dir>`` runs in ``<dir>`` (no new ``outputs/<date>/<time>``) unless
    ``hydra.run.dir`` is given or it is a sweep."""
    resume = [arg.partition("=")[2] for arg in argv if re.match(r"^\+{0,2}resume=", arg)]
    if not resume or resume[-1] in ("", "null") or {"-m", "--multirun"} & set(argv):
        return argv
    if any(arg.startswith("hydra.run.dir=") for arg in argv):
        return argv
    check(Path(resume[-1]).is_dir(), f"run directory {resume[-1]} does not exist")
    return [*argv, f"hydra.run.dir={resume[-1]}"]


def is_sweep(argv: Sequence[str]) -> bool:
    """Whether ``argv`` runs a sweep: ``-m``, or a ``+sweep=`` search (``hydra.mode=MULTIRUN``)."""
    return bool({"-m", "--multirun"} & set(argv)) or any(
        re.match(r"^\+{0,2}sweep=", arg) for arg in argv
    )


def quote_letters(argv: list[str]) -> list[str]:
    """Quote for Hydra the values its grammar takes only quoted: letters beyond ASCII (a run dir
    ``hydra.run.dir=/data/résumé`` becomes ``hydra.run.dir='/data/résumé'``)."""
    quoted = []
    for arg in argv:
        key, eq, value = arg.partition("=")
        if eq and not value.isascii() and not re.search(r"""['"\\\[\]{}]""", value):
            arg = f"{key}='{value}'"
        quoted.append(arg)
    return quoted


class NewRunDir(Callback):
    """Hydra callback: before Hydra makes a run's dir, note which of it and its parents are
    missing, so that :meth:`remove_if_empty` can take away those still empty when the command
    ends (a run that failed before writing anything); nothing that existed before is removed."""

    missing: ClassVar[list[Path]] = []  # deepest first

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        run_dir = Path(config.hydra.run.dir).absolute()
        NewRunDir.missing = [d for d in (run_dir, *run_dir.parents) if not os.path.lexists(d)]

    @classmethod
    def remove_if_empty(cls) -> None:
        """Remove the noted dirs that are empty, deepest first (stopping at one that is not)."""
        for directory in cls.missing:
            try:
                directory.rmdir()
            except OSError:  # not empty (the run wrote), or not ours to remove
                break
        cls.missing = []


def check_launcher(argv: Sequence[str]) -> None:
    """Refuse ``hydra/launcher=submitit_slurm`` where Slurm is not (no ``srun`` on the PATH)."""
    launchers = [arg.partition("=")[2] for arg in argv if re.match(r"^\+{0,2}hydra/launcher=", arg)]
    check(
        not launchers or launchers[-1] != "submitit_slurm" or shutil.which("srun") is not None,
        "hydra/launcher=submitit_slurm needs a Slurm cluster, and srun is not on the PATH here: "
        "run the sweep on a Slurm login node, or here with hydra/launcher=submitit_local (or "
        "joblib)",
    )


def show_job_config(argv: Sequence[str]) -> bool:
    """``--cfg job`` (``-c job``, with ``--resolve`` or not): print the checked config as Hydra
    would, composed once, and return True; any other ``--cfg`` use: check it, return False (Hydra
    prints it)."""
    cfg = validate_overrides(argv)
    flags = [arg for arg in argv if arg.startswith("-")]
    if any(flag not in ("-c", "--cfg", "--resolve") for flag in flags):
        return False
    shown = argv[max(i for i, arg in enumerate(argv) if arg in ("-c", "--cfg")) + 1 :][:1]
    if shown != ["job"]:
        return False
    if "--resolve" in argv:
        OmegaConf.resolve(cfg)
    sys.stdout.write(OmegaConf.to_yaml(cfg))
    return True


def validate_overrides(argv: Sequence[str]) -> DictConfig:
    """Compose ``python -m rlpipe``'s config from ``argv``'s overrides (flags, their values and
    ``hydra`` keys left out), run every check :func:`to_config` runs, and return it."""
    overrides, skip = [], False
    for arg in argv:
        if skip or arg.startswith("-"):
            skip = arg in ("-c", "--cfg", "-p", "--package", "-cn", "--config-name", "-cp")
            continue
        if not re.match(r"^[+~]{0,2}hydra[./]", arg):
            overrides.append(arg)
    with initialize_config_module("rlpipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=overrides, return_hydra_config=True)
    check_choices(cfg.hydra.runtime.choices, OmegaConf.select(cfg, "env.id", default=None))
    cfg = without_hydra(cfg)
    to_config(cfg.copy())
    return cfg


@hydra.main(version_base="1.3", config_path="pkg://rlpipe.conf", config_name="config")
def task(cfg: DictConfig) -> float | None:
    """One run in Hydra's run dir, or one job of a sweep (a failure is recorded and the sweep
    goes on); prints the summary line and returns the final eval mean (what sweepers optimise).
    """
    hydra_cfg = HydraConfig.get()
    run_dir = hydra_cfg.runtime.output_dir

    def job() -> RunResult:
        check_choices(hydra_cfg.runtime.choices, OmegaConf.select(cfg, "env.id", default=None))
        config = to_config(cfg)  # checked before torch loads (with the pipeline, below)
        choices = hydra_cfg.runtime.choices
        notice = (
            tuned_notice(choices)
            or trap_notice(config.algo, config.env.id)
            or tuned_elsewhere_notice(choices, config.env)
        )
        if notice:
            say(notice)
        RunDir(config.resume or run_dir).precheck(required=bool(config.resume))
        from rlpipe.pipeline import train

        if "BasicLauncher" not in hydra_cfg.launcher.get("_target_", "BasicLauncher"):
            # jobs in parallel processes (joblib, submitit) would draw over each other's bars:
            # each prints its summary line instead
            config = replace(config, progress=False)
        return train(config, run_dir, on_start=record)

    def record(run: RunDir) -> None:  # Hydra's record of the job, once the dir is checked
        run.write_hydra_record(cfg, hydra_cfg)

    if hydra_cfg.mode == RunMode.MULTIRUN:
        rejected = Path(hydra_cfg.sweep.dir) / REJECTED / str(hydra_cfg.job.num)
        result = run_sweep_job(
            job, run_dir, record=record, rejected_dir=rejected, sweep_dir=hydra_cfg.sweep.dir
        )
        if result is None:
            return None  # a failed trial for sweepers (Optuna)
    else:
        try:
            result = job()
        except USER_ERRORS as err:
            fail(err)  # here rather than in main: Hydra would add a line of its own
    say(f"rlpipe: {result.summary_line()}")
    return result.eval_mean
