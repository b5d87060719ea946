"""The performance-profile figure of benchmarks/presets.py: runs at or above τ × the target.

rliable's score distribution over all presets: for each τ, the fraction of a preset's runs whose
normalised final eval ((score - random) / (target - random): 0 is a random policy, 1 the target)
is ≥ τ, averaged over presets, with its 95% stratified-bootstrap band (seeds resampled within
each preset), one curve per library.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rlpipe.stats import score_profile, score_profile_band

TAUS = np.linspace(0.0, 1.25, 126)


def profile_figure(series: dict[str, list[np.ndarray]], path: Path, seeds: str) -> None:
    """Draw each label's profile (its normalised finals, one array per preset) to ``path``."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 4.2))
    ax = fig.subplots()
    for (label, groups), color in zip(series.items(), ("tab:blue", "tab:orange")):
        low, high = score_profile_band(groups, TAUS)
        ax.fill_between(TAUS, low, high, color=color, alpha=0.25, linewidth=0)
        profile = score_profile(groups, TAUS)
        ax.plot(TAUS, profile, color=color, label=f"{label} ({len(groups)} preset(s))")
    ax.axvline(1.0, color="grey", linestyle="--", linewidth=1)
    ax.text(1.0, 0.03, " the target", color="grey", fontsize=8)
    ax.set_xlim(TAUS[0], TAUS[-1])
    ax.set_ylim(0.0, 1.02)
    ax.set_xlabel("τ: normalised final greedy eval ((score − random) / (target − random))")
    ax.set_ylabel("fraction of runs with score ≥ τ")
    ax.set_title(f"Performance profile of the tuned presets, {seeds}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
