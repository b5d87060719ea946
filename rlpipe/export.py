"""``python -m rlpipe.export run_dir=... [checkpoint=best] [format=torchscript|onnx|state_dict]``.

Writes a trained run's greedy policy as one standalone file that maps a float32 batch of raw
observations ``[batch, obs]`` to the actions rlpipe's evaluation takes (normaliser and action
head included): ``format=torchscript`` (the default; ``torch.jit.load`` is all it needs),
``onnx`` (any ONNX runtime; the ``onnx`` extra) or ``state_dict`` (the tensors and a spec, to
load into the same module). ``run_dir=latest`` is the newest run under ``outputs/``;
``checkpoint=best`` the best evaluation's (default: the newest). The file goes to
``<run_dir>/export/policy-<checkpoint>.pt`` (``.onnx``, ``-state_dict.pt``) or ``out=<file>``
(an existing file only with ``overwrite=true``), and only once, loaded back, it takes the run's
actions on ``observations`` observations sampled from the env's observation space. A run dir's
``env.id`` of the form ``module:Id`` is refused unless ``allow_env_import=true``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from hydra.core.config_store import ConfigStore

from rlpipe.cli import compose_config, run_entry_point
from rlpipe.errors import check
from rlpipe.export_formats import ExportResult, export_policy
from rlpipe.runs import latest_run
from rlpipe.runtime import set_threads


@dataclass
class ExportConfig:
    """``conf/export.yaml``: which run and checkpoint, the format, where the file goes."""

    run_dir: str | None = None  # a training run's directory; latest: the newest under outputs/
    checkpoint: str | None = None  # a file in <run_dir>/checkpoints; best; null: the newest
    format: str = "torchscript"  # torchscript | onnx | state_dict
    out: str | None = None  # null: <run_dir>/export/policy-<checkpoint><suffix>
    overwrite: bool = False  # replace an existing out= file
    observations: int = 1000  # sampled observations the file is checked on before it is written
    seed: int = 0  # the sampled observations'
    # let a run dir's env.id import its module (module:Id); only for run dirs you trust
    allow_env_import: bool = False

    def __post_init__(self) -> None:  # the other keys: export_policy checks them first
        check(
            self.run_dir is not None,
            "pass run_dir=<a training run's directory> (or run_dir=latest)",
        )


def run(cfg: ExportConfig) -> ExportResult:
    """Export as ``cfg`` says (:func:`rlpipe.export_formats.export_policy`)."""
    run_dir = str(latest_run()) if cfg.run_dir == "latest" else cfg.run_dir
    set_threads("auto", torch.device("cpu"))  # one thread: small networks, busy cores
    keys = {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg) if f.name != "run_dir"}
    return export_policy(run_dir, **keys)


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m rlpipe.export key=value ...``; user errors: one line, exit 2."""
    keys = ", ".join(f.name for f in dataclasses.fields(ExportConfig))
    run_entry_point(f"{__doc__.strip()}\n\nkeys (conf/export.yaml): {keys}", argv, _export)


def _export(args: list[str]) -> None:
    print(f"rlpipe: {run(compose_config('export', args)).summary_line()}")


ConfigStore.instance().store(name="export_schema", node=ExportConfig)

if __name__ == "__main__":
    main()
