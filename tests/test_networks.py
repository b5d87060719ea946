"""Bring your own network: every algorithm takes a module (Python) or an ``algo.network`` spec
(config) in place of its default network, checked against the env's sizes."""

from __future__ import annotations

from functools import partial

import pytest
import torch
from torch import nn

from rlpipe import (
    ARS,
    DQN,
    MBRL,
    PPO,
    SAC,
    ARSConfig,
    DQNConfig,
    EnvConfig,
    MBRLConfig,
    PPOConfig,
    Reinforce,
    ReinforceConfig,
    SACConfig,
    make_env,
)
from rlpipe.algos.mbrl import WorldModel
from rlpipe.errors import RlpipeError

CARTPOLE = partial(make_env, EnvConfig(id="CartPole-v1", num_envs=2), seed=0)
PENDULUM = partial(make_env, EnvConfig(id="Pendulum-v1", num_envs=2), seed=0)
SMALL_DQN = DQNConfig(batch_size=8, buffer_size=64, learning_starts=8, frames_per_batch=8)


class Tagged(nn.Module):
    """A small network with a recognisable layer (to find it inside the algorithm)."""

    def __init__(self, in_features: int, out_features: int, hidden: int = 8) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Linear(in_features, hidden), nn.LayerNorm(hidden))
        self.head = nn.Linear(hidden, out_features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(x))


SPEC = {"_target_": f"{__name__}.Tagged", "hidden": 5}


def layer_norms(module: nn.Module) -> list[nn.LayerNorm]:
    return [m for m in module.modules() if isinstance(m, nn.LayerNorm)]


@pytest.mark.parametrize(
    "build",
    [
        lambda net: DQN(CARTPOLE, SMALL_DQN, network=net),
        lambda net: Reinforce(CARTPOLE, ReinforceConfig(episodes_per_epoch=2), network=net),
        lambda net: ARS(  # noise large enough that ± perturbations act differently
            CARTPOLE, ARSConfig(workers=1, num_directions=2, num_best=2, noise=0.5), network=net
        ),
        lambda net: PPO(CARTPOLE, PPOConfig(frames_per_batch=32, minibatch_size=16), network=net),
        lambda net: SAC(
            PENDULUM, SACConfig(batch_size=8, learning_starts=8, hidden_sizes=[8]), network=net
        ),
    ],
    ids=["dqn", "reinforce", "ars", "ppo", "sac"],
)
def test_a_module_replaces_the_default_network_and_trains(request, build):
    # CartPole: 4 observations, 2 actions; SAC on Pendulum: 3 observations, mean and std of 1
    torch.manual_seed(0)
    net = Tagged(3, 2) if request.node.callspec.id == "sac" else Tagged(4, 2)
    algo = build(net)
    try:
        assert layer_norms(algo.policy) == [net.body[1]]  # the very module, not a copy
        before = net.head.weight.detach().clone()
        for _ in range(4):
            algo.train_step()
        assert not torch.equal(before, net.head.weight)  # its parameters are trained
    finally:
        algo.close()


def test_a_spec_is_instantiated_with_the_envs_sizes():
    algo = DQN(CARTPOLE, DQNConfig(**{**SMALL_DQN.__dict__, "network": SPEC}))
    try:
        (norm,) = layer_norms(algo.policy)
        assert norm.normalized_shape == (5,)  # hidden=5 from the spec
        linears = [m for m in algo.policy.modules() if isinstance(m, nn.Linear)]
        assert (linears[0].in_features, linears[-1].out_features) == (4, 2)  # filled in
    finally:
        algo.close()


def test_continuous_reinforce_network_gives_a_mean_and_a_std_per_dimension():
    algo = Reinforce(PENDULUM, ReinforceConfig(network=SPEC))
    try:
        td = algo.policy(PENDULUM().reset())
        assert td["loc"].shape == td["scale"].shape == (2, 1)
    finally:
        algo.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(network=Tagged(4, 3)), "maps a batch of 2 inputs of size 4 to (2, 3)"),
        (dict(network=Tagged(5, 2)), "fails on a batch of 2 inputs of size 4"),
        (dict(cfg={"_target_": "no_such_module.Net"}), "no module named 'no_such_module'"),
        (dict(cfg={"_target_": f"{__name__}.Missing"}), f"module {__name__} has no Missing"),
        (dict(cfg={**SPEC, "hiden": 3}), "unexpected keyword argument 'hiden'"),
        (dict(cfg={"hidden": 3}), "algo.network._target_ must name"),
        (dict(cfg={"_target_": "builtins.dict"}), "must build a torch nn.Module, got dict"),
        (dict(cfg=SPEC, network=Tagged(4, 2)), "both as an object and as algo.network"),
        (dict(cfg=SPEC, layer_norm=True), "algo.layer_norm shapes dqn's default network"),
        (dict(network=Tagged(4, 2), layer_norm=True), "put the LayerNorm in your network"),
    ],
)
def test_bad_networks_are_one_clear_line(kwargs, message):
    given = {"network": kwargs.pop("cfg", {}), "layer_norm": kwargs.pop("layer_norm", False)}
    cfg = DQNConfig(**{**SMALL_DQN.__dict__, **given})
    with pytest.raises(RlpipeError) as err:
        DQN(CARTPOLE, cfg, **kwargs)
    assert message in str(err.value) and "\n" not in str(err.value)


class BiggerRewardModel(WorldModel):
    """A world model subclass with a wider reward network."""

    def __init__(self, obs_size, action_size, hidden_sizes, members):
        super().__init__(obs_size, action_size, hidden_sizes, members)
        self.reward = nn.Sequential(nn.Linear(2 * obs_size + action_size, 7), nn.Tanh())
        self.reward.append(nn.Linear(7, 1))


def test_mbrl_takes_a_world_model_as_object_or_spec():
    small = dict(ensemble_size=2, hidden_sizes=[8], frames_per_batch=8, warmup_frames=8)
    model = BiggerRewardModel(3, 1, [8], 2)
    algo = MBRL(PENDULUM, MBRLConfig(**small), network=model)
    assert algo.model is model
    algo.close()
    spec = {"_target_": f"{__name__}.BiggerRewardModel"}
    algo = MBRL(PENDULUM, MBRLConfig(**small, network=spec))
    assert isinstance(algo.model, BiggerRewardModel) and algo.model.dynamics.members == 2
    algo.close()
    with pytest.raises(RlpipeError, match="a rlpipe.algos.mbrl.WorldModel"):
        MBRL(PENDULUM, MBRLConfig(**small), network=Tagged(3, 1))


def test_a_runner_run_with_a_network_object_records_its_class(tmp_path):
    from rlpipe import RunDir, Runner, load_run

    algo = DQN(CARTPOLE, SMALL_DQN, network=Tagged(4, 2))
    eval_env = make_env(EnvConfig(id="CartPole-v1"), seed=1)
    Runner(algo, eval_env, RunDir(tmp_path), total_frames=16, eval_episodes=1, progress=False).run()
    algo.close()
    eval_env.close()
    with pytest.raises(RlpipeError, match=f"network was a Python object \\({__name__}.Tagged\\)"):
        load_run(tmp_path)
    run = load_run(tmp_path, network=Tagged(4, 2))
    assert len(layer_norms(run.algo.policy)) == 1
    run.algo.close()
