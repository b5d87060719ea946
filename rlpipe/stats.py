"""Aggregates over seeds: the mean, the interquartile mean (IQM) and their 95% percentile-bootstrap
confidence intervals (the curves of ``python -m rlpipe.plot``, a sweep's per-group rows)."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np


def mean(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """The mean of ``values`` along ``axis``."""
    return values.mean(axis=axis)


def iqm(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50% of ``values`` along ``axis``."""
    import numpy as np

    ordered = np.sort(values, axis=axis)
    n = ordered.shape[axis]
    cut = n // 4
    return np.take(ordered, range(cut, n - cut), axis=axis).mean(axis=axis)


AGGREGATES = {"mean": mean, "iqm": iqm}


def bootstrap_band(
    values: np.ndarray, aggregate: str, samples: int = 2000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """95% percentile-bootstrap interval of ``aggregate`` over runs (rows of ``values``)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(values), size=(samples, len(values)))
    stats = AGGREGATES[aggregate](values[picks], axis=1)  # (samples, ...)
    return np.percentile(stats, 2.5, axis=0), np.percentile(stats, 97.5, axis=0)
