"""The run's progress bar."""

from __future__ import annotations

import math

from tqdm.auto import tqdm

from rlpipe.algos.base import Algorithm
from rlpipe.episodes import EvalResult


class ProgressBar:
    """A tqdm bar of frames towards ``total_frames`` (iterations towards the algorithm's own
    budget when only that binds), with tqdm's frame rate and ETA, and the latest training
    episode's return and the last evaluation as its postfix.

    While it counts frames and the algorithm also has a budget of iterations, its total (and so
    its ETA) is where that budget will end at the frames per iteration so far, if that comes
    before ``total_frames``. A last whole batch past ``total_frames`` raises the total to the
    frames run, so the bar ends at 100% rather than losing its total.
    """

    def __init__(self, algo: Algorithm, total_frames: int | None, *, enabled: bool) -> None:
        self.algo, self.total_frames = algo, total_frames
        self.shown = self.count()  # what the bar has counted
        by_frames = total_frames is not None
        self.bar = tqdm(
            total=total_frames if by_frames else algo.budget,
            initial=self.shown,
            unit="frame" if by_frames else "it",
            unit_scale=True,
            disable=not enabled,
            dynamic_ncols=True,
            mininterval=0.5,
        )

    def count(self) -> int:
        """What the bar counts: frames, or iterations when only the algorithm's budget binds."""
        return self.algo.frames if self.total_frames is not None else self.algo.iterations

    def advance(self) -> None:
        """Catch up with the algorithm after an iteration; follow the binding budget."""
        algo = self.algo
        if self.total_frames is not None and algo.budget is not None and algo.iterations > 0:
            projected = math.ceil(algo.frames / algo.iterations * algo.budget)
            self.bar.total = min(self.total_frames, max(projected, algo.frames))
        count = self.count()
        if self.bar.total is not None and count > self.bar.total:
            self.bar.total = count
        self.bar.update(count - self.shown)
        self.shown = count

    def show(self, last_return: float, last_eval: EvalResult | None) -> None:
        """Set the postfix: the latest training episode's return and the last evaluation, once
        there are any (the bar shows the frame rate itself)."""
        self.bar.set_postfix(postfix(last_return, last_eval), refresh=False)

    def close(self) -> None:
        self.bar.close()

    def __enter__(self) -> ProgressBar:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def postfix(last_return: float, last_eval: EvalResult | None) -> dict[str, str]:
    """The bar's postfix fields."""
    fields = {} if math.isnan(last_return) else {"ep_return": f"{last_return:.1f}"}
    if last_eval is not None:
        fields["eval"] = f"{last_eval.mean:.1f}±{last_eval.std:.1f}"
    return fields
