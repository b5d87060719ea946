"""Model-based RL: the algorithm (:mod:`~rlpipe.algos.mbrl.algorithm`) and the learned world
model and planner it plans with (:mod:`~rlpipe.algos.mbrl.planning`)."""

from rlpipe.algos.mbrl.algorithm import MBRL, MODEL_LOSS, MBRLConfig, MPCPolicy, action_coder
from rlpipe.algos.mbrl.planning import ActionCoder, EnsembleMLP, Planner, WorldModel

__all__ = [
    "MBRL",
    "MODEL_LOSS",
    "ActionCoder",
    "EnsembleMLP",
    "MBRLConfig",
    "MPCPolicy",
    "Planner",
    "WorldModel",
    "action_coder",
]
