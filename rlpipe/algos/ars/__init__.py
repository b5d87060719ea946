"""Augmented random search (ARS) for any TensorDictModule policy, as an rlpipe algorithm or alone.

The search evolves the policy's flat parameter vector θ: each iteration samples ``N`` Gaussian
directions δ, rolls out the ``2N`` perturbed policies θ ± ν·δ as one population (one batched
policy call per step over a population dimension), keeps the ``b`` directions with the best
``max(r+, r-)`` and moves θ by ``α / (b·σ) · Σ (r+ - r-)·δ``, σ being the std of the selected
returns (Mania et al., 2018). A :class:`rlpipe.normalizer.Normalizer` inside the policy (ARS V2)
standardises observations with running statistics that are updated after each iteration and
frozen in between.

- :mod:`~rlpipe.algos.ars.algorithm`: :class:`ARS` and its config, the runner's algorithm;
- :mod:`~rlpipe.algos.ars.search`: :class:`ARSSearch`, the loop, and the update rule;
- :mod:`~rlpipe.algos.ars.rollout`: one episode per member on the gymnasium copies (its
  ``rollout`` function is not re-exported here, where it would hide the module);
- :mod:`~rlpipe.algos.ars.population`: the policy as NumPy functions of a population;
- :mod:`~rlpipe.algos.ars.backends`: this process, worker processes or Ray actors (a worker
  process that dies raises :class:`WorkerDied`).
"""

from rlpipe.algos.ars.algorithm import ARS, ARSConfig, RayConfig, make_ars_policy
from rlpipe.algos.ars.backends import BACKENDS, WorkerDied
from rlpipe.algos.ars.population import PopulationPolicy, batched_call, numpy_layer
from rlpipe.algos.ars.rollout import RolloutResult
from rlpipe.algos.ars.search import ARSSearch, ars_update, centered_ranks

__all__ = [
    "ARS",
    "ARSConfig",
    "ARSSearch",
    "BACKENDS",
    "PopulationPolicy",
    "RayConfig",
    "RolloutResult",
    "WorkerDied",
    "ars_update",
    "batched_call",
    "centered_ranks",
    "make_ars_policy",
    "numpy_layer",
]
