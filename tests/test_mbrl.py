"""Model-based RL: ensemble shapes, model fitting, planners on toy models, resume, CLI."""

from __future__ import annotations

import io
import json
from functools import partial

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import ExplorationType, set_exploration_type

from rlpipe.algos import MBRL, Algorithm, MBRLConfig
from rlpipe.algos.base import EPISODE_RETURN
from rlpipe.algos.mbrl import ActionCoder, EnsembleMLP, Planner, WorldModel
from rlpipe.algos.mbrl.algorithm import MPCPolicy, _sub_batch_steps
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError

SMALL = dict(
    ensemble_size=2,
    hidden_sizes=[16],
    fit_steps=5,
    batch_size=16,
    warmup_frames=20,
    frames_per_batch=20,
    horizon=3,
    num_candidates=8,
    cem_iterations=2,
    elites=2,
)
PENDULUM = EnvConfig(id="Pendulum-v1")


@pytest.fixture(autouse=True)
def one_thread():
    """Tiny tensors: one torch thread is faster than two contending ones on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_ensemble_members_are_independent():
    torch.manual_seed(0)
    net = EnsembleMLP(3, 4, 2, [8, 8])
    x = torch.randn(3, 5, 4)
    out = net(x)
    assert out.shape == (3, 5, 2)
    with torch.no_grad():
        net.weights[0][0].zero_()  # member 0 only
    changed = net(x)
    assert not torch.allclose(changed[0], out[0]) and torch.equal(changed[1:], out[1:])


def test_world_model_fit_reduces_validation_loss():
    """Known dynamics s' = s + 0.1 a, reward -|s|^2, terminated when s'[0] > 1."""
    torch.manual_seed(0)
    obs, act = torch.rand(2000, 2) * 4 - 2, torch.rand(2000, 1) * 2 - 1
    nxt = obs + 0.1 * act
    reward, terminated = -(obs**2).sum(-1), nxt[:, 0] > 1
    model = WorldModel(2, 1, [32, 32], members=3)
    model.observe(obs, nxt, reward, terminated)
    assert bool(model.can_terminate)
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    valid = [t[1600:].expand(3, *t[1600:].shape) for t in (obs, act, nxt, reward, terminated)]

    def validation() -> dict[str, float]:
        with torch.no_grad():
            return {k: float(v) for k, v in model.losses(*valid).items()}

    before = validation()
    for _ in range(300):
        idx = torch.randint(1600, (3, 64))
        loss = sum(
            model.losses(obs[idx], act[idx], nxt[idx], reward[idx], terminated[idx]).values()
        )
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = validation()
    assert set(after) == {"dynamics", "reward", "termination"}
    assert after["dynamics"] < before["dynamics"] / 10
    assert after["reward"] < before["reward"] / 5
    assert after["termination"] < 0.3 < before["termination"]
    with torch.no_grad():
        next_obs, predicted_reward, p_done = model.step(
            obs[:1].expand(3, 1, 2), act[:1].expand(3, 1, 1)
        )
    assert next_obs.shape == (3, 1, 2) and predicted_reward.shape == p_done.shape == (3, 1)


class ToyModel:
    """Known 1-D model for planner tests: s' = s + move(a), reward -(s' - goal)^2; the episode
    terminates with probability ``p_done`` each step. Box actions move by the decoded action,
    discrete ones by ``moves[a]``."""

    def __init__(self, goal: float, coder: ActionCoder, moves=None, p_done: float = 0.0):
        self.goal, self.coder, self.moves, self.p_done = goal, coder, moves, p_done
        self.dynamics = EnsembleMLP(2, 1, 1, [])  # two members: every candidate on both

    def step(self, state, action):
        if self.moves is None:
            move = self.coder.decode(action)
        else:
            move = action @ self.moves.unsqueeze(-1)
        nxt = state + move
        reward = -((nxt - self.goal) ** 2).squeeze(-1)
        return nxt, reward, torch.full_like(reward, self.p_done)


def planner(model, coder, method, **kw) -> Planner:
    args = dict(method=method, horizon=3, candidates=400, iterations=5, elites=40, gamma=1.0)
    return Planner(model, coder, **{**args, "init_std": 0.5, **kw})


@pytest.mark.parametrize("method", ["cem", "random"])
def test_planner_finds_the_best_continuous_action(method):
    coder = ActionCoder(low=torch.tensor([-2.0]), high=torch.tensor([2.0]))
    plan = planner(ToyModel(1.3, coder), coder, method)
    obs = torch.tensor([[0.0], [0.5], [3.0]])
    action = plan.plan(obs, torch.Generator().manual_seed(0))
    # optimum: reach the goal in one step (clipped to the bounds), then stay
    expected = torch.tensor([[1.3], [0.8], [-1.7]])
    assert action.shape == (3, 1)
    assert torch.allclose(action, expected, atol=0.15 if method == "cem" else 0.35)


@pytest.mark.parametrize("method", ["cem", "random"])
def test_planner_finds_the_best_discrete_action(method):
    coder = ActionCoder(num_actions=3)  # actions move by -1, 0, +1
    plan = planner(ToyModel(2.0, coder, torch.tensor([-1.0, 0.0, 1.0])), coder, method)
    action = plan.plan(torch.tensor([[0.0], [2.0], [5.0]]), torch.Generator().manual_seed(0))
    assert action.tolist() == [2, 1, 0]


def test_planned_return_is_discounted_and_stops_at_termination():
    coder = ActionCoder(low=torch.tensor([-1.0]), high=torch.tensor([1.0]))
    codes = torch.zeros(1, 1, 3, 1)  # stay at 0: reward -1 per step with goal 1
    plan = planner(ToyModel(1.0, coder), coder, "random", gamma=0.5)
    assert plan.returns(torch.zeros(1, 1), codes).item() == pytest.approx(-(1 + 0.5 + 0.25))
    plan = planner(ToyModel(1.0, coder, p_done=0.5), coder, "random", gamma=1.0)
    assert plan.returns(torch.zeros(1, 1), codes).item() == pytest.approx(-(1 + 0.5 + 0.25))


def test_action_coder_round_trip():
    coder = ActionCoder(low=torch.tensor([-2.0, 0.0]), high=torch.tensor([2.0, 1.0]))
    action = torch.tensor([[-2.0, 1.0], [1.0, 0.25]])
    assert torch.allclose(coder.encode(action), torch.tensor([[-1.0, 1.0], [0.5, -0.5]]))
    assert torch.allclose(coder.decode(coder.encode(action)), action)
    onehot = ActionCoder(num_actions=3).encode(torch.tensor([2, 0]))
    assert onehot.tolist() == [[0, 0, 1], [1, 0, 0]]


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"horizon": 0}, "algo.horizon must be >= 1, got 0"),
        ({"num_candidates": 0}, "algo.num_candidates must be >= 1, got 0"),
        ({"ensemble_size": 0}, "algo.ensemble_size must be >= 1, got 0"),
        ({"elites": 0}, "algo.elites must be in"),
        ({"num_candidates": 10, "elites": 11}, "algo.elites must be in"),
        ({"cem_iterations": 0}, "algo.cem_iterations"),
        ({"planner": "mppi"}, "algo.planner must be one of cem, random"),
        ({"gamma": 0.0}, "algo.gamma"),
        ({"validation_fraction": 1.0}, "algo.validation_fraction"),
        ({"fit_steps": 0}, "algo.fit_steps"),
        ({"init_std": 0.0}, "algo.init_std"),
    ],
)
def test_bad_values(kwargs, message):
    with pytest.raises(RlpipeError, match=message.replace("(", r"\(").replace("[", r"\[")):
        MBRLConfig(**kwargs)


class UnboundedEnv(gym.Env):
    """A one-step env whose continuous actions have no bounds."""

    observation_space = gym.spaces.Box(-1, 1, (2,))
    action_space = gym.spaces.Box(-np.inf, np.inf, (1,))

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return self.observation_space.sample(), {}

    def step(self, action):
        return self.observation_space.sample(), 0.0, True, False, {}


def test_unbounded_actions_are_a_clear_error():
    if "rlpipe/TestUnbounded-v0" not in gym.registry:
        gym.register("rlpipe/TestUnbounded-v0", entry_point=UnboundedEnv)
    env = make_env(EnvConfig(id="rlpipe/TestUnbounded-v0"))
    with pytest.raises(RlpipeError, match="needs discrete actions or a bounded flat box"):
        MBRL(lambda: env, MBRLConfig(**SMALL))
    assert env.is_closed  # the algorithm closes the env it was given when it cannot use it


def greedy_actions(algo: MBRL, td):
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        return algo.policy(td.clone())["action"]


def test_pendulum_steps_fit_and_resume_exactly():
    torch.manual_seed(0)
    algo = MBRL(partial(make_env, PENDULUM, num_envs=2, seed=0), MBRLConfig(**SMALL))
    assert isinstance(algo, Algorithm)
    first = algo.train_step()  # warm-up batch (random actions), then the first fit
    assert algo.frames == 20 and len(algo.buffer) == 20
    assert {"train/model_loss", "train/val_dynamics_loss", "train/val_reward_loss"} <= set(first)
    assert "train/val_termination_loss" not in first  # Pendulum only truncates
    algo.train_step()  # planned actions
    td = make_env(PENDULUM, num_envs=3, seed=1).reset()
    action = greedy_actions(algo, td)
    assert action.shape == (3, 1) and bool((action.abs() <= 2).all())
    assert torch.equal(action, greedy_actions(algo, td))  # greedy: a function of the obs

    buf = io.BytesIO()
    torch.save(algo.state_dict(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)
    torch.manual_seed(123)
    restored = MBRL(partial(make_env, PENDULUM, num_envs=2, seed=0), MBRLConfig(**SMALL))
    restored.load_state_dict(state)
    assert restored.frames == algo.frames and len(restored.buffer) == 40
    assert not restored.mpc.warmup
    assert torch.equal(greedy_actions(restored, td), action)
    # the same data, generators and optimiser state: the next fit is identical
    assert algo.fit() == restored.fit()
    algo.close()
    restored.close()


def checkpoint(algo: MBRL) -> dict:
    buf = io.BytesIO()
    torch.save(algo.state_dict(), buf)
    buf.seek(0)
    return torch.load(buf, weights_only=True)


class _StopsWhen(MBRL):
    """MBRL whose stop request is a condition on its own state (a signal at a chosen moment)."""

    when = staticmethod(lambda algo: False)

    @property
    def stop_requested(self) -> bool:
        return self.when(self)


def test_a_stop_request_ends_the_step_after_a_sub_batch_in_a_consistent_state():
    """A signal mid-collection: return after the current sub-batch without fitting, every frame
    stored and normalised; the next step completes the iteration and fits, also after a resume."""
    torch.manual_seed(0)
    # 2 envs x 20 steps per iteration, in sub-batches of 10 steps
    cfg = MBRLConfig(**{**SMALL, "frames_per_batch": 40})
    envs = partial(make_env, PENDULUM, num_envs=2, seed=0)
    algo = _StopsWhen(envs, cfg)
    algo.when = lambda algo: algo.frames > 0  # True once the first sub-batch is in
    metrics = algo.train_step()
    assert 0 < algo.frames < cfg.frames_per_batch and algo.frames == 20
    assert len(algo.buffer) == algo.frames == int(algo.model.obs_norm.count)
    assert algo.iterations == 1
    assert "train/model_loss" not in metrics and not algo.optimizer.state  # the fit is skipped
    assert algo.mpc.warmup  # random actions until the first fit

    state = checkpoint(algo)  # a resume point
    restored = MBRL(envs, cfg)
    restored.load_state_dict(state)
    assert restored.frames == 20 and len(restored.buffer) == 20
    assert restored.mpc.warmup  # 20 >= warmup_frames, but no fit yet

    algo.when = lambda algo: False
    for run in (algo, restored):  # the rest of the iteration, then the fit
        metrics = run.train_step()
        assert run.frames == len(run.buffer) == cfg.frames_per_batch
        assert int(run.model.obs_norm.count) == cfg.frames_per_batch
        assert "train/model_loss" in metrics and not run.mpc.warmup
    algo.train_step()  # a whole iteration again
    assert algo.frames == len(algo.buffer) == 2 * cfg.frames_per_batch and algo.iterations == 3
    algo.close()
    restored.close()


def test_a_stop_request_ends_the_fit_after_an_adam_step():
    torch.manual_seed(0)
    cfg = MBRLConfig(**{**SMALL, "frames_per_batch": 40})
    algo = _StopsWhen(partial(make_env, PENDULUM, num_envs=2, seed=0), cfg)
    algo.when = lambda algo: algo.frames >= 40  # the signal comes during the last sub-batch
    metrics = algo.train_step()
    assert algo.frames == len(algo.buffer) == 40
    assert "train/model_loss" in metrics and "train/val_dynamics_loss" in metrics
    steps = {int(s["step"]) for s in algo.optimizer.state.values()}
    assert steps == {1}, f"{cfg.fit_steps} fit steps configured, one expected, got {steps}"
    assert not algo.mpc.warmup
    restored = MBRL(partial(make_env, PENDULUM, num_envs=2, seed=0), cfg)
    restored.load_state_dict(checkpoint(algo))
    assert not restored.mpc.warmup  # fitted
    algo.close()
    restored.close()


def test_episode_metrics_cover_every_sub_batch():
    torch.manual_seed(0)
    # 2 envs x 48 steps in 3 sub-batches of 16 steps; random CartPole episodes end within them
    cfg = MBRLConfig(**{**SMALL, "frames_per_batch": 96, "warmup_frames": 1000})
    algo = MBRL(partial(make_env, EnvConfig(id="CartPole-v1", num_envs=2), seed=0), cfg)
    assert (algo._copies, algo._steps) == (2, 16)  # sub-batches of 16 steps of both copies
    metrics = algo.train_step()
    assert algo.frames == len(algo.buffer) == 96
    # episodes end only by termination here (no truncation within 48 steps)
    terminated = int(algo.buffer[:96]["next", "terminated"].sum())
    assert terminated >= 3 and len(metrics[EPISODE_RETURN]) == terminated
    algo.close()


@pytest.mark.parametrize(
    "steps, expected", [(200, 10), (100, 10), (10, 10), (32, 16), (16, 16), (101, 1), (1, 1)]
)
def test_sub_batches_add_up_to_the_iteration(steps, expected):
    assert _sub_batch_steps(steps) == expected


def test_discrete_env_learns_termination():
    torch.manual_seed(0)
    cfg = MBRLConfig(**{**SMALL, "frames_per_batch": 64})
    algo = MBRL(partial(make_env, EnvConfig(id="CartPole-v1", num_envs=4), seed=0), cfg)
    metrics = algo.train_step()  # random CartPole episodes end within 64 frames
    assert bool(algo.model.can_terminate)
    assert "train/val_termination_loss" in metrics or "train/model_loss" in metrics
    action = greedy_actions(algo, make_env(EnvConfig(id="CartPole-v1", num_envs=3)).reset())
    assert action.shape == (3,) and action.dtype == torch.int64
    assert set(action.tolist()) <= {0, 1}
    algo.close()


def test_cli_trains_on_pendulum(rlpipe_cli, tmp_path):
    # 1,000 random frames (the runner logs scalars every 1,000), one fit, one planned episode
    small = {**SMALL, "warmup_frames": 1000, "frames_per_batch": 1000}
    args = [f"algo.{k}={v}".replace(" ", "") for k, v in small.items()]
    proc = rlpipe_cli(
        "algo=mbrl", "env=pendulum", "progress=false", "total_frames=1000", "eval_episodes=1", *args
    )
    assert proc.returncode == 0, proc.stderr
    run = tmp_path / "run"
    assert json.loads((run / "summary.json").read_text())["frames"] == 1000
    assert (run / "metrics" / "scalars" / "train" / "val_dynamics_loss.csv").exists()
    assert any((run / "checkpoints").iterdir())


BAD_INPUTS = [
    (["algo.horizon=0"], "algo.horizon must be >= 1, got 0"),
    (["algo.horizon=-3"], "algo.horizon must be >= 1, got -3"),
    (["algo.num_candidates=0"], "algo.num_candidates must be >= 1, got 0"),
    (["algo.ensemble_size=0"], "algo.ensemble_size must be >= 1, got 0"),
    (["algo.elites=1000"], "algo.elites must be in [1, algo.num_candidates=100], got 1000"),
    (["algo.planner=mppi"], "algo.planner must be one of cem, random; got 'mppi'"),
    (["algo.hidden_sizes=[0]"], "algo.hidden_sizes must be positive"),
]


@pytest.mark.parametrize("args, message", BAD_INPUTS, ids=[" ".join(a) for a, _ in BAD_INPUTS])
def test_cli_bad_input_is_one_clear_line(rlpipe_cli, tmp_path, args, message):
    proc = rlpipe_cli("progress=false", "algo=mbrl", "env=pendulum", *args)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error: ") and message in lines[0]
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.parametrize("method", ["cem", "random"])
@pytest.mark.parametrize("discrete", [False, True])
def test_plans_and_warmup_actions_on_another_device_than_the_generators(method, discrete):
    """The planner's and the warm-up's draws come from CPU generators (a seed plans the same on
    any device) and move to the observation's device: meta stands for CUDA here, where mixing
    devices failed (a CUDA check of mbrl_pendulum, device=cuda)."""
    meta = torch.device("meta")
    if discrete:
        coder = ActionCoder(num_actions=3)
        model = ToyModel(2.0, coder, torch.tensor([-1.0, 0.0, 1.0]).to(meta))
    else:
        coder = ActionCoder(low=torch.tensor([-2.0]).to(meta), high=torch.tensor([2.0]).to(meta))
        model = ToyModel(1.3, coder)
    model.goal = torch.as_tensor(model.goal).to(meta)
    plan = planner(model, coder, method)
    observation = torch.zeros(4, 1, device=meta)
    assert plan.plan(observation, torch.Generator().manual_seed(0)).device == meta
    policy = MPCPolicy(plan, torch.Generator().manual_seed(0))
    policy.warmup = True
    with set_exploration_type(ExplorationType.RANDOM):
        assert policy(observation).device == meta
