"""A trained run's greedy policy written as one standalone file (TorchScript, ONNX or a state
dict), checked against the run's own policy before anything is written.

:func:`export_policy` loads a run (:func:`rlpipe.load_run`), builds its greedy module
(:func:`rlpipe.greedy.greedy_policy`), serialises it, loads the bytes back the way a user would
(``torch.jit.load``, an ``onnxruntime`` session, ``load_state_dict`` into a blank copy) and
compares their actions with the run's policy on observations sampled from the env's
observation space; only then does it write the file. Each file carries a spec (JSON: the env,
the observation and action shapes, the action bounds, the run and checkpoint): in a TorchScript
file as the extra file ``rlpipe.json``, in an ONNX file as the metadata entry ``rlpipe``, in a
state-dict file under ``"spec"``.
"""

from __future__ import annotations

import copy
import io
import json
import logging
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torch import nn

from rlpipe import __version__
from rlpipe.envs.observations import dict_observation
from rlpipe.errors import RlpipeError, check
from rlpipe.files import check_writable, write_atomic
from rlpipe.greedy import FixedNoisePlanner, greedy_policy, policy_actions
from rlpipe.loggers import require_extra
from rlpipe.models import error_reason
from rlpipe.pipeline import LoadedRun, load_run
from rlpipe.rundir import RunDir

SPEC_NAME = "rlpipe"  # the spec's name: rlpipe.json in a TorchScript file, ONNX metadata key
# format -> (the file's suffix, how to load it: {path} is filled in)
FORMATS = {
    "torchscript": (".pt", "torch.jit.load({path!r})"),
    "onnx": (".onnx", "onnxruntime.InferenceSession({path!r})"),
    "state_dict": ("-state_dict.pt", "torch.load({path!r}, weights_only=True)"),
}
TOLERANCE = 1e-5  # continuous actions: the largest difference accepted (ONNX Runtime's kernels)

Actions = Callable[[torch.Tensor], torch.Tensor]  # a loaded file, as observations -> actions


@dataclass
class ExportResult:
    """What :func:`export_policy` wrote.

    The file, its format and spec, and on how many observations it was checked."""

    path: Path
    format: str
    spec: dict[str, Any]
    checked: int

    def summary_line(self) -> str:
        """One line: what was exported, where, the check, and how to load it."""
        spec, obs = self.spec, self.spec["observation"]["shape"][0]
        action = spec["action"]
        out = "int64 [batch]"
        if action["kind"] != "discrete":
            out = f"float32 [batch, {action['shape'][0]}]"
        load = FORMATS[self.format][1].format(path=str(self.path))
        return (
            f"exported {spec['algo']}'s greedy policy ({spec['checkpoint']}, {spec['frames']:,} "
            f"frames) as {self.format} to {self.path} | the same actions as the run's policy on "
            f"{self.checked} sampled observations | load it with {load}: float32 [batch, {obs}] "
            f"observations -> {out} actions"
        )


def export_policy(
    run_dir: str | Path,
    *,
    format: str = "torchscript",
    checkpoint: str | None = None,
    out: str | Path | None = None,
    overwrite: bool = False,
    observations: int = 1000,
    seed: int = 0,
    allow_env_import: bool = False,
    network: nn.Module | None = None,
) -> ExportResult:
    """Write a trained run's greedy policy as one standalone file.

    ``run_dir``'s policy (its newest checkpoint; ``"best"``, or a file name in
    its ``checkpoints/``) as one ``format`` file at ``out`` (default:
    ``<run_dir>/export/policy-<checkpoint><suffix>``), after checking that the file, loaded
    back, takes the run's actions on ``observations`` observations sampled (``seed``) from the
    env's observation space. An existing ``out`` is replaced only with ``overwrite``.
    ``allow_env_import`` and ``network``: as :func:`rlpipe.load_run` takes them."""
    check(
        format in FORMATS,
        f"format must be one of {', '.join(FORMATS)}; got {format!r}",
    )
    check(observations >= 1, f"observations must be >= 1, got {observations}")
    if format == "onnx":
        require_extra("onnx", "format=onnx")
    check(
        out is None or overwrite or not os.path.lexists(out),
        f"{out} exists; pass overwrite=true to replace it, or another out=<file>",
    )
    loaded = load_run(  # gymnasium's env: the spaces a plain loop sees (no EnvPool to start)
        run_dir,
        checkpoint,
        allow_env_import=allow_env_import,
        network=network,
        backend="gymnasium",
    )
    try:
        name = f"policy-{loaded.checkpoint.stem}{FORMATS[format][0]}"
        path = Path(out) if out is not None else Path(run_dir) / RunDir.EXPORT / name
        check_writable(path, "pick a writable place for the file with out=<file>")
        module = greedy_policy(loaded.algo)
        observation_space, spec = _spec(loaded, format, module)
        sampled = _sample(observation_space, observations + 2, seed)
        example, sampled = sampled[:2], sampled[2:]  # the trace's example batch, and the check's
        rows_alone = isinstance(module, FixedNoisePlanner)
        expected = policy_actions(loaded.algo.policy, sampled, rows_alone=rows_alone)
    finally:
        loaded.algo.close()
    writer, reader = _WRITERS[format]
    with warnings.catch_warnings():  # torch's notes on its tracers' internals
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", FutureWarning)
        data = writer(module, example, spec)
    with torch.no_grad():
        _check_same(expected, reader(data, module)(sampled), format)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, data)
    return ExportResult(path, format, spec, observations)


def _spec(loaded: LoadedRun, format: str, module: nn.Module) -> tuple[gym.spaces.Box, dict]:
    """The env's observation space, and the spec a file carries."""
    cfg = loaded.cfg
    env = dict_observation(gym.make(cfg.env.id, **cfg.env.kwargs))  # a Dict: its vector
    observation_space, action_space = env.observation_space, env.action_space
    env.close()
    if isinstance(action_space, gym.spaces.Discrete):
        action = {"kind": "discrete", "n": int(action_space.n), "dtype": "int64"}
    else:
        action = {
            "kind": "box",
            "shape": list(action_space.shape),
            "low": action_space.low.tolist(),
            "high": action_space.high.tolist(),
            "dtype": "float32",
        }
    spec = {
        "format": format,
        "algo": cfg.algo.name,
        "env": {
            "id": cfg.env.id,
            "kwargs": dict(cfg.env.kwargs),
            "max_episode_steps": cfg.env.max_episode_steps,
        },
        "observation": {"shape": list(observation_space.shape), "dtype": "float32"},
        "action": action,
        "checkpoint": loaded.checkpoint.name,
        "frames": loaded.algo.frames,
        "versions": {"rlpipe": __version__, "torch": str(torch.__version__)},
    }
    if format == "state_dict":  # what the state dict's keys belong to
        spec["module"] = str(module)
    return observation_space, spec


def _sample(space: gym.Space, n: int, seed: int) -> torch.Tensor:
    """``n`` observations drawn from ``space`` (seeded), as float32 rows."""
    space.seed(seed)
    return torch.as_tensor(np.stack([space.sample() for _ in range(n)]), dtype=torch.float32)


def _check_same(expected: torch.Tensor, actual: torch.Tensor, format: str) -> None:
    """One line unless the file's actions are the run's policy's (continuous: to
    :data:`TOLERANCE`)."""
    if actual.shape != expected.shape or actual.dtype != expected.dtype:
        differ = (
            f"actions of shape {tuple(actual.shape)} ({actual.dtype}), not "
            f"{tuple(expected.shape)} ({expected.dtype}),"
        )
    else:
        same = torch.isclose(actual, expected, rtol=TOLERANCE, atol=TOLERANCE, equal_nan=True)
        wrong = int((~same.reshape(len(same), -1).all(1)).sum())
        if not wrong:
            return
        differ = f"other actions on {wrong} of {len(expected)} observations"
    raise RlpipeError(
        f"the {format} file, loaded back, takes {differ} than the run's policy, so nothing was "
        "written: a network that is random in eval mode, or whose Python control flow depends "
        "on its inputs, cannot be exported faithfully (try another format=)"
    )


def _torchscript(module: nn.Module, example: torch.Tensor, spec: dict) -> bytes:
    """``torch.jit.trace`` of the module, saved with the spec."""
    traced = _user_step("torch.jit.trace", lambda: torch.jit.trace(module, example))
    buffer = io.BytesIO()
    torch.jit.save(traced, buffer, _extra_files={f"{SPEC_NAME}.json": json.dumps(spec)})
    return buffer.getvalue()


def _read_torchscript(data: bytes, module: nn.Module) -> Actions:
    return torch.jit.load(io.BytesIO(data))


def _onnx(module: nn.Module, example: torch.Tensor, spec: dict) -> bytes:
    """``torch.onnx.export`` (torch.export) with a dynamic batch; the spec in its metadata."""
    quiet = logging.getLogger("torch.onnx")  # its notes on missing torchvision operators
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        program = _user_step(
            "torch.onnx.export",
            lambda: torch.onnx.export(
                module,
                (example,),
                input_names=["observation"],
                output_names=["action"],
                dynamic_shapes=({0: torch.export.Dim("batch")},),
                dynamo=True,
                verbose=False,
            ),
        )
    finally:
        quiet.setLevel(level)
    model = program.model_proto
    entry = model.metadata_props.add()
    entry.key, entry.value = SPEC_NAME, json.dumps(spec)
    return model.SerializeToString()


def _read_onnx(data: bytes, module: nn.Module) -> Actions:
    import onnxruntime

    session = onnxruntime.InferenceSession(data, providers=["CPUExecutionProvider"])
    return lambda observations: torch.as_tensor(
        session.run(None, {"observation": observations.numpy()})[0]
    )


def _state_dict(module: nn.Module, example: torch.Tensor, spec: dict) -> bytes:
    """``{"state_dict": ..., "spec": ...}`` as ``torch.save`` writes it."""
    buffer = io.BytesIO()
    torch.save({"state_dict": module.state_dict(), "spec": spec}, buffer)
    return buffer.getvalue()


def _read_state_dict(data: bytes, module: nn.Module) -> Actions:
    """A copy of ``module`` with every tensor zeroed, then the file's state dict loaded: the
    file must hold everything the policy needs."""
    blank = copy.deepcopy(module)
    for tensor in blank.state_dict().values():
        tensor.zero_()
    blank.load_state_dict(torch.load(io.BytesIO(data), weights_only=True)["state_dict"])
    return blank


_WRITERS: dict[str, tuple[Callable[..., bytes], Callable[[bytes, nn.Module], Actions]]] = {
    "torchscript": (_torchscript, _read_torchscript),
    "onnx": (_onnx, _read_onnx),
    "state_dict": (_state_dict, _read_state_dict),
}


def _user_step(what: str, step: Callable[[], Any]) -> Any:
    """``step()``; its failure (on a network of the user's) as one line naming ``what``."""
    try:
        return step()
    except Exception as err:  # the network's code is the user's: show its failure in one line
        raise RlpipeError(
            f"{what} cannot follow this policy ({error_reason(err)}); try another format="
        ) from err
