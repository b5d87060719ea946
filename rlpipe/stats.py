"""Aggregates over seeds: the mean, the interquartile mean (IQM), performance profiles and their
95% (stratified) percentile-bootstrap confidence intervals, rliable's protocol (the curves of
``python -m rlpipe.plot``, a sweep's per-group rows, ``benchmarks/presets.py``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np


def mean(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """The mean of ``values`` along ``axis``."""
    return values.mean(axis=axis)


def iqm(values: np.ndarray, axis: int = 0) -> np.ndarray:
    """Interquartile mean: the mean of the middle 50% of ``values`` along ``axis`` (a quarter
    of the values, rounded down, cut from each end: scipy's ``trim_mean(values, 0.25)``)."""
    import numpy as np

    ordered = np.sort(values, axis=axis)
    n = ordered.shape[axis]
    cut = n // 4
    return np.take(ordered, range(cut, n - cut), axis=axis).mean(axis=axis)


AGGREGATES = {"mean": mean, "iqm": iqm}


def resample(groups: Sequence[np.ndarray], samples: int = 2000, seed: int = 0) -> list[np.ndarray]:
    """Stratified bootstrap draws: each group's runs (rows) drawn with replacement within that
    group, ``samples`` times; one array per group, shaped (samples, runs of the group, ...)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return [g[rng.integers(0, len(g), size=(samples, len(g)))] for g in groups]


def percentile_band(stats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The 95% percentile interval of bootstrap statistics (draws along axis 0)."""
    import numpy as np

    return np.percentile(stats, 2.5, axis=0), np.percentile(stats, 97.5, axis=0)


def bootstrap_band(
    values: np.ndarray, aggregate: str, samples: int = 2000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """95% percentile-bootstrap interval of ``aggregate`` over runs (rows of ``values``)."""
    (draws,) = resample([values], samples, seed)
    return percentile_band(AGGREGATES[aggregate](draws, axis=1))


def pooled_iqm(groups: Sequence[np.ndarray]) -> float:
    """The IQM of every run of every group, pooled (rliable's aggregate over tasks)."""
    import numpy as np

    return float(iqm(np.concatenate(groups)))


def pooled_iqm_band(
    groups: Sequence[np.ndarray], samples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """95% stratified-bootstrap interval of :func:`pooled_iqm` (runs resampled within groups;
    one group: the plain bootstrap over its runs)."""
    import numpy as np

    low, high = percentile_band(iqm(np.concatenate(resample(groups, samples, seed), axis=1), 1))
    return float(low), float(high)


def score_profile(groups: Sequence[np.ndarray], taus: np.ndarray) -> np.ndarray:
    """Performance profile: for each τ, the fraction of a group's runs scoring ≥ τ, averaged
    over groups (each group, e.g. a task, weighs the same however many runs it has)."""
    import numpy as np

    return np.mean([(np.asarray(g)[..., None] >= taus).mean(axis=-2) for g in groups], axis=0)


def score_profile_band(
    groups: Sequence[np.ndarray], taus: np.ndarray, samples: int = 2000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """95% stratified-bootstrap band of :func:`score_profile` at each τ."""
    return percentile_band(score_profile(resample(groups, samples, seed), taus))
