"""Process-wide runtime settings a run needs: device, seeds, torch threads, RNG state."""

from __future__ import annotations

import os
import random
from typing import Any

import numpy as np
import torch

from rlpipe.errors import RlpipeError, check

# torch's own intra-op threads (one per core) as rlpipe found them: what ``threads=0`` restores
TORCH_THREADS = torch.get_num_threads()


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda when available, else cpu; else ``cpu``, ``cuda`` or ``cuda:N`` (the
    configs check the name: see the ``device`` rule of :data:`rlpipe.errors.RULES`)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RlpipeError(f"device={name} asked for, but no CUDA device is available; use auto")
    return device


def seed_everything(seed: int) -> None:
    """Seed Python's, NumPy's and torch's global generators."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def set_threads(threads: int | str, device: torch.device) -> None:
    """Set torch's intra-op threads, process-wide: ``"auto"`` is 1 on a CPU device (the networks
    here are small: more threads only contend with other processes) and torch's default
    elsewhere; ``0`` is torch's default (:data:`TORCH_THREADS`, one per core); ``N`` uses N.
    Building an algorithm, a :class:`~rlpipe.Runner` and ``load_run`` call it.

    It also flushes subnormal floats (below 1.2e-38) to zero on the calling thread, where torch
    runs its ops with one thread (``torch.set_flush_denormal``; x86 and ARM CPUs): weights that
    weight decay shrinks into that range made MBRL's planner up to 6x slower on a CPU
    (benchmarks/denormals.py), and no result here depends on numbers that small."""
    check(
        threads == "auto" or (type(threads) is int and threads >= 0),
        f"threads must be auto or a number >= 0 (0: torch's default), got {threads!r}",
    )
    if threads == "auto":
        threads = 1 if device.type == "cpu" else 0
    torch.set_num_threads(threads or TORCH_THREADS)
    torch.set_flush_denormal(True)


def env_threads(threads: int | str) -> int:
    """EnvPool's worker threads under rlpipe's ``threads`` setting: ``"auto"`` is 1 (a training
    run's env copies cost little next to its learning; ARS sets its own from ``algo.workers``),
    ``0`` one per core, ``N`` N."""
    if threads == "auto":
        return 1
    return threads or os.cpu_count() or 1


def rng_state() -> dict[str, Any]:
    """Python's, NumPy's and torch's global generator states (the CUDA devices' too, once CUDA
    is in use: draws on a CUDA device come from them), as checkpoint-safe containers."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    state = {
        "python": random.getstate(),
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, cached],
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_initialized():  # never initialises CUDA for a CPU run
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore what :func:`rng_state` captured (CUDA's on the devices this machine has)."""
    random.setstate(state["python"])
    kind, keys, pos, has_gauss, cached = state["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])
    if state.get("cuda") and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"][: torch.cuda.device_count()])
