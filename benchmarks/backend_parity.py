"""Backend parity: trained policies evaluated on gymnasium and on EnvPool, 100 episodes each.

For every run dir given, ``python -m rlpipe.evaluate run_dir=<run> episodes=N backend=<b>`` on
each backend (the same evaluation seed), then one row: the mean return on each with its 95%
bootstrap CI, the difference of the means with its CI, and whether each mean lies inside the
other's CI. Evaluations already written
(``<run>/evaluation/parity-<backend>-<episodes>-seed<seed>.json``) are read back, so a call
with the same run dirs, episodes and seed continues.

    python benchmarks/backend_parity.py RUN [RUN ...] --append BENCHMARKS.md
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from common import evaluated, machine, publish_section, runs_parser, script, table

from rlpipe.rundir import RunDir

BACKENDS = ("gymnasium", "envpool")


def evaluation(run: Path, backend: str, episodes: int, seed: int) -> list[float]:
    """The returns of ``episodes`` greedy episodes of ``run``'s newest checkpoint on ``backend``."""
    out = run / "evaluation" / f"parity-{backend}-{episodes}-seed{seed}.json"  # one per call
    keys = [f"run_dir={run}", f"episodes={episodes}", f"backend={backend}", f"seed={seed}"]
    return evaluated(out, *keys)["returns"]


def ci(values: np.ndarray, rng: np.random.Generator, draws: int = 10_000) -> tuple[float, float]:
    """The 95% percentile-bootstrap CI of the mean of ``values``."""
    means = rng.choice(values, (draws, len(values))).mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def row(run: Path, episodes: int, seed: int) -> list[str]:
    """The run's parity row."""
    cfg = RunDir(run).read_config()
    rng = np.random.default_rng(0)
    returns = {b: np.asarray(evaluation(run, b, episodes, seed)) for b in BACKENDS}
    bounds = {b: ci(r, rng) for b, r in returns.items()}
    gym, pool = (returns[b].mean() for b in BACKENDS)
    diffs = [
        rng.choice(returns["envpool"], episodes).mean()
        - rng.choice(returns["gymnasium"], episodes).mean()
        for _ in range(10_000)
    ]
    inside = bounds["envpool"][0] <= gym <= bounds["envpool"][1]
    inside = inside and bounds["gymnasium"][0] <= pool <= bounds["gymnasium"][1]
    return [
        f"{cfg.algo.name} on {cfg.env.id}",
        cfg.env.backend,
        f"{gym:.1f} [{bounds['gymnasium'][0]:.1f}, {bounds['gymnasium'][1]:.1f}]",
        f"{pool:.1f} [{bounds['envpool'][0]:.1f}, {bounds['envpool'][1]:.1f}]",
        f"{pool - gym:+.1f} [{np.percentile(diffs, 2.5):+.1f}, {np.percentile(diffs, 97.5):+.1f}]",
        "yes" if inside else "no",
    ]


def main() -> None:
    args = runs_parser(__doc__.splitlines()[0]).parse_args()
    rows = [row(run.resolve(), args.episodes, args.seed) for run in args.runs]
    headers = ["policy", "trained on", "gymnasium mean [95% CI]", "EnvPool mean [95% CI]"]
    headers += ["EnvPool − gymnasium [95% CI]", "each mean inside the other's CI"]
    text = "\n".join(
        [
            "## Backend parity (benchmarks/backend_parity.py)",
            "",
            f"- machine: {machine(['torch', 'torchrl', 'gymnasium', 'envpool'])}",
            f"- command: `python benchmarks/backend_parity.py <runs> --episodes {args.episodes}"
            f" --seed {args.seed}`; 1-min load average at the end: {os.getloadavg()[0]:.2f}",
            f"- each trained run's newest checkpoint, {args.episodes} greedy episodes per backend "
            "(`python -m rlpipe.evaluate ... backend=<b>`); CIs: percentile bootstrap, 10,000 "
            "draws",
            "",
            table(headers, rows),
        ]
    )
    publish_section(text, args.append)


if __name__ == "__main__":
    script(main)
