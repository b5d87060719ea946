"""A run's budget: ``total_frames``, the algorithm's own (epochs, iterations), when it is spent,
whether it ended before ``total_frames``, and whether any evaluation falls inside it."""

from __future__ import annotations

from rlpipe.algos.base import Algorithm
from rlpipe.errors import check


def check_budget(algo: Algorithm, total_frames: int | None) -> None:
    """A run needs ``total_frames`` unless the algorithm has a budget of its own."""
    check(
        total_frames is not None or algo.budget is not None,
        f"total_frames=null, but {type(algo).__name__} has no budget of its own "
        "(epochs, iterations): set total_frames=N",
    )


def spent(algo: Algorithm, total_frames: int | None) -> bool:
    """Whether the frame budget or the algorithm's own budget is spent."""
    return (total_frames is not None and algo.frames >= total_frames) or (
        algo.budget is not None and algo.iterations >= algo.budget
    )


def ended_short(algo: Algorithm, total_frames: int | None) -> str | None:
    """The note for a run whose own budget (epochs, iterations) ended it before
    ``total_frames``, or None."""
    if total_frames is None or algo.frames >= total_frames or not spent(algo, None):
        return None
    key = algo.budget_key or "the algorithm's budget"
    return (
        f"the run ended at {key}={algo.budget:,} after {algo.frames:,} of total_frames="
        f"{total_frames:,} frames: raise {key} to train to total_frames"
    )


def no_evaluation_inside(algo: Algorithm, total_frames: int | None, eval_every: int) -> str | None:
    """The warning for a run starting whose first evaluation lies past the most frames its
    budget can take (it evaluates only at the end), or None."""
    bounds = [b for b in (total_frames, algo.budget_frames) if b is not None]
    if algo.frames or eval_every <= 0 or not bounds or eval_every < min(bounds):
        return None
    return (
        f"eval_every={eval_every:,} frames, and this run ends within {min(bounds):,} frames: "
        "it evaluates only at the end; set eval_every=<frames> to evaluate along the way"
    )
