"""``python -m rlpipe [overrides]``: train one run (or a ``-m`` sweep) from the Hydra config."""

from __future__ import annotations

import logging
import re
import sys
from dataclasses import replace
from functools import partial
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from rlpipe.cli import (
    USER_ERRORS,
    check_launcher,
    fail,
    open_entries,
    register_configs,
    run_cli,
    to_config,
    validate_overrides,
    write_hydra_record,
)
from rlpipe.errors import check
from rlpipe.help import help_text
from rlpipe.pipeline import train
from rlpipe.runner import RunResult
from rlpipe.sweep import SweepStopped, SweepSummary, resume_sweep, run_sweep_job

register_configs()


@hydra.main(version_base="1.3", config_path="pkg://rlpipe.conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> float | None:
    hydra_cfg = HydraConfig.get()
    run_dir = hydra_cfg.runtime.output_dir

    def job() -> RunResult:
        config = to_config(cfg)
        if "BasicLauncher" not in hydra_cfg.launcher.get("_target_", "BasicLauncher"):
            # jobs in parallel processes (joblib, submitit) would draw over each other's bars:
            # each prints its summary line instead
            config = replace(config, progress=False)
        return train(config, run_dir, on_start=partial(write_hydra_record, job_cfg=cfg))

    if hydra_cfg.mode == RunMode.MULTIRUN:
        # exiting would end the whole sweep: the failure is recorded and the other jobs run
        record = partial(write_hydra_record, job_cfg=cfg)
        rejected = Path(hydra_cfg.sweep.dir) / "rejected" / str(hydra_cfg.job.num)
        result = run_sweep_job(
            job, run_dir, record=record, rejected_dir=rejected, sweep_dir=hydra_cfg.sweep.dir
        )
        if result is None:
            return None  # a failed trial for sweepers (Optuna)
    else:
        try:
            result = job()
        except USER_ERRORS as err:
            fail(err)  # here rather than in run_cli: Hydra would add a line of its own
    print(f"rlpipe: {result.summary_line()}")
    return result.eval_mean  # what Hydra sweepers optimise


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


def main() -> None:
    """Console entry point (also ``rlpipe`` on the PATH)."""
    if {"-h", "--help"} & set(sys.argv[1:]):  # ours; Hydra's own: --hydra-help
        print(help_text())
        return
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # keep the console to progress + summary
    try:
        sys.argv[1:] = open_entries(resume_in_place(resume_sweep(sys.argv[1:])))
        check_launcher(sys.argv[1:])
        if {"-c", "--cfg"} & set(sys.argv[1:]):
            validate_overrides(sys.argv[1:])  # Hydra prints the config without calling the job
    except USER_ERRORS as err:
        fail(err)
    try:
        run_cli(_hydra_main)
    except SweepStopped as stop:
        print(f"\n{stop.table}")
        print(f"rlpipe: {stop.message}", file=sys.stderr)
        sys.exit(stop.exit_code)
    if SweepSummary.failed_jobs:
        sys.exit(1)  # the sweep's summary, just printed, names the failed jobs and their errors


if __name__ == "__main__":
    main()
