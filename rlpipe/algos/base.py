"""The small interface every algorithm exposes to the shared runner."""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

# Scalars are averaged over the runner's logging window; lists hold one value per event
# (e.g. one return per finished training episode) and are logged row by row.
Metrics = dict[str, float | list[float]]


@runtime_checkable
class Algorithm(Protocol):
    """What the runner needs: a greedy policy, a frame counter, one iteration, and state."""

    policy: TensorDictModuleBase  # deterministic/greedy policy used by evaluation and video
    frames: int  # environment frames consumed so far
    iterations: int  # train_step calls so far
    budget: int | None  # the algorithm's own budget in iterations (REINFORCE epochs, ARS
    # iterations); None: none, the run's total_frames decides

    def train_step(self) -> Metrics:
        """Run one iteration (collect and update); advance ``frames``; return metrics."""
        ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...

    def close(self) -> None:
        """Release the env the algorithm was given and any workers or collectors it started."""
        ...


def episode_metrics(batch: TensorDictBase) -> Metrics:
    """Returns and lengths of the episodes that ended inside a collected batch."""
    done = batch["next", "done"]
    if not bool(done.any()):
        return {}
    return {
        "train/episode_return": batch["next", "episode_reward"][done].tolist(),
        "train/episode_length": batch["next", "step_count"][done].float().tolist(),
    }
