"""Which engine steps an env config's copies: ``env.backend`` (auto, gymnasium or envpool)
resolved to the one a run uses, with the line that announces it. Imports no torch."""

from __future__ import annotations

import functools
from dataclasses import replace

from rlpipe.config import EnvConfig
from rlpipe.errors import RlpipeError

__all__ = [
    "ENVPOOL_DIFFERS",
    "ENVPOOL_IDS",
    "ENVPOOL_INSTALL",
    "backend_of",
    "envpool_task",
    "envpool_version",
    "resolve_backend",
]

ENVPOOL_INSTALL = 'pip install "envpool>=1.2.5" (Linux x86_64, Python >= 3.11)'
MIN_ENVPOOL = (1, 2, 5)  # partial steps (env_id=) and per-env seeds, as this backend uses them
# gymnasium ids whose EnvPool twins were checked against gymnasium's: the same spaces and time
# limits, episode returns the same in distribution (docs/api.md "Environments")
ENVPOOL_IDS = (
    "Acrobot-v1",
    "BipedalWalker-v3",
    "BipedalWalkerHardcore-v3",
    "CartPole-v0",
    "CartPole-v1",
    "LunarLander-v3",
    "LunarLanderContinuous-v3",
    "MountainCar-v0",
    "MountainCarContinuous-v0",
    "Pendulum-v1",
)
# ids whose EnvPool twins step differently from gymnasium's (tests/test_envpool.py compares one
# step from the same state): auto takes gymnasium for them, env.backend=envpool says so
ENVPOOL_DIFFERS = {
    "Pendulum-v1": "EnvPool's Pendulum-v1 moves the angle before clipping the speed at 8 (gym's v0 "
    "order), so its episodes differ from gymnasium's wherever the pendulum spins that fast",
}
# gymnasium kwargs that EnvPool honours by building another id (it takes no kwargs)
ENVPOOL_VARIANTS = {
    ("BipedalWalker-v3", "hardcore"): "BipedalWalkerHardcore-v3",
    ("LunarLander-v3", "continuous"): "LunarLanderContinuous-v3",
}


@functools.cache
def envpool_version() -> str | None:
    """The installed EnvPool's version if it is recent enough to serve, else None."""
    try:
        import envpool
    except (ImportError, OSError):  # not installed, or its shared libraries do not load here
        return None
    version = envpool.__version__
    parts = tuple(int(p) if p.isdigit() else 0 for p in version.split(".")[:3])
    return version if parts >= MIN_ENVPOOL else None


def envpool_task(cfg: EnvConfig) -> str | None:
    """EnvPool's id for ``cfg`` (its own, or the variant its ``env.kwargs`` select), or None
    when EnvPool cannot honour the kwargs."""
    task = cfg.id
    for key, value in cfg.kwargs.items():
        variant = ENVPOOL_VARIANTS.get((cfg.id, key))
        if variant is None or not isinstance(value, bool):
            return None
        task = variant if value else task
    return task


def _why_not_envpool(cfg: EnvConfig) -> str | None:
    """Why EnvPool cannot run ``cfg`` (None: it can)."""
    if cfg.id not in ENVPOOL_IDS:
        return (
            f"EnvPool runs only the ids rlpipe checked against gymnasium's "
            f"({', '.join(ENVPOOL_IDS)}), not {cfg.id!r}"
        )
    if envpool_task(cfg) is None:
        takes = [f"{key}=true|false" for env_id, key in ENVPOOL_VARIANTS if env_id == cfg.id]
        return (
            f"EnvPool cannot honour env.kwargs {cfg.kwargs}: for {cfg.id} it takes "
            f"{' or '.join(takes) or 'none'}"
        )
    if envpool_version() is None:
        version = ".".join(map(str, MIN_ENVPOOL))
        return f"EnvPool >= {version} is not installed (install it: {ENVPOOL_INSTALL})"
    return None


def backend_of(cfg: EnvConfig, render_mode: str | None = None) -> str:
    """The backend that builds ``cfg``'s envs: ``gymnasium`` or ``envpool``.

    ``auto`` is EnvPool where it is installed and runs the id with these kwargs as gymnasium
    does (not the ids of :data:`ENVPOOL_DIFFERS`), else gymnasium; ``envpool`` where it cannot
    is one line naming why. Rendering (``render_mode``: videos, ``render=human``) is always
    gymnasium's.
    """
    if render_mode is not None or cfg.backend == "gymnasium":
        return "gymnasium"
    why = _why_not_envpool(cfg)
    if why is not None and cfg.backend == "envpool":
        raise RlpipeError(f"env.backend=envpool: {why}; or set env.backend=gymnasium (or auto)")
    if cfg.backend == "auto" and cfg.id in ENVPOOL_DIFFERS:
        return "gymnasium"
    return "gymnasium" if why is not None else "envpool"


def resolve_backend(
    cfg: EnvConfig, recorded: str | None = None, copies: int | None = None
) -> tuple[EnvConfig, str]:
    """``cfg`` with ``backend`` set to the one a run uses, and the line that announces it.

    ``recorded``: the backend the run dir being continued recorded; ``auto`` takes it, so a
    resume rebuilds the same envs (a recorded ``envpool`` must then be available).
    ``copies``: how many env copies the run steps at once (``AlgoConfig.stepped_copies``);
    ``auto`` takes gymnasium for one: every call to EnvPool hands its work to a worker thread
    and waits for it, which costs more than one copy's step in this process (the one-copy SAC
    presets trained at 0.89-0.96x gymnasium's speed on EnvPool alone on an Intel Xeon VM,
    0.97-0.99x on an AMD EPYC VM: benchmarks/env_backends.py).
    """
    if cfg.backend == "auto" and recorded in ("gymnasium", "envpool"):
        chosen = replace(cfg, backend=recorded)
        backend_of(chosen)  # EnvPool gone since: one line saying so
        return chosen, f"env backend {recorded} (auto: the one the run dir recorded)"
    backend = backend_of(cfg)
    if cfg.backend == "auto" and backend == "envpool" and copies == 1:
        why = "auto: one env copy steps faster in gymnasium than through EnvPool's worker thread"
        return replace(cfg, backend="gymnasium"), (
            f"env backend gymnasium ({why}; env.backend=envpool to use it anyway)"
        )
    if cfg.backend != "auto":  # typed, or set by tuned settings: the line says how to undo it
        why = f"env.backend={cfg.backend}; env.backend=auto lets rlpipe choose"
        if backend == "envpool" and cfg.id in ENVPOOL_DIFFERS:
            why += f"; warning: {ENVPOOL_DIFFERS[cfg.id]}"
    elif cfg.id in ENVPOOL_DIFFERS and _why_not_envpool(cfg) is None:
        why = f"auto: {ENVPOOL_DIFFERS[cfg.id]}; env.backend=envpool to use it anyway"
    elif backend == "envpool":
        task = envpool_task(cfg)  # the variant env.kwargs select: BipedalWalkerHardcore-v3
        why = f"auto: EnvPool {envpool_version()} runs {task}; env.backend=gymnasium to change"
    elif cfg.id not in ENVPOOL_IDS:  # the usual case for an env of one's own: said briefly
        why = f"auto: EnvPool does not run {cfg.id}"
    else:
        why = f"auto: {_why_not_envpool(cfg)}"
    return replace(cfg, backend=backend), f"env backend {backend} ({why})"
