"""ARS rollout workers against one process, for any policy: seconds per iteration.

For each policy network (the notebook's linear map, which runs as NumPy; an MLP with LayerNorm,
NumPy since LayerNorm has a NumPy form; a custom ``nn.Module``, which runs through
``torch.vmap`` every step) and env, ``ARSSearch`` runs ``--iterations`` iterations with
``workers=1`` and with ``workers=2``, and, for reference, with ``workers=2`` and the chunking
every policy had before (eight chunks per worker). Per run: the one-off cost (start-up, i.e.
worker processes and env copies, plus the first iteration, which runs cold in any process) and
the mean seconds of the iterations after it (those that time the workers against this process
included); each cell is the median over ``--repeats`` interleaved rounds. Ratio: seconds per
iteration with 2 workers ÷ with 1 (below 1: the workers are faster). ``--backend``: the envs'
(``auto``, the default, is EnvPool where it runs the id; the table says which ran).

    python benchmarks/ars_workers.py --iterations 60 --repeats 3 --append BENCHMARKS.md
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from functools import partial
from statistics import median

import torch
from common import load_span, parser, publish_section, script, section_head, table
from torch import nn

from rlpipe import ARSConfig, ARSSearch, EnvConfig, make_env
from rlpipe.algos.ars import make_ars_policy, pool
from rlpipe.envs.backends import backend_of


class LayerNormMLP(nn.Module):
    """Linear -> LayerNorm -> tanh -> linear (examples/ars_layernorm.py's network)."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(in_features, 16), nn.LayerNorm(16), nn.Tanh(), nn.Linear(16, out_features)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class Custom(nn.Module):
    """A network with its own forward (no NumPy form): a gated linear map."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.linear = nn.Linear(in_features, out_features)
        self.gate = nn.Linear(in_features, out_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.linear(x) * torch.sigmoid(self.gate(x))


NETWORKS: dict[str, Callable[[int, int], nn.Module] | None] = {
    "linear (NumPy)": None,
    "Sequential with LayerNorm (NumPy)": lambda n_in, n_out: LayerNormMLP(n_in, n_out).net,
    "custom nn.Module (torch.vmap)": Custom,
}
SETUPS = {
    "1 worker": (1, None),
    "2 workers": (2, None),
    "2 workers, 8 chunks each (before)": (2, 8),
}


def seconds_per_iteration(
    env_id: str, network: str, workers: int, chunks: int | None, args
) -> tuple[float, float]:
    """Seconds of start-up plus the first ARS iteration (16 directions), and the mean seconds
    of the iterations after it."""
    env_cfg = EnvConfig(id=env_id, backend=args.backend)
    probe = make_env(env_cfg)
    size, outputs = probe.observation_spec["observation"].shape[-1], None
    spec = probe.action_spec_unbatched
    outputs = spec.space.n if hasattr(spec.space, "n") else spec.shape[0]
    probe.close()
    build = NETWORKS[network]
    torch.manual_seed(0)
    policy, normalizer = make_ars_policy(
        make_env(env_cfg), ARSConfig(), None if build is None else build(size, outputs)
    )
    saved = pool.chunks_per_worker
    if chunks is not None:  # the chunking of every policy before: small chunks whatever the cost
        pool.chunks_per_worker = lambda *_args: chunks
    try:
        search = ARSSearch(
            policy,
            partial(make_env, env_cfg, vectorization="sync"),
            num_directions=16,
            max_steps=args.max_steps,
            normalizer=normalizer,
            workers=workers,
        )
        start = time.perf_counter()
        search.step()  # starts the workers first
        first = time.perf_counter() - start
        start = time.perf_counter()
        for _ in range(args.iterations - 1):
            search.step()
        rest = (time.perf_counter() - start) / (args.iterations - 1)
        search.close()
    finally:
        pool.chunks_per_worker = saved
    return first, rest


def main() -> None:
    p = parser(__doc__.splitlines()[0])
    p.add_argument("--envs", nargs="+", default=["Pendulum-v1", "CartPole-v1"])
    p.add_argument("--iterations", type=int, default=60)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--max-steps", type=int, default=1000)
    p.add_argument("--backend", choices=["auto", "gymnasium", "envpool"], default="auto")
    args = p.parse_args()
    cells: dict[tuple[str, str, str], list[tuple[float, float]]] = {}
    load_before = os.getloadavg()
    for _ in range(args.repeats):  # interleaved: a burst of load moves one round, not a column
        for env_id in args.envs:
            for network in NETWORKS:
                for setup, (workers, chunks) in SETUPS.items():
                    key = (env_id, network, setup)
                    seconds = seconds_per_iteration(env_id, network, workers, chunks, args)
                    cells.setdefault(key, []).append(seconds)
    rows = []
    for env_id in args.envs:
        for network in NETWORKS:
            runs = [cells[env_id, network, setup] for setup in SETUPS]
            first_one, first_two, _ = (median(first for first, _ in cell) for cell in runs)
            one, two, before = (median(rest for _, rest in cell) for cell in runs)
            rows.append(
                [
                    env_id,
                    backend_of(EnvConfig(id=env_id, backend=args.backend)),
                    network,
                    f"{first_one:.3f}",
                    f"{first_two:.3f}",
                    f"{one:.3f}",
                    f"{two:.3f}",
                    f"{before:.3f}",
                    f"{two / one:.2f}×",
                    f"{before / one:.2f}×",
                ]
            )
    head = section_head(
        "ARS workers vs one process, by policy",
        ["torch", "torchrl", "gymnasium", "envpool"],
        load_span(load_before, os.getloadavg()),
        f"{args.iterations} iterations, median of {args.repeats} interleaved round(s)",
    )
    report = "\n".join(
        [
            *head,
            table(
                [
                    "env",
                    "env backend",
                    "policy network",
                    "start-up + 1st iteration s, 1 worker",
                    "start-up + 1st iteration s, 2 workers",
                    "s/iter, 1 worker",
                    "s/iter, 2 workers",
                    "s/iter, 2 workers, 8 chunks each (before)",
                    "2 ÷ 1",
                    "before ÷ 1",
                ],
                rows,
            ),
        ]
    )
    publish_section(report, args.append)


if __name__ == "__main__":
    script(main)
