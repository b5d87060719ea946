"""Fine-tuning (``init_from``): each algorithm starts from another run's weights with its own
settings, the new run records its parent, every bad input is one line that writes nothing, and
a run extended with ``resume=`` keeps its schedules on the frames it began with."""

from __future__ import annotations

import math
from dataclasses import replace
from functools import partial
from pathlib import Path

import pytest
import torch
from conftest import BASE, run_module

from rlpipe.algos import make_algorithm
from rlpipe.algos.configs import (
    ARSConfig,
    DQNConfig,
    MBRLConfig,
    PPOConfig,
    ReinforceConfig,
    SACConfig,
)
from rlpipe.config import Config, EnvConfig, split_init_from
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError
from rlpipe.lineage import Parent, read_parent
from rlpipe.pipeline import load_run, train
from rlpipe.rundir import RunDir

CARTPOLE = EnvConfig(id="CartPole-v1", num_envs=2, backend="gymnasium")
PENDULUM = EnvConfig(id="Pendulum-v1", num_envs=2, backend="gymnasium")
# algorithm -> (env, parent config, the child's changes: other learning rates and settings)
PAIRS = {
    "dqn": (
        CARTPOLE,
        DQNConfig(frames_per_batch=32, learning_starts=16, batch_size=16, buffer_size=500),
        dict(lr=5e-3, eps_start=0.2),
    ),
    "sac": (
        PENDULUM,
        SACConfig(frames_per_batch=32, learning_starts=16, batch_size=16, hidden_sizes=[16]),
        dict(lr=1e-2, target_entropy=-3.0),
    ),
    "ppo": (
        CARTPOLE,
        PPOConfig(  # its clip range annealed over 64 frames, its observations normalised
            frames_per_batch=32,
            minibatch_size=16,
            epochs=1,
            hidden_sizes=[16],
            anneal_clip=True,
            total_frames=64,
            normalize_observations=True,
        ),
        dict(lr=1e-2, clip_epsilon=0.3, anneal_clip=False),
    ),
    "reinforce": (
        CARTPOLE,
        ReinforceConfig(episodes_per_epoch=2, updates_per_epoch=2, batch_size=8, baseline="value"),
        dict(lr=5e-2, value_lr=5e-3),
    ),
    "mbrl": (
        PENDULUM,
        MBRLConfig(warmup_frames=0, frames_per_batch=20, fit_steps=2, hidden_sizes=[8], horizon=2),
        dict(lr=3e-2),
    ),
    "ars": (
        CARTPOLE,
        ARSConfig(num_directions=2, num_best=2, episode_length=20, workers=1),
        dict(step_size=0.5),
    ),
}


def _build(env: EnvConfig, cfg, seed: int):
    torch.manual_seed(seed)
    return make_algorithm(partial(make_env, env, seed=seed), cfg)


def _weights(algo) -> dict[str, torch.Tensor]:
    """Every parameter of the algorithm's networks, and its greedy policy's whole state (the
    observation normaliser's statistics included)."""
    modules = {"policy": algo.search.policy} if hasattr(algo, "search") else {"policy": algo.policy}
    for name in getattr(algo, "state_attrs", ()):
        if isinstance(getattr(algo, name), torch.nn.Module):
            modules[name] = getattr(algo, name)
    found = {f"{m}.{k}": v for m, module in modules.items() for k, v in module.named_parameters()}
    found.update({f"policy:{k}": v for k, v in modules["policy"].state_dict().items()})
    return found


@pytest.mark.parametrize("name", PAIRS)
def test_a_child_starts_from_the_parents_weights_with_its_own_settings(name):
    env, parent_cfg, changes = PAIRS[name]
    child_cfg = replace(parent_cfg, **changes)
    parent = _build(env, parent_cfg, seed=0)
    child = _build(env, child_cfg, seed=1)
    try:
        parent.train_step()
        ours, theirs = _weights(child), _weights(parent)
        assert ours.keys() == theirs.keys()
        assert any(not torch.equal(ours[k], theirs[k]) for k in ours)  # so the test can fail
        optimizer = hasattr(child, "optimizer")
        child.start_from(parent.state_dict(), ["optimizer"] if optimizer else [], parent.cfg)
        ours = _weights(child)
        assert all(torch.equal(ours[k], theirs[k]) for k in ours), name
        assert (child.frames, child.iterations) == (0, 0)
        if optimizer:  # Adam's moments are the parent's, the learning rates this config's
            assert child.optimizer.state_dict()["state"].keys()
            moments = [s["exp_avg"] for s in parent.optimizer.state_dict()["state"].values()]
            loaded = [s["exp_avg"] for s in child.optimizer.state_dict()["state"].values()]
            assert all(torch.equal(a, b) for a, b in zip(moments, loaded))
            assert child.optimizer.param_groups[0]["lr"] == child_cfg.lr != parent_cfg.lr
    finally:
        parent.close()
        child.close()
    if name == "dqn":  # epsilon follows the new config from its frame 0
        assert float(child.exploration.eps) == pytest.approx(0.2)
    if name == "ppo":  # the clip range is a setting: this config's, not the parent's annealed one
        assert float(parent.loss.clip_epsilon) < 0.2
        assert float(child.loss.clip_epsilon) == pytest.approx(0.3)
    if name == "sac":  # the target entropy is this config's; alpha, learned, the parent's
        assert float(child.loss.target_entropy) == -3.0 != float(parent.loss.target_entropy)
        assert torch.equal(child.loss.log_alpha, parent.loss.log_alpha)
    if name == "reinforce":  # V(s)'s own learning rate too
        assert child.optimizer.param_groups[1]["lr"] == 5e-3


def test_sac_alpha_restarts_where_the_new_config_asks_for_another_start():
    env, parent_cfg, _ = PAIRS["sac"]
    parent = _build(env, parent_cfg, seed=0)
    child = _build(env, replace(parent_cfg, alpha_init=0.25), seed=1)
    try:
        parent.train_step()
        child.start_from(parent.state_dict(), [], parent.cfg)
        assert float(child.loss.log_alpha.detach()) == pytest.approx(math.log(0.25))
    finally:
        parent.close()
        child.close()


@pytest.mark.parametrize(
    "name, part, message",
    [
        ("ppo", "buffer", "init_buffer=true, but PPO keeps no replay buffer to start from"),
        ("reinforce", "buffer", "init_buffer=true, but Reinforce keeps no replay buffer"),
        ("ars", "optimizer", "init_optimizer=true, but ARS keeps no optimizer or replay buffer"),
    ],
)
def test_a_part_the_algorithm_does_not_keep_is_one_line(name, part, message):
    env, parent_cfg, _ = PAIRS[name]
    algo = _build(env, parent_cfg, seed=0)
    try:
        with pytest.raises(RlpipeError, match=message):
            algo.start_from(algo.state_dict(), [part], algo.cfg)
    finally:
        algo.close()


# ---- runs: train(init_from=...), the record, the bad inputs --------------------------------

TINY = DQNConfig(frames_per_batch=16, learning_starts=32, batch_size=16, lr_end=0.0)


def _config(**changes) -> Config:
    base = Config(env=CARTPOLE, algo=TINY, total_frames=64, eval_every=0, eval_episodes=2)
    return replace(base, progress=False, **changes)


@pytest.fixture(scope="module")
def parent(tmp_path_factory) -> Path:
    """A finished tiny DQN run (checkpoints at 32 and 64 frames)."""
    run_dir = tmp_path_factory.mktemp("parent") / "run"
    train(_config(checkpoint_every=32), run_dir)
    return run_dir


def test_a_fine_tuned_run_records_its_parent_and_starts_at_zero(parent, tmp_path, capsys):
    child = tmp_path / "child"
    cfg = _config(init_from=f"{parent}:32", algo=replace(TINY, lr=3e-3), total_frames=32)
    result = train(cfg, child)
    assert result.frames == 32
    out = capsys.readouterr().out
    assert f"a new run from {parent} at 32 frames (ckpt_000000000032.pt): its networks" in out
    recorded = RunDir(child).read_config()
    assert recorded.init_from == f"{parent}:ckpt_000000000032.pt"  # pinned: absolute, the file
    assert RunDir(child).parent() == (parent, 32)
    loaded = load_run(child)
    # its own schedule over its own 32 frames: the learning rate annealed from 3e-3 to 0 there
    assert loaded.algo.optimizer.param_groups[0]["lr"] == 0.0
    assert loaded.algo.frames == 32
    loaded.algo.close()
    # resumed with the same overrides (init_from included), it continues: no second start
    more = train(replace(cfg, total_frames=48, init_from=str(parent)), child)
    assert more.frames == 48 and "a new run from" not in capsys.readouterr().out
    assert RunDir(child).read_config().init_from == recorded.init_from


def test_init_from_best_pins_the_best_checkpoint(parent, tmp_path):
    best = RunDir(parent).bests()[-1].name
    cfg = _config(init_from=f"{parent}:best", total_frames=16)
    assert read_parent(cfg).checkpoint.path.name == best


def _refused(cfg: Config, run_dir: Path, message: str) -> None:
    """``train`` refuses ``cfg`` with one line holding ``message``; ``run_dir`` is untouched."""
    before = (
        sorted(p.relative_to(run_dir) for p in run_dir.rglob("*")) if run_dir.exists() else None
    )
    with pytest.raises(RlpipeError, match=message) as err:
        train(cfg, run_dir)
    assert len(str(err.value).splitlines()) == 1
    after = sorted(p.relative_to(run_dir) for p in run_dir.rglob("*")) if run_dir.exists() else None
    assert after == before


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            dict(algo=PPOConfig(frames_per_batch=32, minibatch_size=16)),
            "is a dqn run and this one is ppo: a fine-tuned run keeps its parent's algorithm "
            r"\(algo=dqn\)",
        ),
        (
            dict(env=EnvConfig(id="Acrobot-v1", backend="gymnasium")),
            r"was trained on CartPole-v1 and this run is on Acrobot-v1: .*\(env.id=CartPole-v1",
        ),
        (
            dict(algo=replace(TINY, hidden_sizes=[64])),
            r"networks differ from the parent's in algo.hidden_sizes \(\[64\] here, \[128, 128\] "
            r"there\); fine-tune with the parent's \(algo.hidden_sizes=\[128,128\]\)",
        ),
        (
            dict(init_buffer=True, algo=replace(TINY, buffer_size=400)),
            r"init_buffer=true takes the parent's replay buffer as it was filled, but "
            r"algo.buffer_size differs \(400 here, 10000 there\)",
        ),
        (dict(init_from="NOPE"), "run directory .*nope does not exist"),
        (dict(init_from="PARENT:96"), "has no checkpoint at 96 frames .* it has 32, 64"),
        (dict(init_from="PARENT:foo"), r"does not exist \(after a colon: a frame count, best"),
    ],
)
def test_a_parent_that_does_not_fit_is_one_line(parent, tmp_path, changes, message):
    spec = changes.pop("init_from", str(parent))
    spec = spec.replace("PARENT", str(parent)).replace("NOPE", str(tmp_path / "nope"))
    _refused(_config(init_from=spec, **changes), tmp_path / "child", message)


def test_a_damaged_or_empty_parent_is_one_line(parent, tmp_path):
    import shutil

    damaged = Path(shutil.copytree(parent, tmp_path / "damaged"))
    (damaged / "config.yaml").write_text("algo: [not, a, config\n")
    _refused(_config(init_from=str(damaged)), tmp_path / "a", r"config.yaml is damaged")
    empty = Path(shutil.copytree(parent, tmp_path / "empty"))
    shutil.rmtree(empty / "checkpoints")
    _refused(_config(init_from=str(empty)), tmp_path / "b", "has no checkpoint yet")
    broken = Path(shutil.copytree(parent, tmp_path / "broken"))
    for checkpoint in broken.glob("checkpoints/*.pt"):
        checkpoint.write_bytes(b"not a checkpoint")
    _refused(_config(init_from=str(broken)), tmp_path / "c", "every checkpoint .* is damaged")
    assert sorted(p.name for p in (broken / "checkpoints").iterdir()) == sorted(
        p.name for p in (parent / "checkpoints").iterdir()
    )  # the parent's files are read, never moved or written


def test_init_from_with_resume_of_another_run_is_one_line(parent, tmp_path):
    other = tmp_path / "other"
    train(_config(total_frames=16), other)
    cfg = _config(init_from=str(parent), resume=str(other))
    _refused(
        cfg,
        other,
        f"init_from={parent} starts a new run, but {other} holds a run "
        r"\(begun from scratch\) that this would continue: drop init_from",
    )


@pytest.mark.parametrize(
    "changes, message",
    [
        (dict(init_optimizer=True), "init_optimizer=true takes a part of the run init_from names"),
        (dict(init_buffer=True), "init_buffer=true takes a part of the run init_from names"),
        (dict(init_from=""), "init_from must be a run dir, optionally with :<frames>"),
    ],
)
def test_init_keys_are_checked_with_the_config(changes, message):
    with pytest.raises(RlpipeError, match=message):
        _config(**changes)


def test_init_from_splits_its_checkpoint():
    assert split_init_from("runs/a:4096") == ("runs/a", "4096")
    assert split_init_from("runs/a:best") == ("runs/a", "best")
    assert split_init_from("/x/runs/a:ckpt_000000000064.pt") == (
        "/x/runs/a",
        "ckpt_000000000064.pt",
    )
    assert split_init_from("runs/a") == ("runs/a", None)
    assert split_init_from("runs/a:b/c") == ("runs/a:b/c", None)  # a colon in a dir's name


def test_a_state_that_does_not_fit_is_one_line_naming_the_env_kwargs(parent):
    cfg = _config(init_from=str(parent), env=replace(CARTPOLE, kwargs={"sutton_barto_reward": 1}))
    found = Parent(parent, RunDir(parent).read_config(), RunDir(parent).read_checkpoint())
    with pytest.raises(RlpipeError) as err, found.applying(cfg):
        raise RuntimeError("size mismatch for weight: copying a param with shape [2, 4]\nmore")
    assert str(err.value) == (
        f"init_from={parent}: ckpt_000000000064.pt does not fit this run "
        "(RuntimeError: size mismatch for weight: copying a param with shape [2, 4]); its env's "
        "observation and action shapes and its networks must be the parent's (env.kwargs "
        "there: {})"
    )


# ---- extending a run: its schedules stay on the frames it began with --------------------


def test_an_extended_run_keeps_its_schedules_on_its_first_frames(parent, tmp_path, capsys):
    import shutil

    run = Path(shutil.copytree(parent, tmp_path / "run"))
    result = train(_config(total_frames=96), run)
    assert result.frames == 96
    assert "96 frames, where the run began with 64: its schedules" in capsys.readouterr().out
    loaded = load_run(run)
    assert loaded.algo.optimizer.param_groups[0]["lr"] == 0.0  # annealed to 0 at 64, stays 0
    assert (loaded.cfg.total_frames, loaded.cfg.algo.total_frames) == (96, 64)
    loaded.algo.close()


# ---- the command line ------------------------------------------------------------------------


def test_fine_tuning_from_the_command_line(finished_run, tmp_path):
    common = [*BASE, f"init_from={finished_run}:100", "algo.lr=1e-3", "init_optimizer=true"]
    child = tmp_path / "child"
    done = run_module("rlpipe", *common, f"hydra.run.dir={child}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (
        f"a new run from {finished_run} at 100 frames (ckpt_000000000100.pt): its networks "
        "(with any observation normaliser), optimizer state;" in done.stdout
    )
    assert RunDir(child).parent() == (finished_run, 100)
    bad = run_module(
        "rlpipe", *common, "algo.hidden_sizes=[8]", f"hydra.run.dir={tmp_path / 'x'}", cwd=tmp_path
    )
    assert bad.returncode == 2 and not (tmp_path / "x").exists()
    assert bad.stderr.strip().splitlines() == [
        f"rlpipe: error: init_from={finished_run}:100: this run's networks differ from the "
        "parent's in algo.hidden_sizes ([8] here, [128, 128] there); fine-tune with the "
        "parent's (algo.hidden_sizes=[128,128])"
    ]
