"""``python -m rlpipe [overrides]``: train one run (or a ``-m`` sweep) from the Hydra config."""

from __future__ import annotations

import logging

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from rlpipe.cli import USER_ERRORS, fail, register_configs, run_cli, to_config
from rlpipe.train import train

register_configs()


@hydra.main(version_base="1.3", config_path="pkg://rlpipe.conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> float:
    try:
        config = to_config(cfg)
        result = train(config, HydraConfig.get().runtime.output_dir)
    except USER_ERRORS as err:
        fail(err)  # here rather than in run_cli: Hydra would add a line of its own
    print(f"rlpipe: {result.summary_line()}")
    return result.eval_mean  # what Hydra sweepers optimise


def main() -> None:
    """Console entry point (also ``rlpipe`` on the PATH)."""
    logging.getLogger("torchrl").setLevel(logging.WARNING)  # keep the console to progress + summary
    run_cli(_hydra_main)


if __name__ == "__main__":
    main()
