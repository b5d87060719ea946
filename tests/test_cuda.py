"""device=cuda: every algorithm trains, is killed, resumes and evaluates on CUDA (on both env
backends), every preset runs, compiled losses too; skipped where torch sees no CUDA device.

Run on a GPU machine: ``pytest tests/test_cuda.py``. ``RLPIPE_TEST_DEVICE=cpu`` runs the same
checks on the CPU (to check the checks)."""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path
from typing import Any

import pytest
import torch
from conftest import run_module
from fault_harness import ALGOS
from tensordict import TensorDict

from rlpipe.algos.reinforce import normalized_returns
from rlpipe.checkpoint import load_checkpoint
from rlpipe.envs.backends import envpool_version
from rlpipe.rundir import RunDir

DEVICE = os.environ.get("RLPIPE_TEST_DEVICE", "cuda")
pytestmark = pytest.mark.skipif(
    DEVICE == "cuda" and not torch.cuda.is_available(), reason="needs a CUDA device"
)
ROOT = Path(__file__).resolve().parents[1]
PRESETS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
BACKENDS = [
    "gymnasium",
    pytest.param("envpool", marks=pytest.mark.skipif(not envpool_version(), reason="no EnvPool")),
]
TIMEOUT = 600


def tensor_devices(state: Any) -> set[str]:
    """The device types of every floating-point tensor in a checkpoint's (nested) state (not
    counters, nor the CPU random generators' byte states)."""
    if isinstance(state, dict):
        return set().union(*map(tensor_devices, state.values()))
    if isinstance(state, list | tuple):
        return set().union(*map(tensor_devices, state))
    floating = isinstance(state, torch.Tensor) and state.is_floating_point()
    return {state.device.type} if floating else set()


def assert_trained_on_device(run_dir: Path, algo: str) -> None:
    """The newest checkpoint's networks, losses and replay buffers were saved from ``DEVICE``
    (ARS's from the CPU: it runs there whatever ``device`` says). The optimizers are left out:
    torch keeps a non-fused Adam's step counts on the CPU by design."""
    state = load_checkpoint(RunDir(run_dir).checkpoints()[-1], map_location=None)["algo"]
    learner = {key: value for key, value in state.items() if key != "optimizer"}
    assert tensor_devices(learner) == {"cpu" if algo == "ars" else DEVICE}, sorted(learner)


def rlpipe(*args: str, cwd: Path, env: dict[str, str] | None = None):
    """``python -m rlpipe`` in a fresh interpreter (CUDA cannot be used in a forked child of a
    process that has used it)."""
    return run_module("rlpipe", *args, cwd=cwd, timeout=TIMEOUT, fresh=True, env=env)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("algo", sorted(ALGOS))
def test_a_run_killed_on_the_device_resumes_and_evaluates(tmp_path, algo, backend):
    run_dir = tmp_path / "run"
    args = [*ALGOS[algo], f"device={DEVICE}", f"env.backend={backend}", "progress=false"]
    if backend == "envpool":  # EnvPool has no continuous-action CartPole: REINFORCE's own
        args = [arg.replace("=cartpole_continuous", "=cartpole") for arg in args]
    args.append(f"hydra.run.dir={run_dir}")
    killed = rlpipe(*args, cwd=tmp_path, env={"RLPIPE_FAULT": "checkpoint_write@2"})
    assert killed.returncode == -signal.SIGKILL, killed.stderr  # writing its second checkpoint
    assert not (run_dir / "summary.json").exists()
    assert len(RunDir(run_dir).checkpoints()) == 1
    resumed = rlpipe(*args, cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert "rlpipe: resuming" in resumed.stdout, resumed.stdout
    assert json.loads((run_dir / "summary.json").read_text())["frames"] > 0
    assert_trained_on_device(run_dir, algo)
    for device in sorted({DEVICE, "cpu"}):  # a run trained on the device evaluates anywhere
        out = tmp_path / f"eval-{device}.json"
        evaluated = run_module(
            "rlpipe.evaluate", f"run_dir={run_dir}", f"device={device}", "episodes=2",
            f"out={out}", cwd=tmp_path, timeout=TIMEOUT, fresh=True,
        )  # fmt: skip
        assert evaluated.returncode == 0, evaluated.stderr
        assert len(json.loads(out.read_text())["returns"]) == 2


def tiny(preset: str) -> list[str]:
    """The preset with its algorithm's tiny run (tests/fault_harness.py) in place of its budget."""
    algo = preset.partition("_")[0]
    keep = [arg for arg in ALGOS[algo] if not arg.startswith(("~tuned", "algo=", "env="))]
    return [f"+experiment={preset}", *keep, "env.num_envs=2", "checkpoint_every=0"]


@pytest.mark.parametrize("preset", PRESETS)
def test_every_preset_runs_on_the_device(tmp_path, preset):
    if preset.endswith("minigrid_pixels"):
        pytest.importorskip("minigrid", reason="needs the minigrid extra")
    run_dir = tmp_path / "run"
    proc = rlpipe(*tiny(preset), f"device={DEVICE}", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert_trained_on_device(run_dir, preset.partition("_")[0])


@pytest.mark.parametrize("algo", ["dqn", "ppo", "sac"])
def test_a_compiled_loss_trains_on_the_device(tmp_path, algo):
    run_dir = tmp_path / "run"
    args = [*ALGOS[algo], f"device={DEVICE}", "compile=true", f"hydra.run.dir={run_dir}"]
    proc = rlpipe(*args, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert_trained_on_device(run_dir, algo)


def test_reinforces_normalised_returns_are_deterministic_on_the_device():
    """torch's deterministic mode refuses CUDA's ``bincount`` with weights (atomic adds in no
    fixed order): REINFORCE's per-episode normalisation runs under it and equals the CPU's."""
    reward = torch.rand(64, 1, generator=torch.Generator().manual_seed(0))
    done = torch.zeros(64, 1, dtype=torch.bool)
    done[[9, 30, 63]] = True
    batch = TensorDict({"next": {"reward": reward, "done": done}}, [64])
    on_cpu = normalized_returns(batch, 0.99)
    torch.use_deterministic_algorithms(True)
    try:
        ours = normalized_returns(batch.to(DEVICE), 0.99)
    finally:
        torch.use_deterministic_algorithms(False)
    assert ours.device.type == DEVICE
    torch.testing.assert_close(ours.cpu(), on_cpu)
