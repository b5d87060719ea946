"""``python -m rlpipe [overrides]``: train one run (or a ``-m`` sweep) from the Hydra config."""

from __future__ import annotations

import logging
import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from rlpipe.cli import USER_ERRORS, fail, register_configs, run_cli, to_config
from rlpipe.pipeline import train
from rlpipe.runner import RunResult
from rlpipe.sweep import SweepSummary, run_sweep_job

register_configs()


@hydra.main(version_base="1.3", config_path="pkg://rlpipe.conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> float | None:
    hydra_cfg = HydraConfig.get()
    run_dir = hydra_cfg.runtime.output_dir

    def job() -> RunResult:
        return train(to_config(cfg), run_dir)

    if hydra_cfg.mode == RunMode.MULTIRUN:
        # exiting would end the whole sweep: the failure is recorded and the other jobs run
        result = run_sweep_job(job, run_dir)
        if result is None:
            return None  # a failed trial for sweepers (Optuna)
    else:
        try:
            result = job()
        except USER_ERRORS as err:
            fail(err)  # here rather than in run_cli: Hydra would add a line of its own
    print(f"rlpipe: {result.summary_line()}")
    return result.eval_mean  # what Hydra sweepers optimise


def main() -> None:
    """Console entry point (also ``rlpipe`` on the PATH)."""
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # keep the console to progress + summary
    run_cli(_hydra_main)
    if SweepSummary.failed_jobs:
        sys.exit(1)  # the sweep's summary, just printed, names the failed jobs and their errors


if __name__ == "__main__":
    main()
