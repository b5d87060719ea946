"""The EnvPool backend's env: gymnasium's specs and time limits, no autoreset filler in rollouts
or collector batches, partial resets, seeds; which backend ``env.backend`` picks, and why not."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule
from torchrl.collectors import Collector
from torchrl.envs.utils import check_env_specs

from rlpipe.algos.configs import ARSConfig, DQNConfig
from rlpipe.config import Config, EnvConfig
from rlpipe.envs import backends as env_backends
from rlpipe.envs import envpool_env, make_env
from rlpipe.envs.backends import (
    ENVPOOL_DIFFERS,
    ENVPOOL_IDS,
    ENVPOOL_INSTALL,
    backend_of,
    resolve_backend,
)
from rlpipe.errors import RlpipeError

needs_envpool = pytest.mark.skipif(
    env_backends.envpool_version() is None,
    reason=f"EnvPool is not installed: {ENVPOOL_INSTALL}",
)


def pooled(env_id: str = "CartPole-v1", n: int = 4, seed: int = 0, **options):
    """``n`` copies on the EnvPool backend, and the same on gymnasium's."""
    both = [
        make_env(EnvConfig(id=env_id, backend=b, **options), num_envs=n, seed=seed)
        for b in ("envpool", "gymnasium")
    ]
    assert envpool_env(both[0]) is not None and envpool_env(both[1]) is None
    return both


def constant(env, value: float = 1.0) -> TensorDictModule:
    """A deterministic policy: the same action every step (action index 1 if discrete)."""
    action = torch.full(env.action_spec_unbatched.shape, value)
    action = action.to(env.action_spec_unbatched.dtype)
    return TensorDictModule(
        lambda obs: action.expand(*obs.shape[:-1], *action.shape), ["observation"], ["action"]
    )


def episodes(batch) -> tuple[list[float], list[int]]:
    """Returns and lengths of the episodes that end in a rollout or collector batch."""
    done = batch["next", "done"]
    return batch["next", "episode_reward"][done].tolist(), batch["next", "step_count"][
        done
    ].tolist()


@needs_envpool
@pytest.mark.parametrize("env_id", ENVPOOL_IDS)
def test_specs_and_time_limits_are_gymnasiums(env_id):
    ours, theirs = pooled(env_id, n=2)
    for spec in ("observation", "action", "reward", "done"):
        assert getattr(ours, f"full_{spec}_spec") == getattr(theirs, f"full_{spec}_spec"), spec
    assert envpool_env(ours).pool.config["max_episode_steps"] == gym.spec(env_id).max_episode_steps
    check_env_specs(ours)  # BipedalWalker's declared EnvPool space would fail this


@needs_envpool
def test_no_filler_transition_reaches_a_rollout():
    """A filler step (reward 0, not done) would break CartPole's reward 1 per step, and the
    episodes' returns and lengths (a deterministic policy) match gymnasium's."""
    results = []
    for env in pooled("CartPole-v1", n=4, max_episode_steps=30):
        batch = env.rollout(200, constant(env), break_when_any_done=False)
        assert (batch["next", "reward"] == 1).all()
        returns, lengths = episodes(batch)
        assert returns == [float(n) for n in lengths]
        # every step of an episode is counted once: counts run 1, 2, ... from each reset
        counts = batch["next", "step_count"].squeeze(-1)
        restart = torch.cat(
            [torch.ones(4, 1, dtype=torch.bool), batch["next", "done"].squeeze(-1)[:, :-1]], 1
        )
        assert (counts[restart] == 1).all() and (counts[~restart] > 1).all()
        results.append(sorted(lengths))
    ours, theirs = results
    assert abs(np.mean(ours) - np.mean(theirs)) < 1.0 and max(ours) <= 11 and min(ours) >= 8


@needs_envpool
def test_no_filler_transition_reaches_a_collector_batch():
    """The copies end at different steps: each restarts alone, and no step pays 0."""
    env, _ = pooled("CartPole-v1", n=3)
    collector = Collector(env, constant(env), frames_per_batch=3 * 50, total_frames=3 * 100)
    for batch in collector:
        assert (batch["next", "reward"] == 1).all()
        returns, lengths = episodes(batch)
        assert returns == [float(n) for n in lengths] and len(set(lengths)) > 1
    collector.shutdown()


@needs_envpool
def test_partial_reset_restarts_only_the_masked_copies():
    env, _ = pooled("CartPole-v1", n=3)
    td = env.reset()
    for _ in range(3):
        td["action"] = torch.zeros(3, dtype=torch.long)
        td = env.step(td)["next"]
    before = td["observation"].clone()
    td["_reset"] = torch.tensor([[False], [True], [False]])
    after = env.reset(td)
    assert after["step_count"].squeeze(-1).tolist() == [3, 0, 3]
    assert torch.equal(after["observation"][[0, 2]], before[[0, 2]])
    assert not torch.equal(after["observation"][1], before[1])


@needs_envpool
def test_a_finished_copy_is_not_stepped_until_it_is_reset():
    """EnvPool would autoreset it; here it stays as it ended: done, reward 0, same observation."""
    env, _ = pooled("CartPole-v1", n=2, max_episode_steps=3)
    td = env.reset()
    for _ in range(3):
        td["action"] = torch.zeros(2, dtype=torch.long)
        td = env.step(td)["next"]
    assert td["done"].all()
    ended = td["observation"].clone()
    td["action"] = torch.zeros(2, dtype=torch.long)
    again = env.step(td)["next"]
    assert again["done"].all() and (again["reward"] == 0).all()
    assert torch.equal(again["observation"], ended)


@needs_envpool
def test_seeds_apply_at_build_whatever_the_threads():
    def run(seed, threads=1):
        env = make_env(
            EnvConfig(id="BipedalWalker-v3", backend="envpool"),
            num_envs=3,
            seed=seed,
            threads=threads,
        )
        return env.rollout(60, constant(env, 0.3), break_when_any_done=False)["next", "observation"]

    assert torch.equal(run(5), run(5, threads=2))
    assert not torch.equal(run(5), run(6))
    env = make_env(EnvConfig(id="BipedalWalker-v3", backend="envpool"), num_envs=3, seed=9)
    env.set_seed(5)
    rolled = env.rollout(60, constant(env, 0.3), break_when_any_done=False)["next", "observation"]
    assert torch.equal(rolled, run(5))


@needs_envpool
def test_kwargs_that_select_an_envpool_variant_are_honoured():
    cfg = EnvConfig(id="BipedalWalker-v3", kwargs={"hardcore": True})
    assert (
        backend_of(cfg) == "envpool"
        and env_backends.envpool_task(cfg) == "BipedalWalkerHardcore-v3"
    )
    assert envpool_env(make_env(cfg, num_envs=1)).pool.config["hardcore"] is True


@needs_envpool
@pytest.mark.parametrize(
    "cfg, backend",
    [
        (EnvConfig(id="CartPole-v1"), "envpool"),
        (EnvConfig(id="rlpipe/CartPoleNoop-v0"), "gymnasium"),  # EnvPool has no such id
        (EnvConfig(id="CartPole-v1", kwargs={"sutton_barto_reward": True}), "gymnasium"),
        (EnvConfig(id="CartPole-v1", backend="gymnasium"), "gymnasium"),
        (EnvConfig(id="Pendulum-v1"), "gymnasium"),  # EnvPool's steps differently
        (EnvConfig(id="Pendulum-v1", backend="envpool"), "envpool"),  # asked for: a warning
    ],
)
def test_auto_picks_envpool_where_it_can_and_says_why(cfg, backend):
    chosen, line = resolve_backend(cfg)
    assert chosen.backend == backend and line.startswith(f"env backend {backend} (")
    assert backend_of(cfg, render_mode="rgb_array") == "gymnasium"  # videos render on gymnasium


@needs_envpool
def test_auto_names_the_variant_envpool_runs():
    line = resolve_backend(EnvConfig(id="BipedalWalker-v3", kwargs={"hardcore": True}))[1]
    assert " runs BipedalWalkerHardcore-v3; " in line


@needs_envpool
def test_auto_takes_gymnasium_for_one_env_copy():
    one, line = resolve_backend(EnvConfig(id="MountainCarContinuous-v0"), copies=1)
    assert one.backend == "gymnasium" and "one env copy" in line and "env.backend=envpool" in line
    assert resolve_backend(EnvConfig(id="MountainCarContinuous-v0"), copies=2)[0].backend == (
        "envpool"
    )
    asked = EnvConfig(id="MountainCarContinuous-v0", backend="envpool")
    chosen, line = resolve_backend(asked, copies=1)
    assert chosen.backend == "envpool" and line.endswith("; env.backend=auto lets rlpipe choose)")
    # what a run steps at once: env.num_envs, or ARS's population whatever num_envs says
    assert DQNConfig().stepped_copies(1) == 1 and DQNConfig().stepped_copies(8) == 8
    assert ARSConfig(num_directions=4, num_best=4).stepped_copies(1) == 8
    assert Config(env=EnvConfig(num_envs=8)).stepped_copies() == 8  # DQN's: the env's copies


def test_auto_keeps_the_backend_a_run_recorded():
    chosen, line = resolve_backend(EnvConfig(id="CartPole-v1"), recorded="gymnasium")
    assert chosen.backend == "gymnasium" and "recorded" in line


@pytest.mark.parametrize(
    "cfg, message",
    [
        (EnvConfig(id="rlpipe/CartPoleNoop-v0", backend="envpool"), "BipedalWalker-v3, "),
        (
            EnvConfig(id="CartPole-v1", backend="envpool", kwargs={"foo": 1}),
            r"cannot honour env.kwargs \{'foo': 1\}: for CartPole-v1 it takes none;",
        ),
        (
            EnvConfig(id="BipedalWalker-v3", backend="envpool", kwargs={"hardcore": 1}),
            "for BipedalWalker-v3 it takes hardcore=true[|]false;",
        ),
    ],
)
def test_what_envpool_cannot_run_is_one_line(cfg, message):
    with pytest.raises(RlpipeError, match=message) as error:
        make_env(cfg)
    assert "\n" not in str(error.value) and "env.backend=gymnasium" in str(error.value)


def test_envpool_not_installed_says_how_to_install_and_auto_falls_back(monkeypatch):
    monkeypatch.setattr(env_backends, "envpool_version", lambda: None)
    with pytest.raises(RlpipeError, match="pip install"):
        make_env(EnvConfig(id="CartPole-v1", backend="envpool"))
    assert envpool_env(make_env(EnvConfig(id="CartPole-v1"))) is None
    assert "not installed" in resolve_backend(EnvConfig(id="CartPole-v1"))[1]


def test_envpool_is_installed_only_where_its_wheels_were_checked():
    """The install line brings EnvPool on Linux x86_64, Python >= 3.11; elsewhere the marker
    leaves it out (the install succeeds and auto is gymnasium)."""
    tomllib = pytest.importorskip("tomllib")
    from packaging.markers import default_environment
    from packaging.requirements import Requirement

    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    requirements = map(Requirement, project["project"]["dependencies"])
    (dependency,) = [r for r in requirements if r.name == "envpool"]
    assert str(dependency.specifier) == ">=1.2.5"

    def installed(system: str, machine: str, python: str) -> bool:
        where = dict(platform_system=system, platform_machine=machine, python_version=python)
        return dependency.marker.evaluate({**default_environment(), **where})

    assert installed("Linux", "x86_64", "3.11") and installed("Linux", "x86_64", "3.13")
    assert not installed("Linux", "x86_64", "3.10")  # no 1.2.5 wheel: pip would pick 0.8
    assert not installed("Darwin", "arm64", "3.11") and not installed("Windows", "AMD64", "3.12")
    assert not installed("Linux", "aarch64", "3.12")


def _state(env_id: str, obs: np.ndarray) -> np.ndarray:
    """The gymnasium env's ``state`` behind an observation (classic control)."""
    if env_id == "Pendulum-v1":
        return np.array([np.arctan2(obs[1], obs[0]), obs[2]])
    if env_id == "Acrobot-v1":
        return np.array([np.arctan2(obs[1], obs[0]), np.arctan2(obs[3], obs[2]), *obs[4:]])
    return obs.astype(np.float64)


@needs_envpool
@pytest.mark.filterwarnings("ignore:.*precision lowered:UserWarning")  # EnvPool's float64 bounds
@pytest.mark.parametrize(
    "env_id",
    ["CartPole-v1", "MountainCar-v0", "MountainCarContinuous-v0", "Acrobot-v1", "Pendulum-v1"],
)
def test_envpool_steps_as_gymnasium_from_the_same_state_or_is_listed(env_id):
    """One step of EnvPool's copy and of gymnasium's from the state EnvPool was in, with the same
    action: the same next observation, except for the ids ENVPOOL_DIFFERS lists (which must
    really differ: a fixed EnvPool makes this fail, and the entry goes)."""
    import envpool

    copies = 32  # Pendulum: some copies reach its speed limit within the steps
    pool = envpool.make(env_id, env_type="gymnasium", num_envs=copies, seed=1)
    env = gym.make(env_id).unwrapped
    env.reset(seed=0)
    rng, worst = np.random.default_rng(0), 0.0
    obs, _ = pool.reset()
    for _ in range(200):
        space = env.action_space
        if isinstance(space, gym.spaces.Discrete):
            action = rng.integers(0, space.n, copies)
        else:
            action = rng.uniform(space.low, space.high, (copies, *space.shape)).astype(np.float32)
        nxt, _, terminated, truncated, _ = pool.step(action)
        for i in np.flatnonzero(~(terminated | truncated)):
            env.state = _state(env_id, obs[i])
            theirs = env.step(action[i])[0]
            worst = max(worst, float(np.abs(np.asarray(theirs) - nxt[i]).max()))
        obs = nxt
        done = np.flatnonzero(terminated | truncated).astype(np.int32)
        if len(done):
            fresh, info = pool.reset(done)
            obs[info["env_id"]] = fresh
    assert (worst > 1e-3) == (env_id in ENVPOOL_DIFFERS), worst
