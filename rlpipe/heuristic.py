"""Baseline policies for ``python -m rlpipe.evaluate policy=random|naive|heuristic``.

- ``random``: uniform actions, any env.
- ``naive``: the agent-templates notebook's hand-written BipedalWalker controller. While a knee
  folds fast (joint speed below -0.5) it eases that leg's hip and knee back; otherwise, and
  whenever both feet are on the ground, it tries a uniformly random torque. It never walks
  (about -97 over 100 episodes, as random actions): a floor to beat.
- ``heuristic``: a hand-written walking gait for BipedalWalker (:class:`WalkerGait`), a
  three-phase state machine per env copy with PD control of the joints. It walks forward on
  most episodes (its 100-episode mean is in BENCHMARKS.md).
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs import EnvBase

from rlpipe.envs import is_discrete, observation_of
from rlpipe.errors import check

# BipedalWalker-v3 observation layout: hull angle, its angular speed, x and y speed, then per
# leg: hip angle, hip speed, knee angle + 1, knee speed, foot contact (then 10 lidar readings)
HULL_ANGLE, HULL_SPEED, SPEED_X, SPEED_Y = 0, 1, 2, 3
HIP, HIP_SPEED, KNEE, KNEE_SPEED, CONTACT = (4, 9), (5, 10), (6, 11), (7, 12), (8, 13)

# the notebook's controller
FOLD_SPEED = -0.5
EASE_BACK = (-0.05, -0.2)  # hip and knee torque for a folding leg


class RandomActions(nn.Module):
    """Uniform samples from an action spec, one per observation in the batch (an observation
    has ``observation_dims`` dimensions of its own: 1 for a vector, 3 for an image)."""

    def __init__(self, spec: TensorSpec, observation_dims: int = 1) -> None:
        super().__init__()
        self.spec, self.observation_dims = spec, observation_dims

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.spec.rand(observation.shape[: observation.ndim - self.observation_dims])


class NotebookWalker(nn.Module):
    """The notebook's naive BipedalWalker controller, batched: observations (..., 24) -> torques."""

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        action = torch.rand(*observation.shape[:-1], 4) * 2 - 1
        ease = torch.tensor(EASE_BACK)
        contact_1, contact_2 = (observation[..., c] == 1 for c in CONTACT)
        both_down = contact_1 & contact_2
        fold_1 = ~both_down & (observation[..., KNEE_SPEED[0]] < FOLD_SPEED)
        fold_2 = ~both_down & ~fold_1 & (observation[..., KNEE_SPEED[1]] < FOLD_SPEED)
        for fold, leg in ((fold_1, slice(0, 2)), (fold_2, slice(2, 4))):
            eased = torch.zeros(4)
            eased[leg] = ease
            action = torch.where(fold.unsqueeze(-1), eased, action)
        return action


# the gait's phases: the swing leg comes forward, is put down ahead, then the support leg
# pushes off and the legs swap roles
SWING, PLACE, PUSH = 0, 1, 2
GAIT = dict(
    # joint angle targets (radians; knees: 0 is straight, negative bends)
    swing_hip=0.73,  # the swing leg's hip while it comes forward...
    swing_knee=-0.46,  # ...with its knee bent to clear the ground
    reach=0.672,  # SWING -> PLACE once the swing hip is this far forward
    place_hip=0.485,  # where the swing foot is put down
    support_hip=-0.343,  # the support leg's hip (it drives the hull forward over the foot)
    support_knee=-0.412,
    push_hip=-0.393,  # the old support leg during push-off
    push_knee=-0.1,
    push_until=-0.934,  # PUSH -> SWING once the old support knee bends past this (or lifts)
    # PD gains (actions are torques in [-1, 1]; speeds are the observation's scaled ones)
    kp_hip=2.694,
    kd_hip=0.572,
    kp_knee=3.595,
    kd_knee=0.673,
    k_hull=0.135,  # the hips of legs on the ground lean against the hull's tilt...
    kd_hull=2.159,  # ...and against its angular speed
    k_vy=8.278,  # the knees damp the hull's vertical speed
    place_v=-0.365,  # the swing leg's aim: + this × forward speed...
    place_a=0.883,  # ...+ this × hull angle
)


class WalkerGait(nn.Module):
    """A hand-written BipedalWalker gait: per env copy, a state machine of three phases.

    SWING: the support leg stands nearly straight and drives the hull forward while the other
    leg swings forward, knee bent; PLACE: once it is far enough forward, it straightens and
    reaches down; PUSH: once it touches the ground, the old support leg pushes off, and when
    that leg has bent (or left the ground) the two swap roles. Each joint follows its phase's
    target angle with a PD law; the hips of the legs on the ground also lean against the hull's
    rotation, the knees damp its vertical speed, and the swing leg's aim moves with the hull's
    speed and tilt. The phase of each copy lives in this module
    and starts again at every episode's first step (``step_count`` 0); it is deterministic. The
    structure is written by hand; its constants (:data:`GAIT`) were set by a short random search
    on the env's return, on episode seeds apart from the evaluation's.
    """

    def __init__(self, gait: dict[str, float] | None = None) -> None:
        super().__init__()
        self.gait = {**GAIT, **(gait or {})}
        self.phase = torch.zeros(0, dtype=torch.long)
        self.support = torch.zeros(0, dtype=torch.long)  # which leg (0 or 1) supports

    def forward(self, observation: torch.Tensor, step_count: torch.Tensor) -> torch.Tensor:
        g, shape = self.gait, observation.shape[:-1]
        obs = observation.reshape(-1, observation.shape[-1]).float()
        if self.phase.shape[0] != obs.shape[0]:
            self.phase = torch.zeros(obs.shape[0], dtype=torch.long, device=obs.device)
            self.support = torch.zeros_like(self.phase)
        start = step_count.reshape(-1) == 0
        self.phase[start], self.support[start] = SWING, 0
        hip, knee = obs[:, list(HIP)], obs[:, list(KNEE)] - 1  # (N, 2): leg 0, leg 1
        hip_speed, knee_speed = obs[:, list(HIP_SPEED)], obs[:, list(KNEE_SPEED)]
        contact = obs[:, list(CONTACT)] > 0.5
        rows = torch.arange(obs.shape[0], device=obs.device)
        support, swing = self.support, 1 - self.support
        # the phase changes that take effect at once
        reached = (self.phase == SWING) & (hip[rows, swing] > g["reach"])
        self.phase[reached] = PLACE
        landed = (self.phase == PLACE) & contact[rows, swing]
        self.phase[landed] = PUSH
        # push-off ends (the legs swap) once the old support knee has bent or the foot lifted;
        # the swap takes effect after this step's targets
        pushed = (self.phase == PUSH) & (
            (knee[rows, support] < g["push_until"]) | ~contact[rows, support]
        )
        # targets: (support hip, support knee, swing hip, swing knee) of each phase
        table = obs.new_tensor(
            [
                [g["support_hip"], g["support_knee"], g["swing_hip"], g["swing_knee"]],
                [g["support_hip"], g["support_knee"], g["place_hip"], g["support_knee"]],
                [g["push_hip"], g["push_knee"], g["support_hip"], g["support_knee"]],
            ]
        )[self.phase]
        is_support = torch.arange(2, device=obs.device) == support.unsqueeze(-1)  # (N, 2)
        # balance: until it lands (and on the step its push-off ends), the swing leg's aim moves
        # with the hull's forward speed (back, the faster) and its tilt (ahead, leaning back)
        aim = g["place_v"] * obs[:, SPEED_X] + g["place_a"] * obs[:, HULL_ANGLE]
        swing_target = table[:, 2] + torch.where((self.phase == PUSH) & ~pushed, 0.0, aim)
        hip_target = torch.where(is_support, table[:, :1], swing_target[:, None])
        knee_target = torch.where(is_support, table[:, 1:2], table[:, 3:4])
        hip_torque = g["kp_hip"] * (hip_target - hip) - g["kd_hip"] * hip_speed
        lean = g["k_hull"] * obs[:, HULL_ANGLE] + g["kd_hull"] * obs[:, HULL_SPEED]
        hip_torque += lean[:, None] * contact  # only a leg on the ground can right the hull
        knee_torque = g["kp_knee"] * (knee_target - knee) - g["kd_knee"] * knee_speed
        knee_torque -= g["k_vy"] * obs[:, SPEED_Y, None]
        self.phase[pushed] = SWING
        self.support[pushed] = swing[pushed]
        action = torch.stack([hip_torque, knee_torque], -1).reshape(-1, 4)  # hip, knee per leg
        return action.clamp(-1, 1).reshape(*shape, 4)


def random_policy(env: EnvBase) -> TensorDictModule:
    """Uniformly random actions for ``env`` (any action space)."""
    dims = len(env.observation_spec_unbatched["observation"].shape)
    return TensorDictModule(
        RandomActions(env.action_spec_unbatched, dims), in_keys=["observation"], out_keys=["action"]
    )


def _check_walker(env: EnvBase, name: str) -> None:
    check(
        not is_discrete(env)
        and observation_of(env).shape == (24,)
        and env.action_spec_unbatched.shape == (4,),
        f"policy={name} is a hand-written BipedalWalker controller: it needs BipedalWalker's "
        "24 observations and 4 torques (env=bipedal or bipedal_hardcore); use policy=random here",
    )


def naive_policy(env: EnvBase) -> TensorDictModule:
    """The notebook's naive BipedalWalker controller; a clear error on any other env."""
    _check_walker(env, "naive")
    return TensorDictModule(NotebookWalker(), in_keys=["observation"], out_keys=["action"])


def heuristic_policy(env: EnvBase) -> TensorDictModule:
    """The hand-written BipedalWalker gait (:class:`WalkerGait`); a clear error on any other env."""
    _check_walker(env, "heuristic")
    return TensorDictModule(
        WalkerGait(), in_keys=["observation", "step_count"], out_keys=["action"]
    )
