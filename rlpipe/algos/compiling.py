"""The ``compile`` key: whether torch can compile here, and ``torch.compile`` of an algorithm's
loss forward (its backward compiled with it), the rest of the update left eager."""

from __future__ import annotations

import os
import shutil
import sys

import torch

from rlpipe.algos.base import Algorithm
from rlpipe.console import say, warn
from rlpipe.errors import RlpipeError

# what inductor's CPU code needs: a C++ compiler ($CXX, else the first of these on PATH)
CXX_NAMES = ("g++", "c++", "clang++")


def compiler_problem(device: torch.device) -> str | None:
    """Why ``torch.compile`` cannot run on ``device`` here, or None."""
    import torch._dynamo

    if not torch._dynamo.is_dynamo_supported():
        return f"torch {torch.__version__} cannot compile on Python {sys.version.split()[0]}"
    if device.type == "cpu":
        names = [os.environ["CXX"]] if os.environ.get("CXX") else list(CXX_NAMES)
        if not any(shutil.which(name) for name in names):
            found = " or ".join(names)
            return f"torch.compile on CPU needs a C++ compiler and none was found ({found})"
    if device.type == "cuda":
        from torch.utils._triton import has_triton

        if not has_triton():
            return "torch.compile on CUDA needs Triton, which is not installed"
    return None


def wants_compile(setting: bool | str, device: torch.device) -> bool:
    """Whether to compile: ``false`` never; ``true`` where torch can, else an
    :class:`~rlpipe.errors.RlpipeError`; ``auto`` where torch can, else one warning line."""
    if setting is False:
        return False
    problem = compiler_problem(device)
    if problem is None:
        return True
    if setting is True:
        raise RlpipeError(f"compile=true, but {problem}: run with compile=false")
    warn(f"compile=auto: {problem}; running without compiling (compile=false says so)")
    return False


def compile_algorithm(algo: Algorithm, *, strict: bool = False) -> None:
    """``torch.compile`` the forward of each module ``algo.compiled`` names (``strict``: an
    algorithm with none is an error). The modules, their parameters and state dicts stay the
    same objects: checkpoints and resumes do not change."""
    if strict and not algo.compiled:
        raise RlpipeError(
            f"compile=true, but {type(algo).__name__} has no gradient step to compile: "
            "run with compile=false"
        )
    for name in algo.compiled:
        module = getattr(algo, name)
        module.forward = torch.compile(module.forward)
    if algo.compiled:
        say(
            f"rlpipe: torch.compile of {type(algo).__name__}'s {' and '.join(algo.compiled)} "
            "(compile=false to turn it off): the first updates wait for the compiler"
        )
